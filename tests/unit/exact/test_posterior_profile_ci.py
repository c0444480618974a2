"""Profile-likelihood confidence intervals through the model (exact.profile_intervals):
closed form for a linear Gaussian model, the box's bounds for a direction the data do not see,
and Wilks coverage on a nonlinear ridge over repeated datasets."""

import numpy as np
import pytest
import torch

from solderpyro.exact.posterior import PROFILE_CHI2_95, IntervalOptions, profile_intervals
from solderpyro.params import Box

SIGMA = 0.1
XS = np.linspace(0.0, 1.0, 12)


def _posterior_samples(rng, mean, cov, fun, y, n=300):
    """Draws of a Gaussian (the posterior stand-in) and their sums of squared residuals."""
    S = rng.multivariate_normal(mean, cov, n)
    return S, ((fun(S) - y) ** 2).sum(1)


def test_linear_model_gives_the_closed_form_interval():
    """y = A theta + noise: the profile chi-square of theta_k is exactly quadratic, so the 95 %
    interval is theta_hat_k +- sqrt(3.84) sd_k with sd_k^2 = ((A'A / sigma^2)^-1)_kk, to 0.1 % of
    its half-width (the damped fits stop within ~1e-3 of the minimum chi-square)."""
    A = np.stack([np.ones_like(XS), XS, XS**2], 1)
    box = Box(("a", "b", "c"), (-10.0, -10.0, -10.0), (10.0, 10.0, 10.0))
    truth = np.array([0.5, -1.0, 2.0])
    rng = np.random.default_rng(1)
    y = A @ truth + SIGMA * rng.standard_normal(len(XS))

    def fun(rows):
        return np.atleast_2d(rows) @ A.T

    H = A.T @ A / SIGMA**2
    cov = np.linalg.inv(H)
    th = cov @ (A.T @ y) / SIGMA**2
    S, ssr = _posterior_samples(rng, th, cov, fun, y)
    out = profile_intervals(fun, box, y, SIGMA, S, ssr, options=IntervalOptions(n_grid=7, iters=6))
    assert [p.parameter for p in out] == ["a", "b", "c"]
    chi2_min = float(((fun(th[None])[0] - y) ** 2).sum() / SIGMA**2)
    for p in out:
        half = np.sqrt(PROFILE_CHI2_95 * cov[p.k, p.k])
        assert p.lower == pytest.approx(th[p.k] - half, abs=1e-3 * half)
        assert p.upper == pytest.approx(th[p.k] + half, abs=1e-3 * half)
        assert p.chi2_min == pytest.approx(chi2_min, abs=1e-3)
        assert not (p.at_lower_bound or p.at_upper_bound or p.truncated)
        assert np.all(np.diff(p.grid) > 0) and len(p.chi2) == len(p.grid)


def test_a_parameter_the_data_do_not_see_spans_the_box():
    """c does not enter the model: its profile is flat, so the interval is the whole box and
    both ends are flagged as set by the box (practical non-identifiability)."""
    box = Box(("a", "c"), (0.0, 1.0), (2.0, 3.0), (False, True))

    def fun(rows):
        r = np.atleast_2d(rows)
        return r[:, :1] * XS[None]

    rng = np.random.default_rng(2)
    y = 1.2 * XS + SIGMA * rng.standard_normal(len(XS))
    S = np.column_stack([rng.normal(1.2, 0.05, 200), np.exp(rng.uniform(0, np.log(3), 200))])
    ssr = ((fun(S) - y) ** 2).sum(1)
    a, c = profile_intervals(fun, box, y, SIGMA, S, ssr)
    assert (c.lower, c.upper) == pytest.approx((1.0, 3.0), rel=1e-12)
    assert c.at_lower_bound and c.at_upper_bound and not c.truncated
    assert not (a.at_lower_bound or a.at_upper_bound)
    with pytest.raises(ValueError, match="n_grid"):
        profile_intervals(fun, box, y, SIGMA, S, ssr, options=IntervalOptions(n_grid=2))
    with pytest.raises(ValueError, match="do not match"):
        profile_intervals(fun, box, y, SIGMA, S[:, :1], ssr)
    with pytest.raises(ValueError, match="finite"):
        profile_intervals(fun, box, y, SIGMA, S, np.full(len(S), np.nan))


@pytest.mark.slow  # ~75-115 s: the default suite stays near 20 minutes
def test_wilks_coverage_on_a_nonlinear_ridge():
    """y = a b x + a x^2 (a b and a tied by the data along a curved ridge on the log-a box):
    over 600 noise replications the 95 % profile interval of each parameter holds the truth
    in 0.95 of them, within 3.5 binomial sd (sd 0.0089: a 90 % interval would fail)."""
    box = Box(("a", "b"), (0.2, 0.2), (5.0, 5.0), (True, False))
    truth = np.array([1.0, 1.5])

    def fun(rows):
        r = np.atleast_2d(rows)
        return r[:, :1] * r[:, 1:2] * XS + r[:, :1] * XS**2

    rng = np.random.default_rng(7)
    hits = np.zeros(2)
    n_rep = 600
    for _ in range(n_rep):
        y = fun(truth[None])[0] + SIGMA * rng.standard_normal(len(XS))
        # stand-in posterior samples: a broad cloud around the ridge through the truth's region
        u = rng.uniform(0, 1, (400, 2))
        S = box.from_unit(torch.as_tensor(u)).numpy()
        ssr = ((fun(S) - y) ** 2).sum(1)
        out = profile_intervals(fun, box, y, SIGMA, S, ssr,
                                options=IntervalOptions(n_grid=9, iters=8))
        hits += [p.lower <= truth[p.k] <= p.upper for p in out]
    cov = hits / n_rep
    assert np.all(np.abs(cov - 0.95) <= 3.5 * np.sqrt(0.05 * 0.95 / n_rep)), cov
