"""The ``koh`` command's computation (solderpyro.calibration.tables): its CSV reader, the
convergence check after sampling and the run directory's index page."""

from __future__ import annotations

import logging
import re

import numpy as np
import pytest

from solderpyro.calibration.tables import (
    MAX_RHAT,
    MIN_ESS_PER_CHAIN,
    RunTables,
    convergence_problems,
    koh_from_tables,
    read_columns,
)
from solderpyro.config.settings import SamplerSettings


def test_read_columns_binary_file_names_it(tmp_path):
    p = tmp_path / "sim.csv"
    p.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x01\xfe")
    with pytest.raises(ValueError, match=re.escape(f"SIM file {p}: not a text file (byte 0x89 "
                                                   "at offset 0 is not UTF-8)")):
        read_columns(p, ["x"], "SIM")


def test_read_columns_skips_a_bom_and_comments(tmp_path):
    p = tmp_path / "sim.csv"
    p.write_bytes(b"\xef\xbb\xbfx,y\r\n# a note\r\n1,2\r\n3,4\r\n")
    assert read_columns(p, ["y", "x"], "SIM").tolist() == [[2.0, 1.0], [4.0, 3.0]]


def test_convergence_bars_are_the_specimen_calibrations():
    assert MAX_RHAT == SamplerSettings.max_rhat == 1.01
    assert MIN_ESS_PER_CHAIN * SamplerSettings.chains == SamplerSettings.min_ess
    assert MIN_ESS_PER_CHAIN == 100


def _row(name, rhat, ess):
    return {"parameter": name, "r_hat": rhat, "ess_bulk": ess}


def test_convergence_problems():
    assert convergence_problems([_row("t", 1.005, 900.0), _row("sigma", 1.0, 401.0)], 4) == []
    split, short = convergence_problems([_row("t", 1.53, 7.0), _row("sigma", 1.0, 500.0)], 4)
    assert "R-hat t 1.530 > 1.01" in split and "sigma" not in split
    assert "bulk ESS t 7 < 400 (100 per chain x 4 chains)" in short
    # the bar scales with the chains; one chain has no R-hat: said, not taken as converged
    assert convergence_problems([_row("t", 1.0, 250.0)], 2) == []
    (msg,) = convergence_problems([_row("t", float("nan"), 150.0)], 1)
    assert "no R-hat for t (1 chain(s))" in msg


def test_koh_warns_on_unconverged_chains_and_writes_an_index(tmp_path, caplog):
    """Two short chains (30 draws each) cannot reach 100 bulk ESS per chain: a warning in the
    log and on index.html, which links every output of the run."""
    rng = np.random.default_rng(0)
    x, t = np.meshgrid(np.linspace(0, 3, 5), np.linspace(0.2, 1.5, 5))
    x, t = x.ravel(), t.ravel()
    np.savetxt(tmp_path / "sim.csv", np.c_[x, t, 5 * np.exp(-t * x)], delimiter=",",
               header="x,t,y", comments="")
    xo = np.arange(6) * 0.5
    np.savetxt(tmp_path / "obs.csv", np.c_[xo, 5 * np.exp(-0.7 * xo)
                                           + 0.2 * rng.standard_normal(6)],
               delimiter=",", header="x,y", comments="")
    out = tmp_path / "out"
    with caplog.at_level(logging.WARNING, logger="solderpyro"):
        koh_from_tables(RunTables(tmp_path / "sim.csv", tmp_path / "obs.csv", ["x"], ["t"], "y"),
                        out, chains=2, warmup=30, draws=30, seed=1, progress=False)
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any("too few effective draws" in w and "< 200" in w for w in warned), warned
    page = (out / "index.html").read_text()
    assert "have not converged" in page and "too few effective draws" in page
    assert "holds no solderpyro run" not in page
    for f in ("summary.csv", "posterior.nc", "traces.png"):
        assert (out / f).is_file() and f'href="{f}"' in page
    assert '<img src="traces.png"' in page
