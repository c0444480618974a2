"""solderpyro.specimen.SpecimenModel as a torch module: reference values and gradients, its
buffers under ``.to``, inside another module, and the run-store path against the direct one."""

import numpy as np
import pytest
import torch

from solderpyro import SpecimenModel
from solderpyro.compute.runstore import RunStore
from solderpyro.fem.loading import SEED_TIMES, ThermalCycle, TimeStepping
from solderpyro.fem.mesh import Layer, MeshSpec
from solderpyro.fem.problem import Problem
from solderpyro.params import LIU2008, ParameterSpace
from solderpyro.specimen import StoreUse

F64 = torch.float64
LAYERS = (Layer("copper", "copper", -4.0, 0.0, 4, 0.25, "top"),
          Layer("solder", "solder", 0.0, 0.5, 2),
          Layer("steel", "steel", 0.5, 4.5, 4, 0.25, "bottom"))
TIMES = (600.0, 1500.0)

#: the reference case at the seed times, two parameter rows (s0, QR, xi, m): V (2, 4, 2) um
#: and the gradient of sum(W * V) with respect to theta, as the forward model gave them
#: before it became a torch module (float64, one thread)
THETA = [[12.9, 10586.0, 2.04, 0.2], [15.0, 9400.0, 1.5, 0.303]]
W = [[1.0, -0.5], [0.3, 2.0], [-1.2, 0.7], [0.4, 1.1]]
V_REF = [[[7.80860346201280642, 1.73427286950414516], [11.09262062023156759, 2.00406344954212878],
          [12.97533924169055375, 0.89902402146107940],
          [-5.63969153649103649, -5.52995687166319883]],
         [[7.74953787809781414, 1.67510734431555552], [10.37904464349266043, 1.30643795371963600],
          [10.32979705135219106, -1.71570710333158627],
          [-8.06001002202490646, -7.95880578356033741]]]
G_REF = [[5.14960095131062667e-01, 3.69818225093902124e-03, -3.76664635715453899e+00,
          -1.54825202984286729e+01],
         [2.93690863036293826e-01, 3.77502993508223132e-03, -3.10830687164959318e+00,
          -2.07420651830893803e+01]]


pytestmark = pytest.mark.usefixtures("one_thread")


def small_problem() -> Problem:
    return Problem(layers=LAYERS, mesh=MeshSpec(nx=10),
                   cycle=ThermalCycle((0.0, 600.0, 1500.0), (25.0, 75.0, 75.0)),
                   stepping=TimeStepping(dT_max=10.0, dwell_dt0=20.0, dt_max=450.0))


def test_reproduces_the_reference_values_and_gradients():
    """The same solve as before, to rounding: the solver rows are the same numbers (the
    defaults copied into the uncalibrated columns), so V and its gradient agree to ~1e-15
    relative; 1e-10 leaves room for another CPU's summation order."""
    model = SpecimenModel()
    assert model.times == SEED_TIMES
    theta = torch.tensor(THETA, dtype=F64, requires_grad=True)
    V = model(theta)
    (g,) = torch.autograd.grad((V * torch.tensor(W, dtype=F64)).sum(), theta)
    torch.testing.assert_close(V.detach(), torch.tensor(V_REF, dtype=F64), rtol=1e-10, atol=0)
    torch.testing.assert_close(g, torch.tensor(G_REF, dtype=F64), rtol=1e-10, atol=0)


def test_gradient_is_a_central_difference():
    """d sum(w V) / d theta by autograd against central differences with steps h = 1e-3 of
    each parameter's box width L: the truncation error ~ (h / L)^2 |f| / L (measured 2.5e-6
    relative on the reference case) and the solver's noise (Newton rtol 1e-10 of V) / h are
    both far below the tolerance, 1e-4 of the derivative plus 1e-4 of the output's size per
    box width."""
    model = SpecimenModel(small_problem(), times=TIMES)
    space = model.space
    theta0 = torch.tensor([12.9, 10586.0, 2.04, 0.2], dtype=F64)
    w = torch.tensor([[1.0, -0.5], [0.3, 2.0]], dtype=F64)
    th = theta0[None].clone().requires_grad_(True)
    V0 = model(th)
    (g,) = torch.autograd.grad((V0 * w).sum(), th)
    L = torch.tensor(space.upper, dtype=F64) - torch.tensor(space.lower, dtype=F64)
    h = 1e-3 * L
    rows = theta0.repeat(8, 1)
    for j in range(4):
        rows[2 * j, j] += h[j]
        rows[2 * j + 1, j] -= h[j]
    with torch.no_grad():
        f = (model(rows) * w).sum((1, 2))
    fd = (f[0::2] - f[1::2]) / (2 * h)
    size = float((w.abs() * V0.detach().abs()).sum())
    tol = 1e-4 * (g[0].abs() + size / L)
    assert torch.all((fd - g[0]).abs() <= tol), (fd, g[0], tol)


def test_buffers_move_with_to_and_come_back_exactly():
    model = SpecimenModel(small_problem(), times=TIMES, effects=("moire_rigid_motion",))
    names = dict(model.named_buffers())
    assert {"anand_defaults", "x_out", "anand_cols", "fe_cols", "obs_cols", "obs_time",
            "obs_out"} <= set(names)
    before = {k: v.clone() for k, v in names.items()}
    model.to(dtype=torch.float32)
    assert model.dtype == torch.float32 and model.anand_defaults.dtype == torch.float32
    assert model.x_out.dtype == torch.float32 and model.fe_cols.dtype == torch.long
    assert model.solver.tkw["dtype"] == torch.float32  # the solver follows the module
    model.to(dtype=F64)
    for k, v in model.named_buffers():  # A = 5.87e6 1/s would not survive float32 otherwise
        assert v.dtype == before[k].dtype and torch.equal(v, before[k]), k
    assert model.solver.tkw["dtype"] == F64
    assert float(model.anand_defaults[2]) == LIU2008["A"]


def test_composes_inside_another_module():
    """A module that holds the parameters in the unit box and calls the model: the model's
    buffers are the outer module's, ``.to`` reaches them, and the gradient reaches the outer
    parameter through the FE (chain rule through the box's map: d theta / d u = L)."""
    space = ParameterSpace.seed()

    class Outer(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.model = SpecimenModel(small_problem(), space, TIMES)
            self.u = torch.nn.Parameter(torch.tensor([[0.4, 0.6, 0.3, 0.2]], dtype=F64))

        def forward(self) -> torch.Tensor:
            return self.model(space.from_unit(self.u))

    outer = Outer()
    assert "model.anand_defaults" in outer.state_dict()
    outer.to(dtype=torch.float32)
    assert outer.model.anand_defaults.dtype == torch.float32
    outer.to(dtype=F64)
    V = outer()
    V[:, -1, 0].sum().backward()
    assert outer.u.grad is not None and torch.isfinite(outer.u.grad).all()
    theta = space.from_unit(outer.u.detach()).requires_grad_(True)
    alone = SpecimenModel(small_problem(), space, TIMES)
    (g,) = torch.autograd.grad(alone(theta)[:, -1, 0].sum(), theta)
    L = torch.tensor(space.upper, dtype=F64) - torch.tensor(space.lower, dtype=F64)
    torch.testing.assert_close(outer.u.grad, g * L, rtol=1e-10, atol=0)


def test_store_path_equals_the_direct_one_and_reuses_runs(tmp_path):
    """Observed outputs through the run store equal the direct (differentiable) solve's; a
    second call reads every run back; rows differing only in the Moire offsets are one run;
    the offsets are added after the FE as ``c_k + 1e-3 w_k (x - x_O)`` at each observation."""
    model = SpecimenModel(small_problem(), times=TIMES,
                          effects=("thermal_lag", "moire_rigid_motion"))
    ti, oi = np.array([0, 0, 1, 1, 1]), np.array([0, 1, 0, 1, 1])
    model.set_observations(ti, oi)
    # s0, QR, xi, m, tau, split, then c_1, c_2 (um), w_1, w_2 (urad) of the two images
    base = [12.9, 10586.0, 2.04, 0.2, 30.0, 0.2, 0.0, 0.0, 0.0, 0.0]
    moved = [12.9, 10586.0, 2.04, 0.2, 30.0, 0.2, 0.3, -0.2, 20.0, -10.0]
    theta = torch.tensor([base, moved], dtype=F64)
    direct = model.observed(theta).detach()
    model.use_store(StoreUse(RunStore(tmp_path / "store"), batch=4))
    V, ok = model.observed_runs(theta)
    assert ok.all() and V.shape == (2, 5)
    scale = float(direct.abs().max())
    torch.testing.assert_close(V, direct, rtol=0, atol=1e-12 * scale)
    t = model.tally
    assert (t.n_rows, t.n_computed, t.n_reused, t.n_ok) == (2, 1, 0, 2)  # one FE run
    V2, _ = model.observed_runs(theta)
    assert (t.n_computed, t.n_reused) == (1, 2) and torch.equal(V2, V)
    # the FE-side outputs (what a surrogate learns) and the offsets added after them
    Vfe, _ = model.fe_observed_runs(theta[:, :6])
    x = model.x_out[torch.as_tensor(oi)]
    q = theta[1, 6:]
    c, w = q[torch.as_tensor(ti)], q[2 + torch.as_tensor(ti)]
    off = c + 1e-3 * w * (x - model.problem.origin[0])
    torch.testing.assert_close(model.offset(q), off, rtol=0, atol=1e-15)
    torch.testing.assert_close(V[1] - Vfe[1], off, rtol=0, atol=1e-12 * scale)
    torch.testing.assert_close(V[0], Vfe[0], rtol=0, atol=0)


def test_bad_input_names_the_field(tmp_path):
    model = SpecimenModel(small_problem(), times=TIMES, effects=("thermal_lag",))
    with pytest.raises(ValueError, match=r"shape \(B, 6\) for s0, QR, xi, m, tau, split"):
        model(torch.ones(1, 4, dtype=F64))
    with pytest.raises(ValueError, match=r"shape \(n, 6\)"):
        model.runs(torch.ones(1, 3, dtype=F64))
    with pytest.raises(ValueError, match="no observation index"):
        model.observed(torch.tensor([[12.9, 10586.0, 2.04, 0.2, 30.0, 0.0]], dtype=F64))
    with pytest.raises(ValueError, match="outside"):
        model.set_observations([0, 2], [0, 0])
    with pytest.raises(ValueError, match="StoreUse.batch"):
        StoreUse(RunStore(tmp_path / "store"), batch=0)
