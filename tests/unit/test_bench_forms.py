"""benchmarks/forms.py: the diagnosis benchmarks' effects in forms other than the library's
load, stay inside the library's boxes, and differ from the library's physics where they
should (and only there)."""

from __future__ import annotations

import importlib
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from solderpyro.effects import EFFECTS
from solderpyro.effects.base import PreHistory
from solderpyro.fem.loading import ThermalCycle, TimeStepping
from solderpyro.fem.mesh import Layer, MeshSpec
from solderpyro.fem.problem import Problem
from solderpyro.fem.solver import SpecimenSolver
from solderpyro.params import anand_tensor

F64 = torch.float64
BENCH = str(Path(__file__).parents[2] / "benchmarks")


@pytest.fixture(scope="module")
def forms():
    sys.path.insert(0, BENCH)
    try:
        yield importlib.import_module("forms")
    finally:
        sys.path.remove(BENCH)


def test_every_form_loads_and_its_fixed_values_lie_in_the_library_box(forms):
    for name, (eff, lib, fixed) in forms.FORMS.items():
        assert lib in EFFECTS, name
        assert eff.name == lib, name  # "selected" means the diagnosis named this effect
        if fixed is not None:
            box = EFFECTS[lib].default_box()
            assert len(fixed) == box.dim, name
            assert all(lo <= v <= hi for v, lo, hi in
                       zip(fixed, box.lower, box.upper, strict=True)), name
    with pytest.raises(SystemExit, match="valid"):
        forms.form("no_such_form")


def test_newton_cooling_closed_form(forms):
    """The Newtonian cool-down runs from T_sf (s = 1) to the start (s = 0), monotonically,
    and its fastest rate (at its start) is ``peak_rate`` times the mean: the slope at s = 1
    from a central difference (h = 1e-6: error ~h^2 a^3 ~ 1e-11)."""
    ph = forms.NewtonCooling(7500.0, 125.0, 900.0)
    s = torch.linspace(0.0, 1.0, 101, dtype=F64)
    f = ph.fraction(s)
    assert f[0].item() == 0.0 and abs(f[-1].item() - 1.0) < 1e-15
    assert bool((f.diff() > 0).all())
    h = 1e-6
    t = torch.tensor([1.0 - h, 1.0 + h], dtype=F64)
    slope = (ph.fraction(t)[1] - ph.fraction(t)[0]).item() / (2 * h)
    assert abs(slope / ph.peak_rate - 1.0) < 1e-8
    assert ph.peak_rate == pytest.approx(3 * math.exp(3) / math.expm1(3), rel=1e-15)
    # the grid resolves the faster ramp: more steps than the library's constant rate
    ts = TimeStepping(dT_max=10.0, dwell_dt0=20.0, dt_max=450.0)
    assert len(ph.grid(ts)) > len(PreHistory(7500.0, 125.0, 900.0).grid(ts))


@pytest.mark.usefixtures("one_thread")
def test_newton_stress_free_is_the_library_where_physics_says_so_and_differs_with_creep(forms):
    """Elastic solder: any cool-down profile leaves V(t) - V(0) unchanged (superposition; the
    library's effect obeys the same to 1e-10 of max|V|). With creep the Newtonian cool-down
    relaxes a different share of the residual stress than the constant rate over the same
    time: the cycle's V differs, by a part of the effect's own size (neither nothing nor all
    of it; 4.9 % measured on this short cycle)."""
    layers = (Layer("copper", "copper", -4.0, 0.0, 4, 0.25, "top"),
              Layer("solder", "solder", 0.0, 0.5, 2),
              Layer("steel", "steel", 0.5, 4.5, 4, 0.25, "bottom"))
    prob = Problem(layers=layers, mesh=MeshSpec(nx=10),
                   stepping=TimeStepping(dT_max=10.0, dwell_dt0=20.0, dt_max=450.0),
                   cycle=ThermalCycle((0.0, 600.0, 1500.0), (25.0, 75.0, 75.0)))
    newton = SpecimenSolver(prob, effects=(forms.StressFreeNewton(),))
    linear = SpecimenSolver(prob, effects=("stress_free_temperature",))
    q = torch.tensor([[25.0, 1800.0], [150.0, 7500.0]], dtype=F64)
    times = [600.0, 1500.0]

    def rows(anand=None):
        return torch.cat([anand_tensor(anand, dtype=F64)[None].expand(2, -1), q], 1)

    Ve = newton.solve(rows({"A": 1e-30}), times).V
    Vn = newton.solve(rows(), times).V
    Vl = linear.solve(rows(), times).V
    assert (Ve[1] - Ve[0]).abs().max().item() < 1e-10 * Ve.abs().max().item()
    effect = (Vl[1] - Vl[0]).abs().max().item()
    differ = (Vn[1] - Vl[1]).abs().max().item()
    assert np.allclose(Vn[0].numpy(), Vl[0].numpy(), rtol=0, atol=1e-12 * effect)  # T_sf 25
    assert 0.02 * effect < differ < effect, (differ, effect)
