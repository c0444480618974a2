# Two commands set everything up on a fresh machine: `make demo` and `make test`.
# TORCH_SPEC is installed first; override it for a CUDA build, e.g.
#   make demo TORCH_SPEC="torch==2.13.0 --index-url https://download.pytorch.org/whl/cu126"
PYTHON ?= python3
VENV ?= .venv
TORCH_SPEC ?= torch==2.13.0
PIN_SPEC ?= gpytorch==1.15.2 linear-operator==0.6.1 pyro-ppl==1.9.2 botorch==0.18.1 \
            dask==2026.8.0 distributed==2026.8.0
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install demo test test-all lint bench bench-koh docs seed-math wheel-smoke clean

$(STAMP): pyproject.toml Makefile
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q $(TORCH_SPEC)
	$(BIN)/python -m pip install -q $(PIN_SPEC)
	$(BIN)/python -m pip install -q -e ".[dev]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/solderpyro demo --out runs/demo

test: $(STAMP)
	$(BIN)/python -m ruff check solderpyro tests benchmarks experiments
	$(BIN)/python -m mypy
	$(BIN)/python -m pytest -q

test-all: $(STAMP)
	$(BIN)/python -m pytest -q -m "slow or not slow"

lint: $(STAMP)
	$(BIN)/python -m ruff check solderpyro tests benchmarks experiments
	$(BIN)/python -m mypy

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_fe.py

bench-koh: $(STAMP)
	$(BIN)/python -m pip install -q -e ".[bench]"
	$(BIN)/python benchmarks/bench_koh.py

docs: $(STAMP)
	$(BIN)/python -m pip install -q -e ".[docs]"
	NO_MKDOCS_2_WARNING=1 $(BIN)/python -m mkdocs build --strict

# build the wheel, install it into a fresh environment outside the checkout (reusing .venv's
# dependencies) and run simulate and a short demo calibration from an empty directory
wheel-smoke: $(STAMP)
	.ci/wheel_smoke $(BIN)/python

seed-math: $(STAMP)
	$(BIN)/solderpyro example seed-math --out runs/seed-math

clean:
	rm -rf $(VENV) runs .pytest_cache build dist
