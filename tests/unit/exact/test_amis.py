"""Adaptive multiple importance sampling: mixtures, EM, the sigma integral, and posteriors that
match brute force."""

import math

import numpy as np
import pytest
from scipy import integrate, stats

from solderpyro.exact.amis import (
    AmisOptions,
    TMixture,
    amis,
    kish_ess,
    log_marginal_sigma,
    pareto_khat,
    weighted_em,
)


def _mix2(df=5.0):
    return TMixture(np.array([0.3, 0.7]), np.array([[0.2, 0.3], [0.6, 0.5]]),
                    np.array([[[0.01, 0.004], [0.004, 0.02]], [[0.03, -0.01], [-0.01, 0.015]]]),
                    np.array([df, np.inf]))


def test_mixture_density_matches_scipy_components():
    m = _mix2()
    u = np.random.default_rng(0).uniform(-0.5, 1.5, (50, 2))
    ref = (0.3 * stats.multivariate_t(m.means[0], m.covs[0], df=5.0).pdf(u)
           + 0.7 * stats.multivariate_normal(m.means[1], m.covs[1]).pdf(u))
    np.testing.assert_allclose(np.exp(m.log_prob(u)), ref, rtol=1e-10)


def test_mixture_samples_have_its_moments():
    m = _mix2(df=8.0)
    x = m.sample(200_000, np.random.default_rng(1))
    mean = 0.3 * m.means[0] + 0.7 * m.means[1]
    c0 = m.covs[0] * 8.0 / 6.0  # t covariance = scale * df / (df - 2)
    cov = (0.3 * (c0 + np.outer(m.means[0], m.means[0]))
           + 0.7 * (m.covs[1] + np.outer(m.means[1], m.means[1])) - np.outer(mean, mean))
    se = np.sqrt(np.diag(cov) / len(x))
    assert np.all(np.abs(x.mean(0) - mean) < 5 * se)
    np.testing.assert_allclose(np.cov(x.T), cov, rtol=0.03, atol=2e-4)


def test_bad_mixture_inputs_are_named():
    with pytest.raises(ValueError, match="weights"):
        TMixture(np.array([-1.0, 2.0]), np.zeros((2, 2)), np.stack([np.eye(2)] * 2), np.inf)
    with pytest.raises(ValueError, match="df"):
        TMixture(np.ones(1), np.zeros((1, 2)), np.eye(2)[None], 0.0)
    with pytest.raises(ValueError, match="rounds"):
        amis(lambda u: (np.zeros(len(u)), {}), TMixture.single(np.zeros(2), np.eye(2)), 10, 0)
    with pytest.raises(ValueError, match="defensive"):
        AmisOptions(defensive=1.0)


def test_weighted_em_recovers_two_components():
    rng = np.random.default_rng(2)
    truth = _mix2(df=np.inf)
    x = truth.sample(20_000, rng)
    # the same sample as weighted points: half of them duplicated with weight 2 vs 1
    w = np.where(np.arange(len(x)) % 2 == 0, 2.0, 1.0)
    x2 = np.concatenate([x, x[::2]])
    w2 = np.concatenate([np.ones(len(x)), np.ones(len(x[::2]))])
    for pts, ww in ((x, np.ones(len(x))), (x2, w2)):
        fit = weighted_em(pts, ww, 2, np.random.default_rng(3))
        k = np.argsort(fit.means[:, 0])
        np.testing.assert_allclose(fit.weights[k], [0.3, 0.7], atol=0.02)
        np.testing.assert_allclose(fit.means[k], truth.means, atol=0.01)
        np.testing.assert_allclose(fit.covs[k], truth.covs, atol=0.002)
    assert w.sum() > 0


def test_kish_ess_and_khat():
    assert kish_ess(np.zeros(100)) == pytest.approx(100.0)
    assert kish_ess(np.array([0.0, -np.inf, 0.0])) == pytest.approx(2.0)
    rng = np.random.default_rng(4)
    # weights of N(0, 1) draws for a N(0, 0.5^2) target: bounded, k-hat well below 0.7;
    # for the reverse (target wider than proposal) the weights' tail is heavy
    x = rng.standard_normal(4000)
    good = stats.norm(0, 0.5).logpdf(x) - stats.norm.logpdf(x)
    bad = stats.norm(0, 3.0).logpdf(x) - stats.norm.logpdf(x)
    assert pareto_khat(good)[1] < 0.5
    assert pareto_khat(bad)[1] > 0.7


@pytest.mark.parametrize("n_obs,ssr", [(8, 0.02), (8, 0.5), (2240, 5.4), (2240, 6.5)])
def test_sigma_integral_matches_quadrature(n_obs, ssr):
    """The trapezoid in log sigma against adaptive quadrature (in log sigma too, over the
    prior's support cut to 60 likelihood sd around the peak, which holds all the mass)."""
    v_hat, sd = 0.5 * math.log(ssr / n_obs), 1.0 / math.sqrt(2 * n_obs)
    C = n_obs * v_hat + 0.5 * n_obs * (1 + math.log(2 * math.pi))  # integrand O(1)
    for known, smax in ((0.05, None), (None, 0.5)):
        if known is not None:
            lpri = stats.norm(math.log(known), 0.1).logpdf  # density of v = log sigma
            lo, hi = math.log(known) - 1.5, math.log(known) + 1.5
        else:
            lpri = lambda v, smax=smax: v - math.log(smax)  # noqa: E731
            lo, hi = math.log(1e-4), math.log(smax)
        lo, hi = max(lo, v_hat - 60 * sd), min(hi, v_hat + 60 * sd)

        def f(v, k=0, lpri=lpri):
            return v**k * math.exp(-n_obs * v - 0.5 * ssr * math.exp(-2 * v)
                                   - 0.5 * n_obs * math.log(2 * math.pi) + C + lpri(v))

        vv = np.linspace(lo, hi, 20001)  # quad needs the peak as a breakpoint
        pts = [float(vv[np.argmax([f(v) for v in vv[::100]]) * 100])]
        ref = integrate.quad(f, lo, hi, points=pts, limit=500, epsabs=0, epsrel=1e-11)[0]
        got, draw = log_marginal_sigma(np.array([ssr]), n_obs, known, smax)
        assert got[0] + C == pytest.approx(math.log(ref), abs=1e-5)
        v = np.log(draw(np.zeros(4000, int), np.random.default_rng(5)))
        mean_ref = integrate.quad(lambda v: f(v, 1), lo, hi, points=pts, limit=500,
                                  epsabs=0, epsrel=1e-11)[0] / ref
        sd_ref = math.sqrt(integrate.quad(lambda v: f(v, 2), lo, hi, points=pts, limit=500,
                                          epsabs=0, epsrel=1e-11)[0] / ref - mean_ref**2)
        assert abs(v.mean() - mean_ref) < 5 * sd_ref / math.sqrt(len(v))
        assert v.std() == pytest.approx(sd_ref, rel=0.05)
    with pytest.raises(ValueError, match="sigma_known or sigma_max"):
        log_marginal_sigma(np.ones(2), 3)


def _banana_logp(u):
    """A curved 2-D posterior on the unit square (a banana), normalizable on a grid."""
    a = (u[:, 0] - 0.45) / 0.15
    b = (u[:, 1] - 0.3 - 1.2 * (u[:, 0] - 0.45) ** 2) / 0.03
    return -0.5 * (a * a + b * b)


def test_amis_matches_the_grid_posterior_from_a_poor_start():
    """From a proposal offset by 2 posterior sd and 3x too narrow, AMIS adapts to the banana and
    its weighted quantiles match the brute-force grid's. (Seeds 0-7 all end reliable, ESS
    833-1277 of 2400, k-hat <= 0.56; with a Gaussian first proposal 4 of 8 end with k-hat
    > 0.7, which is why the first proposals here are Student-t.)"""
    g = np.linspace(0, 1, 801)
    X, Y = np.meshgrid(g, g, indexing="ij")
    p = np.exp(_banana_logp(np.column_stack([X.ravel(), Y.ravel()]))).reshape(X.shape)
    p0 = p.sum(1) / p.sum()
    p1 = p.sum(0) / p.sum()
    q0 = TMixture.single(np.array([0.75, 0.35]), np.diag([0.05, 0.01]) ** 2, df=5.0)
    res = amis(lambda u: (_banana_logp(u), {}), q0, 400, 6, AmisOptions(seed=7))
    assert res.reliable, res.history
    assert res.history[-1]["ess"] > 5 * res.history[0]["ess"]
    w = res.weights()
    ess = res.ess
    dg = g[1] - g[0]
    for k, pk in ((0, p0), (1, p1)):
        o = np.argsort(res.u[:, k])
        cw = np.cumsum(w[o])
        for q in (0.025, 0.5, 0.975):
            est = res.u[o, k][np.searchsorted(cw, q)]
            ref = np.interp(q, np.cumsum(pk), g)
            # Monte Carlo sd of a weighted quantile: sqrt(q (1 - q) / ESS) / density there
            dens = np.interp(ref, g, pk) / dg
            assert abs(est - ref) < 4 * math.sqrt(q * (1 - q) / ess) / dens, (k, q, est, ref)


@pytest.mark.parametrize("seed", [0, 3])
def test_extra_rounds_run_until_the_weights_are_reliable_and_no_further(seed):
    """From the same poor start with 60 samples a round, one round is never reliable (ESS
    2-7); extra rounds go on exactly until the first reliable one (seeds 0-7 reach it after
    6-8 rounds) and stop there; without them AMIS stops after the rounds asked for."""
    q0 = TMixture.single(np.array([0.75, 0.35]), np.diag([0.05, 0.01]) ** 2, df=5.0)

    def target(u):
        return _banana_logp(u), {}

    one = amis(target, q0, 60, 1, AmisOptions(seed=seed))
    assert len(one.history) == 1 and not one.reliable
    res = amis(target, q0, 60, 1, AmisOptions(seed=seed, extra_rounds=10))
    assert res.reliable, res.history
    h = res.history
    assert all(r["ess"] < 50 or r["khat"] > 0.7 for r in h[:-1]), h
    assert len(h) <= 11 and len(res.u) == 60 * len(h)
    with pytest.raises(ValueError, match="extra_rounds"):
        AmisOptions(extra_rounds=-1)


def test_extra_rounds_are_not_spent_on_weights_that_cannot_become_reliable():
    """A target no proposal can match (its log density independent noise of sd 30 at every
    sample): the ESS stays near 1, which doubling per round cannot bring to 50 in the three
    extra rounds, so none runs; on_course is that doubling rule."""
    from solderpyro.exact.amis import on_course

    rng = np.random.default_rng(0)
    q0 = TMixture.single(np.array([0.5, 0.5]), np.diag([0.1, 0.1]) ** 2, df=5.0)

    def target(u):
        return 30.0 * rng.standard_normal(len(u)), {}

    res = amis(target, q0, 60, 3, AmisOptions(seed=1, extra_rounds=3))
    assert res.history[-1]["ess"] < 50.0 / 8.0
    assert len(res.history) == 3 and not res.reliable
    assert on_course(6.25, 3) and not on_course(6.2, 3) and on_course(50.0, 0)
