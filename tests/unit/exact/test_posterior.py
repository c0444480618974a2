"""The FE-exact posterior machinery on a cheap model with a curved ridge: profile, proposal and
AMIS against the brute-force grid posterior, from a proposal that starts on the wrong piece of
the ridge (the failure of a surrogate posterior it exists to fix)."""

import math

import numpy as np
import pytest
import torch

from solderpyro.calibration.intervals import weighted_quantiles
from solderpyro.exact.amis import log_marginal_sigma
from solderpyro.exact.coords import UnitCoords
from solderpyro.exact.fit import LMOptions, lm_fit
from solderpyro.exact.posterior import (
    ExactSampling,
    ProfileOptions,
    exact_posterior,
    fe_profile,
    initial_proposal,
    laplace_cov_unit,
    laplace_cov_w,
    profile_coordinate,
    ridge_mixture,
)
from solderpyro.params import Box

BOX = Box(("a", "b", "c"), (0.2, 0.2, 0.0), (5.0, 5.0, 2.0), (True, False, False))
UC = UnitCoords(BOX)
X = np.linspace(0.0, 2.0, 20)
TRUTH = np.array([1.0, 1.5, 0.7])
SIGMA = 0.2


def model(rows):
    """``(b, 3) -> (b, 20)``: the data fix a*b tightly (a hyperbola in (a, b), curved on the
    log-a unit scale) and a weak a*x^2 term tilts the ridge."""
    r = np.atleast_2d(rows)
    a, b, c = r[:, :1], r[:, 1:2], r[:, 2:3]
    return a * b * X + 0.04 * a * X**2 + c * np.exp(-X)


def data(seed=0):
    return model(TRUTH[None])[0] + SIGMA * np.random.default_rng(seed).standard_normal(len(X))


def grid_posterior(y, n=161):
    """Marginal posteriors of a, b, c on a unit-cube grid (flat prior there), sigma
    integrated out with the same LogNormal prior as the sampler."""
    g = (np.arange(n) + 0.5) / n
    U = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    th = BOX.from_unit(torch.as_tensor(U)).numpy()
    ssr = np.concatenate([((model(th[i:i + 200_000]) - y) ** 2).sum(1)
                          for i in range(0, len(th), 200_000)])
    ll, _ = log_marginal_sigma(ssr, len(y), sigma_known=SIGMA, grid=41)
    p = np.exp(ll - ll.max()).reshape(n, n, n)
    p /= p.sum()
    return g, [p.sum((1, 2)), p.sum((0, 2)), p.sum((0, 1))]


def test_profile_follows_the_ridge_and_its_mixture_covers_it():
    y = data()
    fit = lm_fit(model, np.array([[2.0, 0.8, 0.5]]), BOX.lower, BOX.upper, y, SIGMA,
                 options=LMOptions(iters=20))[0]
    cov = laplace_cov_unit(fit, BOX, SIGMA)
    assert profile_coordinate(cov) in (0, 1)  # the ridge moves a and b, not c
    J = fit.jacobian_unit(BOX.lower, BOX.upper, BOX.log_scale)
    np.testing.assert_allclose(laplace_cov_w(J, UC, fit.x, SIGMA), cov, rtol=1e-12)
    prof = fe_profile(model, UC, fit.x, cov, y, SIGMA, ProfileOptions(n_grid=9, iters=8))
    # the model is linear in the other two parameters once the profiled one is fixed, so each
    # profile point's chi2 must equal the exact least-squares minimum (where it is in the box)
    j = prof.coord
    for x, c2 in zip(prof.x, prof.chi2, strict=True):
        v = x[j]
        if j == 0:  # a fixed: linear in (b, c), 0.04 a x^2 known
            A, t = np.column_stack([v * X, np.exp(-X)]), y - 0.04 * v * X**2
        else:  # b fixed: linear in (a, c)
            A, t = np.column_stack([v * X + 0.04 * X**2, np.exp(-X)]), y
        sol, *_ = np.linalg.lstsq(A, t, rcond=None)
        other = [k for k in range(3) if k != j]
        lo, hi = np.array(BOX.lower)[other], np.array(BOX.upper)[other]
        if np.all((sol > lo) & (sol < hi)):
            c2_ls = float(((A @ sol - t) ** 2).sum() / SIGMA**2)
            assert c2_ls - 1e-6 <= c2 <= c2_ls + 0.05, (v, c2, c2_ls)
    inside = np.isfinite(prof.chi2)
    # the grid passes within 0.5 Laplace sd of the best fit (chi2 + 0.25 for a quadratic
    # profile) and may find lower points along a ridge the fit had not finished descending
    assert np.min(prof.chi2) <= fit.chi2 + 1.0
    mix = ridge_mixture(prof, 3)
    assert mix is not None and len(mix.weights) == 4 * (inside.sum() - 1) + 1
    # the mixture has mass along the whole profiled stretch: its density at each profile point
    # is within a factor 1e3 of its highest
    lp = mix.log_prob(BOX.to_unit(torch.as_tensor(prof.x)).numpy())
    assert lp.max() - lp.min() < math.log(1e3)


@pytest.mark.parametrize("seed", [0, 1])
def test_exact_posterior_matches_the_grid_from_a_misplaced_start(seed):
    """The surrogate-like start: draws on a short piece of the ridge (a in 3-3.5, where the
    exact posterior has little mass). Best fit + profile + AMIS recover the grid posterior's
    2.5 / 50 / 97.5 % quantiles within their Monte Carlo error, and flag the result reliable."""
    y = data(seed)
    rng = np.random.default_rng(seed + 10)
    a = rng.uniform(3.0, 3.5, 300)
    draws = np.column_stack([a, 1.5 / a + 0.01 * rng.standard_normal(300),
                             0.7 + 0.02 * rng.standard_normal(300)])
    fit = lm_fit(model, draws[:2], BOX.lower, BOX.upper, y, SIGMA, options=LMOptions(iters=8))
    best = min(fit, key=lambda f: f.chi2)
    cov = laplace_cov_unit(best, BOX, SIGMA)
    prof = fe_profile(model, UC, best.x, cov, y, SIGMA, ProfileOptions(n_grid=9, iters=6))
    q0 = initial_proposal(UC, draws, (best.x, cov), prof, seed=seed)
    ex = exact_posterior(model, UC, y, q0, ExactSampling(400, 4, seed=seed), sigma_known=SIGMA)
    assert ex.reliable, ex.result.history
    g, marg = grid_posterior(y)
    U = ex.result.u  # unit cube, the grid's coordinates
    w = ex.result.weights()
    ess = ex.result.ess
    dg = g[1] - g[0]
    for k in range(3):
        cdf = np.cumsum(marg[k])
        for q in (0.025, 0.5, 0.975):
            ref = np.interp(q, cdf, g + 0.5 * dg)
            est = weighted_quantiles(U[:, k], w, (q,))[0]
            dens = np.interp(ref, g, marg[k]) / dg
            tol = 4 * math.sqrt(q * (1 - q) / ess) / dens + dg
            assert abs(est - ref) < tol, (k, q, est, ref, tol)
    # the resampled draws carry the model's outputs and a sigma near the truth
    np.testing.assert_allclose(ex.V, model(ex.theta), atol=1e-12)
    assert abs(np.median(ex.sigma) - SIGMA) < 0.2 * SIGMA
    assert [r["parameter"] for r in ex.rows] == ["a", "b", "c", "sigma"]


def test_exact_inputs_are_checked():
    with pytest.raises(ValueError, match="n_grid"):
        fe_profile(model, UC, TRUTH, np.eye(3) * 0.01, data(), SIGMA, ProfileOptions(n_grid=1))
    with pytest.raises(ValueError, match="draws, an FE best fit or a profile"):
        initial_proposal(UC)
