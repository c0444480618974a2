"""Contract tests of the batched FE solver: batch invariance, gradients, failure isolation."""

import dataclasses

import pytest
import torch

from solderpyro.fem.loading import ThermalCycle, TimeStepping
from solderpyro.fem.mesh import Layer, MeshSpec
from solderpyro.fem.problem import Problem
from solderpyro.fem.solver import SpecimenSolver
from solderpyro.params import anand_tensor

SHORT = ThermalCycle((0.0, 600.0, 1500.0), (25.0, 75.0, 75.0))
LAYERS = (Layer("copper", "copper", -4.0, 0.0, 4, 0.25, "top"),
          Layer("solder", "solder", 0.0, 0.5, 2),
          Layer("steel", "steel", 0.5, 4.5, 4, 0.25, "bottom"))
STEP = TimeStepping(dT_max=10.0, dwell_dt0=20.0, dt_max=450.0)


def small_problem(**kw):
    kw.setdefault("stepping", STEP)
    return Problem(layers=LAYERS, mesh=MeshSpec(nx=10), cycle=SHORT, **kw)


def params(rows):
    return torch.stack([anand_tensor(r) for r in rows])


ROWS = [{}, {"s0": 5.0, "QR": 7000.0, "xi": 5.0, "m": 0.05},
        {"s0": 25.0, "QR": 13000.0, "xi": 1.0, "m": 0.5}, {"s0": 9.0, "xi": 3.0, "m": 0.1}]


@pytest.mark.parametrize("plane", ["stress", "strain"])
def test_batch_invariance(plane):
    """Each member of a batch equals its single run to 1e-11 of max|V| (the stiffest members
    sub-step on their own, so the others' time grid is untouched)."""
    solver = SpecimenSolver(small_problem(plane=plane))
    p = params(ROWS)
    batch = solver.solve(p, [600.0, 1500.0]).V
    # a member's Newton iterations do not depend on its batch (converged members are
    # frozen), so batch and single runs differ by the rounding of the batched products
    # and solves (~1 ulp of max|V| measured); 1e-11 max|V| bounds it with room, while a
    # member that saw another's time grid would be off by its discretisation error
    for i in range(len(ROWS)):
        single = solver.solve(p[i:i + 1], [600.0, 1500.0]).V
        tol = 1e-11 * single.abs().max().item()
        assert torch.allclose(batch[i], single[0], rtol=0, atol=tol), (i, batch[i] - single[0])
    # the batch really differs between members (not a constant)
    assert (batch[0] - batch[1]).abs().max() > 0.05


def test_parameter_gradients_match_finite_differences():
    """d V / d (s0, QR, xi, m) through the FE (implicit-function correction) vs central FD."""
    solver = SpecimenSolver(small_problem())
    p = params([{"s0": 10.0, "xi": 2.0, "m": 0.2}]).requires_grad_(True)
    V = solver.solve(p, [600.0, 1500.0]).V.reshape(-1)
    cols = [0, 1, 3, 4]
    J = torch.stack([torch.autograd.grad(V[k], p, retain_graph=True)[0][0, cols]
                     for k in range(V.numel())])
    for j, c in enumerate(cols):
        h = 1e-6 * p[0, c].item()
        p1, p2 = p.detach().clone(), p.detach().clone()
        p1[0, c] += h
        p2[0, c] -= h
        fd = (solver.solve(p1, [600.0, 1500.0]).V - solver.solve(p2, [600.0, 1500.0]).V)
        fd = fd.reshape(-1) / (2 * h)
        assert torch.allclose(J[:, j], fd, rtol=1e-5, atol=1e-8 * fd.abs().max()), (c, J[:, j], fd)


def test_failed_member_is_flagged_and_isolated():
    """A member that cannot converge is reported with a reason, its outputs are NaN, and the
    others equal their own single runs."""
    tight = dataclasses.replace(STEP, max_iter=3, max_depth=1)
    solver = SpecimenSolver(small_problem(stepping=tight))
    elastic = {"A": 1e-30}  # converges in one Newton step
    stiff = {"s0": 5.0, "QR": 7000.0, "xi": 5.0, "m": 0.05}  # needs many iterations
    p = params([elastic, stiff, elastic])
    r = solver.solve(p, [600.0, 1500.0])
    assert r.ok.tolist() == [True, False, True]
    assert "no convergence" in r.reasons[1] and r.reasons[0] == ""
    assert torch.isnan(r.V[1]).all() and torch.isfinite(r.V[[0, 2]]).all()
    single = solver.solve(p[:1], [600.0, 1500.0]).V  # rounding only, as in the batch test
    assert torch.allclose(r.V[0], single[0], rtol=0, atol=1e-11 * single.abs().max().item())


def test_bad_params_raise():
    solver = SpecimenSolver(small_problem())
    with pytest.raises(ValueError, match=r"shape \(B, 9\)"):
        solver.solve(torch.ones(2, 4), [600.0])
    with pytest.raises(ValueError, match="NaN"):
        solver.solve(torch.full((1, 9), float("nan")), [600.0])
    with pytest.raises(ValueError, match="outside the cycle"):
        solver.solve(params([{}]), [2000.0])
