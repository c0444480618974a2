"""solderpyro.params.LocalBox, a local prior region the NUTS sampler supports
(solderpyro.calibration.koh keeps the draws inside the prior box): a parallelepiped aligned
with a Gaussian approximation of the posterior, its unit-cube map, the Latin hypercube on it,
the prior truncation the sampler sees, and NUTS on it against the exact posterior of a linear
model; and the Laplace covariance on a box's unit scale (solderpyro.exact.laplace_cov_unit)."""

import numpy as np
import pytest
import torch

from solderpyro.calibration import Priors, calibrate_direct
from solderpyro.design import lhs
from solderpyro.exact import laplace_cov_unit
from solderpyro.fit import LMFit
from solderpyro.params import Box, LocalBox

OUTER = Box(("a", "b", "c"), (1.0, 0.0, 10.0), (5.0, 1.0, 1000.0), (False, False, True))
COV = np.array([[0.01, 0.0095, 0.0], [0.0095, 0.01, 0.001], [0.0, 0.001, 0.004]])


def test_unit_map_round_trips_and_the_lhs_has_the_gaussians_shape():
    """x -> u -> x is the identity; a Latin hypercube on the +-c sd region has, on the prior
    box's unit scale, the covariance c^2/3 COV of a uniform on the parallelepiped (2000
    points: each entry within 5 % of the largest)."""
    reg = LocalBox.gaussian(OUTER, [3.0, 0.5, 100.0], torch.tensor(COV), 2.0)
    x = lhs(reg, 2000, 0)
    u = reg.to_unit(x)
    assert float(u.min()) >= 0.0 and float(u.max()) <= 1.0
    assert torch.allclose(reg.from_unit(u), x, rtol=1e-12, atol=1e-12)
    v = OUTER.to_unit(x).numpy()
    np.testing.assert_allclose(np.cov(v.T), COV * 2.0**2 / 3.0, atol=0.05 * 4 / 3 * 0.01)
    # centre: the unit cube's centre maps to the given point (log scale for c)
    assert torch.allclose(reg.from_unit(torch.full((3,), 0.5, dtype=torch.float64)),
                          torch.tensor([3.0, 0.5, 100.0], dtype=torch.float64))


def test_log_support_is_zero_inside_the_prior_box_and_a_steep_wall_outside():
    reg = LocalBox.gaussian(OUTER, [3.0, 0.5, 100.0], torch.tensor(COV), 2.0)
    t = torch.tensor([[3.0, 0.5, 100.0], [0.8, 0.5, 100.0], [3.0, 1.01, 2000.0]],
                     dtype=torch.float64, requires_grad=True)
    ls = reg.log_support(t)
    assert ls[0] == 0.0
    r = torch.tensor(reg.basis).abs().sum(1).numpy()  # half-widths, unit scale
    assert float(ls[1].detach()) == pytest.approx(-1e4 * 0.2 / 4.0 / r[0])
    assert float(ls[2].detach()) == pytest.approx(-1e4 * (0.01 / r[1] + np.log(2.0)
                                                          / np.log(100.0) / r[2]))
    ls.sum().backward()
    assert t.grad[1, 0] > 0 and t.grad[2, 1] < 0 and t.grad[2, 2] < 0  # points back inside


def test_bad_local_box_is_named():
    with pytest.raises(ValueError, match="half-width"):
        LocalBox.gaussian(OUTER, [3.0, 0.5, 100.0], torch.tensor(COV), 0.0)
    with pytest.raises(ValueError, match="outer"):
        LocalBox(("a",), (0.0,), (1.0,))
    with pytest.raises(ValueError, match="basis"):
        LocalBox(OUTER.names, OUTER.lower, OUTER.upper, OUTER.log_scale, outer=OUTER,
                 center=(0.5,) * 3, basis=((1.0, 0, 0), (1.0, 0, 0), (0, 0, 1.0)))


def test_laplace_cov_unit_is_the_gauss_newton_covariance():
    """For a linear model on a linear box, (J'J / s^2 + 4I)^-1 on the unit scale; a log-scale
    coordinate's column is rescaled by d(linear unit)/d(log unit) = x log(hi/lo) / (hi - lo)."""
    rng = np.random.default_rng(0)
    J = rng.normal(size=(50, 3))
    fit = LMFit(np.array([3.0, 0.5, 100.0]), 0.0, np.arange(3), J=J)
    c = laplace_cov_unit(fit, OUTER, 0.1)
    s = np.array([1.0, 1.0, 100.0 * np.log(100.0) / 990.0])
    Jv = J * s
    np.testing.assert_allclose(c, np.linalg.inv(Jv.T @ Jv / 0.01 + 4 * np.eye(3)), rtol=1e-12)


def _linear_problem(n=400, seed=3):
    x = torch.linspace(0.1, 1.0, n, dtype=torch.float64)[:, None]
    A = torch.cat([x, x**2], 1)  # t1, t2 strongly correlated (corr ~ -0.97)
    t_true = torch.tensor([2.0, -1.0], dtype=torch.float64)
    g = torch.Generator().manual_seed(seed)
    y = A @ t_true + 0.05 * torch.randn(n, generator=g, dtype=torch.float64)
    return x, A, y


def test_nuts_on_a_local_region_matches_the_exact_posterior():
    """Linear model y = t1 x + t2 x^2 + N(0, s^2), flat prior, s ~ LogNormal(log 0.05, 0.1):
    the exact posterior of t is a scale mixture N(t_hat, s^2 (A'A)^-1) over p(s | y), a 1-D
    integral done on a grid. Sampled on the +-4 sd parallelepiped of its Gaussian (truncating
    ~1e-4 of the mass), the posterior mean and covariance match within 4.5 Monte Carlo
    standard errors (covariance: 15 % of each entry, the spread of a 2000-draw estimate with
    ESS ~ 800 is ~ 5 %)."""
    x, A, y = _linear_problem()
    AtA = A.T @ A
    t_hat = torch.linalg.solve(AtA, A.T @ y)
    rss = float(((y - A @ t_hat) ** 2).sum())
    n, p = A.shape
    s = np.linspace(0.03, 0.08, 4001)
    logp = (-(np.log(s / 0.05)) ** 2 / (2 * 0.1**2) - np.log(s) - (n - p) * np.log(s)
            - rss / (2 * s**2))
    w = np.exp(logp - logp.max())
    es2 = float((w * s**2).sum() / w.sum())
    cov = es2 * torch.linalg.inv(AtA).numpy()
    outer = Box(("t1", "t2"), (-10.0, -10.0), (10.0, 10.0))
    cov_u = cov / 400.0
    reg = LocalBox.gaussian(outer, t_hat.tolist(), torch.tensor(cov_u), 4.0)

    def f(xx, t):
        return t[0] * xx[:, 0] + t[1] * xx[:, 0] ** 2

    post, _ = calibrate_direct(f, x, y, reg, Priors(sigma_known=0.05), chains=2, warmup=300,
                               draws=1000, seed=0, progress=False)
    t = post.flat("t").numpy()
    u = reg.to_unit(torch.tensor(t)).numpy()
    assert u.min() >= 0.0 and u.max() <= 1.0  # inside the region
    sd = np.sqrt(np.diag(cov))
    ess = 600.0  # conservative: NUTS on a Gaussian gives ESS ~ draws here
    np.testing.assert_array_less(np.abs(t.mean(0) - t_hat.numpy()), 4.5 * sd / np.sqrt(ess))
    np.testing.assert_allclose(np.cov(t.T), cov, rtol=0.15, atol=0.15 * np.abs(cov).max()
                               * 0.02)


def test_nuts_stays_inside_the_prior_box_when_the_region_crosses_it():
    """A region centred 1 sd inside the prior box's lower edge of t1: the draws stay in the
    prior box (the wall), and t1's posterior is the Gaussian truncated there (its mean moves
    up by sd * phi(1) / Phi(1)... within 0.25 sd)."""
    x, A, y = _linear_problem()
    AtA = A.T @ A
    t_hat = torch.linalg.solve(AtA, A.T @ y)
    cov = 0.05**2 * torch.linalg.inv(AtA).numpy()
    sd = np.sqrt(np.diag(cov))
    lo1 = float(t_hat[0]) - sd[0]
    outer = Box(("t1", "t2"), (lo1, -10.0), (10.0, 10.0))
    w = np.array([10.0 - lo1, 20.0])
    reg = LocalBox.gaussian(outer, t_hat.tolist(), torch.tensor(cov / np.outer(w, w)), 4.0)

    def f(xx, t):
        return t[0] * xx[:, 0] + t[1] * xx[:, 0] ** 2

    post, _ = calibrate_direct(f, x, y, reg, Priors(sigma_known=0.05), chains=2, warmup=300,
                               draws=600, seed=1, progress=False)
    t1 = post.flat("t")[:, 0].numpy()
    assert t1.min() >= lo1 - 0.01 * sd[0]  # the wall: 1e-3 half-widths cost 10 nats
    from scipy.stats import norm
    shift = sd[0] * norm.pdf(-1.0) / (1.0 - norm.cdf(-1.0))
    assert abs(t1.mean() - (float(t_hat[0]) + shift)) < 0.25 * sd[0]

