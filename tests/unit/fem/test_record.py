"""The solder recorder's contracts (solderpyro.fem.record): the equivalent stresses, marks that
must lie on the time grid, and batch members that do not see each other."""

from __future__ import annotations

import math

import pytest
import torch

from solderpyro.fem.loading import ThermalCycle, TimeStepping
from solderpyro.fem.mesh import Layer, MeshSpec
from solderpyro.fem.problem import Problem
from solderpyro.fem.record import SolderRecorder, nearest_points, shear_xy, von_mises
from solderpyro.fem.solver import SpecimenSolver
from solderpyro.params import anand_tensor

F64 = dict(dtype=torch.float64)


def small_solver() -> SpecimenSolver:
    layers = (Layer("copper", "copper", -1.0, 0.0, 2, 0.5, "top"),
              Layer("solder", "solder", 0.0, 0.1, 2),
              Layer("steel", "steel", 0.1, 1.1, 2, 0.5, "bottom"))
    prob = Problem(layers=layers, half_length=5.0, mesh=MeshSpec(nx=8, x_grading=0.3),
                   cycle=ThermalCycle((0.0, 600.0, 1200.0, 1800.0), (25.0, 75.0, 75.0, 25.0)),
                   stepping=TimeStepping(dT_max=5.0, dwell_dt0=10.0, dt_max=120.0),
                   points={"A": (5.0, 1.1), "B": (5.0, -1.0)})
    return SpecimenSolver(prob)


def test_von_mises_and_shear_of_mandel_stresses():
    """Uniaxial s: von Mises s; pure shear tau (Mandel sqrt2 tau): sqrt(3) tau and tau."""
    s = torch.tensor([[7.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, math.sqrt(2.0) * 3.0]], **F64)
    assert von_mises(s).tolist() == pytest.approx([7.0, math.sqrt(3.0) * 3.0], rel=1e-14)
    assert shear_xy(s).tolist() == pytest.approx([0.0, 3.0], rel=1e-14)
    hydro = torch.tensor([5.0, 5.0, 5.0, 0.0], **F64)
    assert float(von_mises(hydro)) == pytest.approx(0.0, abs=1e-14)


def test_a_mark_off_the_time_grid_is_named():
    slv = small_solver()
    rec = SolderRecorder(marks=(600.0, 777.0))
    with pytest.raises(ValueError, match=r"\[777.0\] s are not on the solve's time grid"):
        slv.solve(anand_tensor(**F64)[None], [1800.0], recorder=rec)


def test_each_member_records_what_its_single_run_records():
    """A batch of two very different constant sets: each member's work, maxima and histories
    equal its single run's to 1e-10 of their size (batched linear algebra sums in another
    order)."""
    slv = small_solver()
    P = torch.stack([anand_tensor(**F64), anand_tensor({"s0": 20.0, "m": 0.3}, **F64)])
    pts = nearest_points(slv, [[4.9, 0.05], [0.1, 0.05]])
    marks = (600.0, 1800.0)
    both = slv.solve(P, [1800.0], recorder=SolderRecorder(marks, pts)).extra["solder"]
    assert both.work.shape == (2, 2, slv.n_s, 4) and both.sigma.shape[2:] == (2, 4)
    for i in range(2):
        one = slv.solve(P[i:i + 1], [1800.0],
                        recorder=SolderRecorder(marks, pts)).extra["solder"]
        for name in ("work", "eps_p_eq", "vm_max", "tau_max", "sigma", "eps_p"):
            a, b = getattr(both, name)[i], getattr(one, name)[0]
            assert torch.allclose(a, b, rtol=0, atol=1e-10 * float(b.abs().max())), name
    # creep during the heating and the dwell: work and inelastic strain grow between marks
    assert bool((both.work[:, 1].sum((1, 2)) > both.work[:, 0].sum((1, 2))).all())
    assert bool((both.eps_p_eq[:, 1] >= both.eps_p_eq[:, 0]).all())
