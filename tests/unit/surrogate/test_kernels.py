"""Correlation functions (solderpyro.surrogate.kernels): known values, unit diagonal,
symmetry and positive semi-definiteness, the parameterizations of GPyTorch's RBF and Matern
5/2 kernels, batching and a finite gradient at coincident points."""

import math

import pytest
import torch

from solderpyro.surrogate.kernels import KERNELS, gaussian, matern52, sqdist

F64 = torch.float64


def _pts(n, d, seed, batch=()):
    return torch.rand(*batch, n, d, generator=torch.Generator().manual_seed(seed), dtype=F64)


def test_sqdist_is_the_weighted_squared_distance():
    x1, x2 = _pts(5, 3, 0), _pts(4, 3, 1)
    w = torch.tensor([0.5, 2.0, 3.0], dtype=F64)
    ref = torch.stack([torch.stack([(w * (a - b) ** 2).sum() for b in x2]) for a in x1])
    torch.testing.assert_close(sqdist(x1, x2, w), ref, rtol=1e-14, atol=0)
    # a (1,) weight is isotropic
    torch.testing.assert_close(sqdist(x1, x2, w[:1]), 0.5 * torch.cdist(x1, x2) ** 2,
                               rtol=1e-12, atol=1e-15)


def test_known_values():
    """gaussian: exp(-theta d^2); matern52 at r = |dx|/l = 1: (1 + sqrt5 + 5/3) e^-sqrt5."""
    x0 = torch.zeros(1, 2, dtype=F64)
    x1 = torch.tensor([[0.3, 0.4]], dtype=F64)  # |dx| = 0.5
    g = gaussian(x0, x1, torch.tensor([2.0, 2.0], dtype=F64))
    assert g.item() == pytest.approx(math.exp(-2.0 * 0.25), rel=1e-15)
    mt = matern52(x0, x1, torch.tensor([0.5], dtype=F64))
    s5 = math.sqrt(5.0)
    assert mt.item() == pytest.approx((1 + s5 + 5 / 3) * math.exp(-s5), rel=1e-14)
    assert KERNELS == {"gaussian": gaussian, "matern52": matern52}


@pytest.mark.parametrize("name", ["gaussian", "matern52"])
def test_correlation_matrices_are_valid(name):
    """R(x, x) = 1 on the diagonal (matern: to 1e-15, its distance is clamped at 1e-15),
    symmetric, entries in (0, 1], positive semi-definite (smallest eigenvalue above
    -n eps |R|)."""
    x = _pts(30, 3, 2)
    par = torch.tensor([3.0, 0.5, 1.0], dtype=F64)
    R = KERNELS[name](x, x, par)
    torch.testing.assert_close(R.diagonal(), torch.ones(30, dtype=F64), rtol=0, atol=1e-15)
    torch.testing.assert_close(R, R.T, rtol=0, atol=0)
    assert bool(((R > 0) & (R <= 1.0)).all())
    assert torch.linalg.eigvalsh(R).min() > -30 * torch.finfo(F64).eps * R.norm()


def test_same_as_gpytorch_kernels():
    """gaussian with theta = 1/(2 l^2) is GPyTorch's RBF, matern52 its Matern nu = 5/2, with
    ARD lengthscales (1e-12: the same formula in another order)."""
    gpytorch = pytest.importorskip("gpytorch")
    x1, x2 = _pts(6, 3, 3), _pts(7, 3, 4)
    ls = torch.tensor([0.3, 1.2, 0.7], dtype=F64)
    rbf = gpytorch.kernels.RBFKernel(ard_num_dims=3).to(F64)
    rbf.lengthscale = ls
    mat = gpytorch.kernels.MaternKernel(nu=2.5, ard_num_dims=3).to(F64)
    mat.lengthscale = ls
    with torch.no_grad():
        torch.testing.assert_close(gaussian(x1, x2, 1 / (2 * ls**2)), rbf(x1, x2).to_dense(),
                                   rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(matern52(x1, x2, ls), mat(x1, x2).to_dense(), rtol=1e-12,
                                   atol=1e-14)


def test_batched_parameters_and_finite_gradient_at_coincident_points():
    """Leading batch dimensions broadcast (one parameter row per output); the gradient of
    matern52 w.r.t. its lengthscale at coincident points is finite (0: R = 1 there)."""
    x = _pts(4, 2, 5, batch=(3,))
    ls = torch.tensor([[0.2, 0.4], [1.0, 1.0], [0.5, 3.0]], dtype=F64, requires_grad=True)
    R = matern52(x, x, ls)
    assert R.shape == (3, 4, 4)
    for b in range(3):
        torch.testing.assert_close(R[b], matern52(x[b], x[b], ls[b]), rtol=0, atol=0)
    (g,) = torch.autograd.grad(R.diagonal(dim1=-2, dim2=-1).sum(), ls)
    assert bool(torch.isfinite(g).all()) and g.abs().max() < 1e-10
    G = gaussian(x, x, 1.0 / ls.detach())
    assert G.shape == (3, 4, 4)
