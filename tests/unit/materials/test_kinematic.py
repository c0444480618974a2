"""Prager kinematic hardening at the material point: C_k = 0 is the isotropic update bit for bit,
consistent tangent and derivatives (C_k, Anand constants, back stress) vs finite differences,
batch broadcasting of C_k, and the optional back-stress field of PointState."""

import pytest
import torch

from solderpyro.materials.integrate import (
    PointInputs,
    PointState,
    anand_update,
    initial_state,
    return_map_3d,
)
from solderpyro.materials.kinematic import equivalent
from solderpyro.params import anand_tensor

CASES = [{}, {"s0": 5.0, "QR": 7000.0, "xi": 5.0, "m": 0.05}, {"s0": 25.0, "m": 0.5},
         {"a": 0.8}]
EPS = torch.tensor([[2e-4, -1e-4, 8e-4], [-5e-4, 3e-4, -2e-3], [1e-3, 1e-3, 1e-6]],
                   dtype=torch.float64)  # module level: created before the float64 fixture
X_N = torch.tensor([[3.0, -1.0, -2.0, 4.0], [-6.0, 2.0, 4.0, -9.0], [1.0, 1.0, -2.0, 0.5]],
                   dtype=torch.float64)  # deviatoric start-of-step back stresses, MPa
E, NU = 32000.0, 0.35


def _state(p, X=None):
    st = initial_state((3,), p[0])
    return PointState(torch.tensor([[1e-4, -3e-4, 2e-4, 1e-4]] * 3), st.s * torch.tensor(
        [1.0, 0.8, 1.3]), torch.zeros(3), X)


def _inputs(dt, Ck=None):
    """The step's conditions at 360 K with the thermal strain 2e-4."""
    return PointInputs(360.0, dt, 2e-4, E, NU, Ck)


def _fields(out):
    sig, st, C, dep, x = out
    return [sig, st.eps_p, st.s, st.eps_zz, dep, x] + ([] if C is None else [C])


@pytest.mark.parametrize("vals", CASES)
@pytest.mark.parametrize("plane", ["stress", "strain"])
@pytest.mark.parametrize("dt", [0.5, 300.0])
def test_zero_modulus_is_bit_exact(vals, plane, dt):
    """(a) C_k = 0 (scalar tensor, or per point with a zero back stress) gives the isotropic
    update (C_k = None, the code path of the model without back stress) to the last bit:
    stress, state, tangent, dep, warm start; and the new back stress is exactly zero."""
    p = anand_tensor(vals)
    ref = anand_update(EPS, _state(p), p, _inputs(dt), plane)
    for Ck, X in [(torch.tensor(0.0), None), (torch.zeros(3), torch.zeros(3, 4))]:
        out = anand_update(EPS, _state(p, X), p, _inputs(dt, Ck), plane)
        for a, b in zip(_fields(ref), _fields(out), strict=True):
            assert torch.equal(a, b)
        assert ref[1].X is None and torch.equal(out[1].X, torch.zeros(3, 4))


def test_zero_modulus_gradient_is_bit_exact():
    """(a) d(sigma, s)/d(Anand constants) at C_k = 0 equal those of the isotropic update."""
    p0 = anand_tensor({})

    def grad(Ck=None):
        p = p0.clone().requires_grad_()
        sig, st, *_ = anand_update(EPS, _state(p0), p, _inputs(20.0, Ck))
        return torch.autograd.grad(sig.sum() + st.s.sum(), p)[0]

    assert torch.equal(grad(), grad(torch.tensor(0.0, requires_grad=True)))


@pytest.mark.parametrize("vals", CASES)
@pytest.mark.parametrize("plane", ["stress", "strain"])
@pytest.mark.parametrize("dt", [0.5, 300.0])
@pytest.mark.parametrize("Ck", [2000.0, 20000.0])
def test_kinematic_tangent_matches_fd(vals, plane, dt, Ck):
    """(d) Consistent in-plane tangent with back stress (non-zero X_n, not collinear with the
    trial deviator) vs central differences, rel 1e-6 as for the isotropic tangent."""
    p = anand_tensor(vals)
    args = (_state(p, X_N), p, _inputs(dt, Ck), plane)
    sig, st, C, _, _ = anand_update(EPS, *args)
    if plane == "stress":
        assert sig[:, 2].abs().max() < 1e-7  # sigma_zz = 0 enforced
    h = 1e-7
    for j in range(3):
        e1, e2 = EPS.clone(), EPS.clone()
        e1[:, j] += h
        e2[:, j] -= h
        fd = (anand_update(e1, *args)[0] - anand_update(e2, *args)[0])
        fd = fd[:, [0, 1, 3]] / (2 * h)
        assert torch.allclose(C[:, :, j], fd, rtol=1e-6, atol=1e-6 * fd.abs().max())


def _outputs(Ck, p, X, plane="stress"):
    sig, st, _, _, _ = anand_update(EPS, _state(p, X), p, _inputs(20.0, Ck), plane,
                                    tangent=False)
    return torch.cat([sig.reshape(-1), st.s, st.eps_p.reshape(-1) * 1e4, st.X.reshape(-1)])


@pytest.mark.parametrize("Ck0", [0.0, 5000.0])
@pytest.mark.parametrize("plane", ["stress", "strain"])
def test_gradient_wrt_Ck_matches_fd(Ck0, plane):
    """(d) d(sigma, s, eps_p, X)/dC_k (one C_k per point) through the implicit correction, at
    C_k = 0 (the isotropic limit) and at an interior value, vs central differences with
    h = 1 MPa (<= 1e-4 of 3G + C_k: truncation ~1e-8, rounding ~1e-13 relative)."""
    p = anand_tensor({})
    Ck = torch.full((3,), Ck0)
    J = torch.autograd.functional.jacobian(lambda c: _outputs(c, p, X_N, plane), Ck)
    assert J.abs().max() > 0
    for j in range(3):
        c1, c2 = Ck.clone(), Ck.clone()
        c1[j] += 1.0
        c2[j] -= 1.0
        fd = (_outputs(c1, p, X_N, plane) - _outputs(c2, p, X_N, plane)) / 2.0
        assert torch.allclose(J[:, j], fd, rtol=1e-6, atol=1e-7 * fd.abs().max())


def test_gradient_wrt_constants_and_back_stress_matches_fd():
    """(d) d(outputs)/d(Anand constants) and d(outputs)/d(X_n) with C_k > 0 vs central
    differences (relative step 1e-6 for the constants, 1e-4 MPa for X_n)."""
    p0 = anand_tensor({"s0": 25.0, "m": 0.5})
    Ck = torch.tensor([3000.0, 500.0, 12000.0])
    J = torch.autograd.functional.jacobian(lambda p: _outputs(Ck, p, X_N), p0)
    for j in range(9):
        h = 1e-6 * p0[j].abs().item()
        p1, p2 = p0.clone(), p0.clone()
        p1[j] += h
        p2[j] -= h
        fd = (_outputs(Ck, p1, X_N) - _outputs(Ck, p2, X_N)) / (2 * h)
        assert torch.allclose(J[:, j], fd, rtol=1e-5, atol=1e-7 * (fd.abs().max() + 1e-12))
    JX = torch.autograd.functional.jacobian(lambda X: _outputs(Ck, p0, X), X_N)
    for i, k in [(0, 0), (1, 3), (2, 2)]:
        X1, X2 = X_N.clone(), X_N.clone()
        X1[i, k] += 1e-4
        X2[i, k] -= 1e-4
        fd = (_outputs(Ck, p0, X1) - _outputs(Ck, p0, X2)) / 2e-4
        assert torch.allclose(JX[:, i, k], fd, rtol=1e-5, atol=1e-7 * fd.abs().max())


def test_batch_broadcast_of_Ck():
    """C_k of shape (b, 1, 1) for points (b, n_e, n_qp), as in the FE solver: every member
    equals a call with its scalar C_k (to 1e-12 MPa)."""
    p = torch.stack([anand_tensor({}), anand_tensor({"m": 0.1})])[:, None, None, :]  # (2,1,1,9)
    Ck = torch.tensor([1500.0, 9000.0])[:, None, None]  # (2, 1, 1)
    eps = torch.stack([EPS, 0.5 * EPS])[None].expand(2, 2, 3, 3)  # (2, 2, 3, 3)
    st = initial_state((2, 2, 3), p[..., 0], kinematic=True)
    sig, st1, C, _, _ = anand_update(eps, st, p, _inputs(10.0, Ck))
    assert st1.X.shape == (2, 2, 3, 4) and C.shape == (2, 2, 3, 3, 3)
    for i in range(2):
        s1, st2, C1, _, _ = anand_update(eps[i], initial_state((2, 3), p[i, 0, 0, 0]),
                                         p[i, 0, 0], _inputs(10.0, Ck[i].item()))
        assert torch.allclose(sig[i], s1, rtol=0, atol=1e-12)
        assert torch.allclose(st1.X[i], st2.X, rtol=0, atol=1e-12)
        assert torch.allclose(C[i], C1, rtol=1e-12, atol=1e-9)


def test_point_state_back_stress_field():
    """X is optional (positional three-field PointState still works), follows index/detach,
    stays deviatoric, and X = X_n + (2/3) C_k deps_p; with C_k None a given X_n is carried."""
    p = anand_tensor({})
    st = PointState(torch.zeros(3, 4), p[0].expand(3).clone(), torch.zeros(3))
    assert st.X is None and st.index([0, 2]).X is None and st.detach().X is None
    k = initial_state((2, 3), p[0], kinematic=True)
    assert k.X.shape == (2, 3, 4) and k.index(1).X.shape == (3, 4)
    Xg = X_N.clone().requires_grad_()
    assert not _state(p, Xg).detach().X.requires_grad
    eps = torch.cat([EPS[:, :2], torch.zeros(3, 1), EPS[:, 2:]], -1)
    Ck = 4000.0
    sig, st1, _, dep, _ = return_map_3d(eps, _state(p, X_N), p, _inputs(30.0, Ck))
    deps = st1.eps_p - _state(p).eps_p
    assert torch.allclose(st1.X, X_N + 2.0 / 3.0 * Ck * deps, rtol=1e-14, atol=1e-12)
    assert st1.X[:, :3].sum(-1).abs().max() < 1e-12  # deviatoric
    # the flow is driven by xi = dev(sigma) - X: eq. inelastic increment and (3G + C_k) relation
    m = torch.tensor([1.0, 1.0, 1.0, 0.0])
    xi = sig - sig[:, :3].sum(-1, keepdim=True) / 3 * m - st1.X
    assert torch.allclose(deps, 1.5 * (dep / equivalent(xi))[:, None] * xi, rtol=1e-10,
                          atol=1e-15)
    _, st2, _, _, _ = return_map_3d(eps, _state(p, X_N), p, _inputs(30.0))
    assert torch.equal(st2.X, X_N)  # no C_k: back stress carried, not evolved
    G = E / (2 * (1 + NU))
    q_tr = equivalent(sig - sig[:, :3].sum(-1, keepdim=True) / 3 * m + 2 * G * deps - X_N)
    assert torch.allclose(equivalent(xi) + (3 * G + Ck) * dep, q_tr, rtol=1e-12)
