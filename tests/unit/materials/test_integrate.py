"""Material-point contract: consistent tangent and parameter gradients vs finite differences."""

import pytest
import torch

from solderpyro.materials.integrate import PointInputs, PointState, anand_update, initial_state
from solderpyro.params import anand_tensor

CASES = [{}, {"s0": 5.0, "QR": 7000.0, "xi": 5.0, "m": 0.05}, {"s0": 25.0, "m": 0.5},
         {"a": 0.8}, {"a": 1.0}]


def _state(p):
    st = initial_state((3,), p[0])
    return PointState(torch.tensor([[1e-4, -3e-4, 2e-4, 1e-4]] * 3), st.s * torch.tensor(
        [1.0, 0.8, 1.3]), torch.zeros(3))


EPS = torch.tensor([[2e-4, -1e-4, 8e-4], [-5e-4, 3e-4, -2e-3], [1e-3, 1e-3, 1e-6]],
                   dtype=torch.float64)  # module level: created before the float64 fixture


@pytest.mark.parametrize("vals", CASES)
@pytest.mark.parametrize("plane", ["stress", "strain"])
@pytest.mark.parametrize("dt", [0.5, 300.0])
def test_consistent_tangent_matches_fd(vals, plane, dt):
    p = anand_tensor(vals)
    st = _state(p)
    args = (st, p, PointInputs(360.0, dt, 2e-4, 32000.0, 0.35), plane)
    sig, _, C, _, _ = anand_update(EPS, *args)
    if plane == "stress":
        assert sig[:, 2].abs().max() < 1e-7  # sigma_zz = 0 enforced
    h = 1e-7
    for j in range(3):
        e1, e2 = EPS.clone(), EPS.clone()
        e1[:, j] += h
        e2[:, j] -= h
        fd = (anand_update(e1, *args)[0] - anand_update(e2, *args)[0])[:, [0, 1, 3]] / (2 * h)
        assert torch.allclose(C[:, :, j], fd, rtol=1e-6, atol=1e-6 * fd.abs().max())


@pytest.mark.parametrize("vals", CASES[:3])
def test_parameter_gradient_matches_fd(vals):
    """d(stress, s)/d(Anand constants) through the one-step implicit correction."""
    p0 = anand_tensor(vals)
    st = _state(p0)

    def f(p):
        sig, st1, _, _, _ = anand_update(EPS, PointState(st.eps_p, st.s, st.eps_zz), p,
                                         PointInputs(360.0, 20.0, 2e-4, 32000.0, 0.35),
                                         "stress", tangent=False)
        return torch.cat([sig.reshape(-1), st1.s, st1.eps_p.reshape(-1) * 1e4])

    J = torch.autograd.functional.jacobian(f, p0)
    # h = 1e-5 relative: the central difference's round-off (the local Newton's last-digit
    # noise over 2h) grows as 1/h and reached 0.27-0.6 of the tolerance at 1e-6-1e-7, its
    # truncation (h^2) is 0.01 of it at 1e-5
    for j in range(9):
        h = 1e-5 * p0[j].abs().item()
        p1, p2 = p0.clone(), p0.clone()
        p1[j] += h
        p2[j] -= h
        fd = (f(p1) - f(p2)) / (2 * h)
        assert torch.allclose(J[:, j], fd, rtol=1e-5, atol=1e-7 * (fd.abs().max() + 1e-12))


def test_batch_shapes_broadcast():
    """Leading dims broadcast: (2, 3) points with per-row parameters equal row-wise calls."""
    p = torch.stack([anand_tensor({}), anand_tensor({"m": 0.1})])[:, None, :]  # (2, 1, 9)
    st = initial_state((2, 3), p[..., 0])
    eps = torch.stack([EPS, EPS])
    inputs = PointInputs(360.0, 10.0, 2e-4, 32000.0, 0.35)
    sig, *_ = anand_update(eps, st, p, inputs)
    for i in range(2):
        s1, *_ = anand_update(EPS, initial_state((3,), p[i, 0, 0]), p[i, 0], inputs)
        assert torch.allclose(sig[i], s1, rtol=0, atol=1e-12)
