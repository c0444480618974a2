"""Armstrong-Frederick recovery of the back stress at the material point (the lagged scheme of
solderpyro.materials.kinematic): gamma_k = 0 is Prager bit for bit and C_k = 0 the isotropic
update whatever gamma_k (torch and native paths), the step is the Prager return on
(a X_n, a C_k), the native and torch paths agree, derivatives with respect to gamma_k and the
lagged rate against finite differences, and the optional p_rate field of PointState."""

import pytest
import torch

from solderpyro import _native
from solderpyro.materials.integrate import (
    PointInputs,
    PointState,
    Tangent3D,
    anand_update,
    initial_state,
    lagged_prager,
    return_map_3d,
)
from solderpyro.params import anand_tensor

F64 = torch.float64
EPS = torch.tensor([[2e-4, -1e-4, 8e-4], [-5e-4, 3e-4, -2e-3], [1e-3, 1e-3, 1e-6]],
                   dtype=F64)  # module level: created before the float64 fixture
X_N = torch.tensor([[3.0, -1.0, -2.0, 4.0], [-6.0, 2.0, 4.0, -9.0], [1.0, 1.0, -2.0, 0.5]],
                   dtype=F64)  # deviatoric start-of-step back stresses, MPa
RATE = torch.tensor([2e-6, 5e-5, 1e-4], dtype=F64)  # lagged rates, 1/s
E, NU = 32000.0, 0.35
PATHS = ["torch", "native"]


def _path(monkeypatch, path):
    """Select the update's code path (the native one needs the compiled kernels)."""
    if path == "native":
        monkeypatch.delenv("SOLDERPYRO_NATIVE", raising=False)
        if _native.library() is None:
            pytest.skip("no native kernels (no C compiler)")
    else:
        monkeypatch.setenv("SOLDERPYRO_NATIVE", "0")


def _state(p, X=X_N, rate=RATE):
    s0 = p[0] * torch.tensor([1.0, 0.8, 1.3], dtype=F64)
    return PointState(torch.tensor([[1e-4, -3e-4, 2e-4, 1e-4]] * 3, dtype=F64), s0,
                      torch.zeros(3, dtype=F64), X, rate)


def _inputs(dt, Ck=None, gk=None):
    """The step's conditions at 360 K with the thermal strain 2e-4."""
    return PointInputs(360.0, dt, 2e-4, E, NU, Ck, gk)


def _fields(out):
    sig, st, C, dep, x = out
    return [sig, st.eps_p, st.s, st.eps_zz, st.X, dep, x] + ([] if C is None else [C])


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("plane", ["stress", "strain"])
@pytest.mark.parametrize("dt", [0.5, 300.0])
def test_zero_recovery_is_prager_bit_for_bit(monkeypatch, path, plane, dt):
    """gamma_k = 0 (a zero tensor per point, a plain 0, None) gives the Prager update to the
    last bit (a = 1/(1 + 0) = 1 exactly): stress, state, back stress, tangent, dep, warm start.
    The new state carries p_rate = dep/dt whenever gamma_k or the start's p_rate is given."""
    _path(monkeypatch, path)
    p = anand_tensor({}, dtype=F64)
    Ck = torch.tensor([3000.0, 500.0, 12000.0], dtype=F64)
    ref = anand_update(EPS, _state(p, rate=None), p, _inputs(dt, Ck), plane)
    assert ref[1].p_rate is None
    for gk, rate in [(torch.zeros(3, dtype=F64), RATE), (0.0, RATE), (None, RATE),
                     (torch.zeros(3, dtype=F64), None)]:
        out = anand_update(EPS, _state(p, rate=rate), p, _inputs(dt, Ck, gk), plane)
        for a, b in zip(_fields(ref), _fields(out), strict=True):
            assert torch.equal(a, b)
        assert torch.equal(out[1].p_rate, out[3] / dt)


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("plane", ["stress", "strain"])
def test_zero_modulus_ignores_the_recovery(monkeypatch, path, plane):
    """C_k = 0 with any gamma_k is the isotropic update (C_k None, no back stress) to the last
    bit, and the back stress stays exactly zero."""
    _path(monkeypatch, path)
    p = anand_tensor({}, dtype=F64)
    ref = anand_update(EPS, _state(p, X=None, rate=None), p, _inputs(20.0), plane)
    for Ck, gk in [(torch.zeros(3, dtype=F64), torch.tensor([50.0, 200.0, 1e3], dtype=F64)),
                   (0.0, 100.0)]:
        out = anand_update(EPS, _state(p, X=torch.zeros(3, 4, dtype=F64)), p,
                           _inputs(20.0, Ck, gk), plane)
        for a, b in zip(_fields(ref), _fields(out), strict=True):
            if a is not None:
                assert torch.equal(a, b)
        assert torch.equal(out[1].X, torch.zeros(3, 4, dtype=F64))


@pytest.mark.parametrize("path", PATHS)
def test_step_is_the_prager_return_on_scaled_inputs(monkeypatch, path):
    """The step with recovery is the Prager step from (a X_n, a C_k), a = 1/(1 + gamma_k
    p_rate dt), bit for bit (the documented scheme); its back stress is the backward-Euler
    Armstrong-Frederick X = X_n + (2/3) C_k deps_p - gamma_k X Dp_lag (to 1e-12 relative: one
    rearrangement of the same operations), and the new lagged rate is its dep/dt."""
    _path(monkeypatch, path)
    p = anand_tensor({"s0": 25.0, "m": 0.5}, dtype=F64)
    Ck = torch.tensor([3000.0, 500.0, 12000.0], dtype=F64)
    gk = torch.tensor([50.0, 200.0, 120.0], dtype=F64)
    dt = 30.0
    out = anand_update(EPS, _state(p), p, _inputs(dt, Ck, gk), "stress")
    st1, dep = out[1], out[3]
    a = 1.0 / (1.0 + gk * RATE * dt)
    ref = anand_update(EPS, _state(p, X=a[:, None] * X_N, rate=None), p, _inputs(dt, a * Ck),
                       "stress")
    for x, y in zip(_fields(ref), _fields(out), strict=True):
        assert torch.equal(x, y)
    deps = st1.eps_p - _state(p).eps_p
    be = (X_N + 2.0 / 3.0 * Ck[:, None] * deps) / (1.0 + gk * RATE * dt)[:, None]
    assert torch.allclose(st1.X, be, rtol=1e-12, atol=1e-12 * be.abs().max())
    assert torch.equal(st1.p_rate, dep / dt)
    assert (a < 1).all() and (1 - a).min() > 1e-3  # the recovery acts


def test_lagged_prager_passes_inputs_untouched_without_recovery():
    """No multiplication where there is nothing to recover: gamma_k None / plain 0, C_k None /
    plain 0, or the virgin state (p_rate None) return the very X and C_k objects."""
    p = anand_tensor({}, dtype=F64)
    Ck = torch.tensor([3000.0, 500.0, 12000.0], dtype=F64)
    for st, inp, carry in [(_state(p), _inputs(1.0, Ck), True),
                           (_state(p, rate=None), _inputs(1.0, Ck, 0.0), False),
                           (_state(p, rate=None), _inputs(1.0, Ck, 50.0), True),
                           (_state(p), _inputs(1.0, None, 50.0), True),
                           (_state(p), _inputs(1.0, 0.0, 50.0), True)]:
        st2, inp2, c = lagged_prager(st, inp)
        assert st2.X is st.X and inp2.C_k is inp.C_k and inp2.gamma_k is None and c == carry


@pytest.mark.parametrize("warm", [False, True])
@pytest.mark.parametrize("n", [3, 4099])
def test_native_matches_torch_with_recovery(monkeypatch, warm, n):
    """Random states, strains and constants with back stress and recovery (gamma_k up to
    400, lagged rates up to 1e-3/s, steps 0.1-100 s: a from ~0.03 to 1): the native update
    equals the torch path to 1e-12 relative (the tolerance of the Prager native-vs-torch
    test: the same algorithm on the same scaled inputs, different rounding), fields, factored
    tangent, dep and p_rate; 4099 points: the 4-lane loop and its scalar tail."""
    _path(monkeypatch, "native")
    g = torch.Generator().manual_seed(n + 11)
    r = lambda *s: torch.rand(*s, generator=g, dtype=F64)  # noqa: E731
    p = anand_tensor({}, dtype=F64).repeat(n, 1)
    p[:, 0] = 5 + 20 * r(n)
    p[:, 1] = 7000 + 6000 * r(n)
    p[:, 4] = 0.05 + 0.45 * r(n)
    eps = (r(n, 4) - 0.5) * 10 ** (-1.5 - 3 * r(n, 1))
    X = (r(n, 4) - 0.5) * 10
    X = X - X[:, :3].sum(-1, keepdim=True) / 3 * torch.tensor([1.0, 1.0, 1.0, 0.0], dtype=F64)
    st = PointState((r(n, 4) - 0.5) * 1e-3, p[:, 0] * (0.5 + r(n)), torch.zeros(n, dtype=F64),
                    X, 1e-3 * r(n))
    inputs = PointInputs(298 + 100 * r(n), 10 ** (3 * r(n) - 1), 2e-4, 32000.0, 0.35,
                         2000 * r(n), 400 * r(n))
    guess = None
    if warm:
        x0 = return_map_3d(eps, st, p, inputs, tangent=False)[4]
        guess = x0 * (1 + 1e-3 * torch.randn(x0.shape, generator=g, dtype=F64))
    nat = return_map_3d(eps, st, p, inputs, guess=guess, tangent="factored")
    monkeypatch.setenv("SOLDERPYRO_NATIVE", "0")
    ref = return_map_3d(eps, st, p, inputs, guess=guess, tangent="factored")
    for a, b in zip(_fields(nat) + [nat[1].p_rate], _fields(ref) + [ref[1].p_rate],
                    strict=True):
        if isinstance(a, Tangent3D):
            for f in ("K", "g2", "coef", "nb"):
                x, y = torch.broadcast_to(getattr(a, f), getattr(b, f).shape), getattr(b, f)
                assert (x - y).abs().max() <= 1e-12 * y.abs().max()
            continue
        assert (a - b).abs().max() <= 1e-12 * b.abs().max().clamp_min(1e-300)
    assert (nat[1].p_rate / ref[1].p_rate - 1).abs().max() <= 1e-12


def _outputs(gk, rate, p, Ck, plane="stress"):
    sig, st, _, _, _ = anand_update(EPS, _state(p, rate=rate), p, _inputs(20.0, Ck, gk), plane,
                                    tangent=False)
    return torch.cat([sig.reshape(-1), st.s, st.eps_p.reshape(-1) * 1e4, st.X.reshape(-1),
                      st.p_rate * 1e6])


@pytest.mark.parametrize("gk0", [0.0, 150.0])
@pytest.mark.parametrize("plane", ["stress", "strain"])
def test_gradients_wrt_recovery_and_lagged_rate_match_fd(gk0, plane):
    """d(sigma, s, eps_p, X, p_rate)/d(gamma_k) and d(...)/d(p_rate) through the implicit
    correction and the factor a, at gamma_k = 0 (Prager) and inside the box, vs central
    differences: h = 1e-3 in gamma_k and 1e-9 /s in p_rate (relative changes of a ~1e-8:
    truncation ~1e-12, rounding ~1e-9 relative)."""
    p = anand_tensor({}, dtype=F64)
    Ck = torch.tensor([3000.0, 500.0, 12000.0], dtype=F64)
    gk = torch.full((3,), gk0, dtype=F64)
    J = torch.autograd.functional.jacobian(lambda g: _outputs(g, RATE, p, Ck, plane), gk)
    JR = torch.autograd.functional.jacobian(lambda r: _outputs(gk, r, p, Ck, plane), RATE)
    assert J.abs().max() > 0 and (gk0 == 0.0 or JR.abs().max() > 0)
    for j in range(3):
        for jac, x0, h, f in [(J, gk, 1e-3, lambda x: _outputs(x, RATE, p, Ck, plane)),
                              (JR, RATE, 1e-9, lambda x: _outputs(gk, x, p, Ck, plane))]:
            x1, x2 = x0.clone(), x0.clone()
            x1[j] += h
            x2[j] -= h
            fd = (f(x1) - f(x2)) / (2 * h)
            assert torch.allclose(jac[:, j], fd, rtol=1e-5, atol=1e-6 * fd.abs().max() + 1e-12)


def test_point_state_lagged_rate_field():
    """p_rate is optional (the positional four-field PointState still works) and follows
    index/detach; initial_state(recovery=True) gives zeros."""
    p = anand_tensor({}, dtype=F64)
    st = PointState(torch.zeros(3, 4), p[0].expand(3).clone(), torch.zeros(3), X_N)
    assert st.p_rate is None and st.index([0, 2]).p_rate is None and st.detach().p_rate is None
    k = initial_state((2, 3), p[0], kinematic=True, recovery=True)
    assert k.p_rate.shape == (2, 3) and not k.p_rate.any() and k.index(1).p_rate.shape == (3,)
    assert initial_state((2, 3), p[0], kinematic=True).p_rate is None
    r = RATE.clone().requires_grad_()
    assert not _state(p, rate=r).detach().p_rate.requires_grad
