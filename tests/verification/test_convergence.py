"""Mesh and time-step convergence of V_A, V_B at the seed times (Liu 2008 constants).

The full study (mesh x0.5..x3, steps x0.5..x8) is benchmarks/convergence.py; its tables are in
docs/verification.md. Here: the default settings against one refined level (default suite) and
the two finest levels (slow).
"""

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from convergence import mesh_problem, time_problem  # noqa: E402

from solderpyro.fem.loading import SEED_TIMES  # noqa: E402
from solderpyro.fem.solver import SpecimenSolver  # noqa: E402
from solderpyro.params import anand_tensor  # noqa: E402


def V(problem):
    return SpecimenSolver(problem).solve(anand_tensor()[None], SEED_TIMES).V[0].reshape(-1)


def rel(a, b):
    return ((a - b).abs() / b.abs()).max().item()


def test_time_steps_default_within_half_percent_of_4x_finer():
    """SDIRK2 at the default grid vs 4x smaller steps: < 0.05 % (measured 3e-4 vs x8)."""
    a, b = V(time_problem(1.0)), V(time_problem(4.0))
    assert rel(a, b) < 5e-4
    assert (a - b).abs().max() < 0.002


def test_mesh_default_within_half_percent_of_2x_finer():
    """Default mesh vs 2x finer in every direction: < 0.5 % and < 0.01 um."""
    a, b = V(mesh_problem(1.0)), V(mesh_problem(2.0))
    assert rel(a, b) < 5e-3
    assert (a - b).abs().max() < 0.01


@pytest.mark.slow
def test_finest_two_mesh_levels_agree():
    """x2 vs x3: within 0.2 % or 0.005 um (measured 4e-4, 0.001 um); default within 0.5 %."""
    a, b, c = V(mesh_problem(1.0)), V(mesh_problem(2.0)), V(mesh_problem(3.0))
    assert rel(b, c) < 2e-3 or (b - c).abs().max() < 0.005
    assert rel(a, c) < 5e-3


@pytest.mark.slow
def test_finest_two_time_levels_agree_and_second_order():
    """x4 vs x8 within 0.2 %; the error falls by ~4x per halving (second order)."""
    v1, v2, v4, v8 = (V(time_problem(s)) for s in (1.0, 2.0, 4.0, 8.0))
    assert rel(v4, v8) < 2e-3
    e2, e4 = (v2 - v8).abs().max(), (v4 - v8).abs().max()
    assert e2 / e4 > 2.0
    assert torch.isfinite(v1).all()
