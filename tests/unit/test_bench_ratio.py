"""benchmarks/bench_koh.py reports a speed ratio only for a converged pair of runs."""

from __future__ import annotations

import importlib
import os
import sys
from pathlib import Path

import pytest


@pytest.fixture(scope="module")
def bench_koh():
    saved = dict(os.environ)  # the script sets its thread and XLA variables on import
    sys.path.insert(0, str(Path(__file__).parents[2] / "benchmarks"))
    try:
        yield importlib.import_module("bench_koh")
    finally:
        sys.path.remove(str(Path(__file__).parents[2] / "benchmarks"))
        os.environ.clear()
        os.environ.update(saved)


def _row(rhat: float, ess: float, seconds: float) -> dict:
    return dict(max_rhat=rhat, min_ess=ess, ess_per_s=ess / seconds)


def test_ratio_only_when_both_sides_converged(bench_koh) -> None:
    # the field_modular case at its defaults: neither side converged
    ratio, text = bench_koh.speed_ratio(_row(2.39, 5.0, 100.0), _row(1.74, 7.0, 600.0), 4)
    assert ratio is None and text.startswith("not converged: no ratio")
    assert "2.39 ours" in text and "1.74 NumPyro's" in text
    # one side unconverged (R-hat just above the bound, or too few effective draws): no ratio
    assert bench_koh.speed_ratio(_row(1.0, 900.0, 10.0), _row(1.012, 900.0, 20.0), 4)[0] is None
    assert bench_koh.speed_ratio(_row(1.0, 399.0, 10.0), _row(1.0, 900.0, 20.0), 4)[0] is None
    # both converged: ESS per second over ESS per second (90 / 45), printed as such
    ratio, text = bench_koh.speed_ratio(_row(1.005, 900.0, 10.0), _row(1.01, 900.0, 20.0), 4)
    assert ratio == pytest.approx(2.0, rel=1e-12) and text == "2.00x"
