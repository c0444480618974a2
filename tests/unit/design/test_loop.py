"""The adaptive design (solderpyro.design): the surrogate as a BoTorch model, the acquisition
functions against closed forms, where they put runs, the stopping rule, and a crash between
rounds."""

import math

import numpy as np
import pytest
import torch

from solderpyro.design import lhs
from solderpyro.design.acquisition import (
    AcquisitionPoints,
    greedy_draws,
    integrated_code_variance,
    loglik_terms,
    propose,
    qIntegratedLogLikVariance,
)
from solderpyro.design.loop import (
    Draws,
    LoopProblem,
    LoopSettings,
    design_rounds,
    final_posterior,
    run_loop,
    stop_rule,
)
from solderpyro.design.model import botorch_model, observed_weights
from solderpyro.params import Box, ParameterSpace
from solderpyro.surrogate import GPOptions, GPSurrogate

BOX1 = Box(("t",), (0.0,), (1.0,))
GRID = torch.linspace(0, 1, 801, dtype=torch.float64)[:, None]
SIGMA = 0.02


def f1(t: torch.Tensor) -> torch.Tensor:
    """A 1-D toy simulator with 12 outputs: ``(n, 1) -> (n, 12)``."""
    k = torch.arange(1, 13, dtype=torch.float64)
    return torch.sin(2.0 * t * k / 4 + k) + t * k / 12


@pytest.fixture(scope="module")
def gp4():
    box = ParameterSpace.seed()
    x = lhs(box, 24, 1)
    u = box.to_unit(x)
    y = torch.stack([torch.sin(3 * u[:, 0]) + u[:, 1] * u[:, 2] + 0.2 * k * u[:, 3]
                     for k in range(15)], 1)
    return box, GPSurrogate(box, output="pca", kernel="matern52", ard=True).fit(x, y)


def _var_after(gp: GPSurrogate, x_new: torch.Tensor, pts: torch.Tensor) -> torch.Tensor:
    """Closed form: the GP coefficients' variance ``(N, k)`` at ``pts`` after adding runs
    ``x_new`` (physical), hyperparameters fixed."""
    f = gp.factors()
    A = torch.cat([f.u[0], gp.gp_inputs(x_new)])  # (n + q, d')
    P = gp.gp_inputs(pts)
    out = []
    for k in range(f.u.shape[0]):
        Kaa = f.outputscale[k] * _corr(f, A, A, k) + f.noise[k] * torch.eye(len(A))
        Kpa = f.outputscale[k] * _corr(f, P, A, k)
        out.append(f.outputscale[k] - (Kpa * torch.linalg.solve(Kaa, Kpa.T).T).sum(1))
    return torch.stack(out, 1)


def _corr(f, a, b, k):
    from solderpyro.surrogate.kernels import matern52

    return matern52(a[None], b[None], f.lengthscale[k:k + 1])[0]


def test_botorch_model_is_the_surrogate(gp4):
    box, gp = gp4
    m = botorch_model(gp)
    x = lhs(box, 9, 7)
    mc, vc = gp.coefficients(x, False)
    post = m.posterior(box.to_unit(x))
    assert m.num_outputs == gp.basis.shape[1]
    # GPyTorch's distance (|a|^2 + |b|^2 - 2ab) rounds at ~1e-8 of the unit scale
    torch.testing.assert_close(post.mean, mc.T, atol=1e-6, rtol=0)
    torch.testing.assert_close(post.variance, vc.T, atol=1e-7, rtol=1e-5)


@pytest.mark.parametrize("mean", ["constant", "linear"])
def test_a_scalar_surrogate_is_a_single_output_botorch_model(mean):
    box = Box(("x", "t"), (0.0, 0.0), (1.0, 2.0))
    x = lhs(box, 20, 3)
    gp = GPSurrogate(box, mean=mean, options=GPOptions(restarts=1)).fit(
        x, torch.sin(2 * x[:, 0]) + x[:, 1])
    m = botorch_model(gp)
    xt = lhs(box, 6, 4)
    mc, vc = gp.coefficients(xt, False)
    post = m.posterior(box.to_unit(xt))
    assert m.num_outputs == 1
    torch.testing.assert_close(post.mean[:, 0], mc[0], atol=1e-7, rtol=0)
    torch.testing.assert_close(post.variance[:, 0], vc[0], atol=1e-9, rtol=1e-5)


def test_acquisitions_have_botorch_shapes_and_equal_their_closed_forms(gp4):
    box, gp = gp4
    m = botorch_model(gp)
    g = torch.Generator().manual_seed(0)
    mc = 0.3 + 0.4 * torch.rand(40, 4, generator=g, dtype=torch.float64)
    a = observed_weights(gp, 0.05)
    y = gp.predict(box.from_unit(torch.full((1, 4), 0.5, dtype=torch.float64)))[0][0]
    gr, M = loglik_terms(gp, box.from_unit(mc), y + 0.01, 0.05)
    acqs = [integrated_code_variance(m, mc, a), qIntegratedLogLikVariance(m, mc, gr, M)]
    X = torch.rand(5, 3, 4, generator=g, dtype=torch.float64)  # (b, q, d)
    for acq in acqs:
        v = acq(X)
        assert v.shape == (5,) and bool((v <= 0).all())
    for b in range(2):
        V = _var_after(gp, box.from_unit(X[b]), box.from_unit(mc))  # (N, k)
        want_v = -(V * a).sum(1).mean()
        want_l = -((gr**2 * V).sum(1) + 0.5 * torch.einsum("nk,kl,nl->n", V, M**2, V)).mean()
        assert float(acqs[0](X[b:b + 1])) == pytest.approx(float(want_v), rel=1e-4)
        assert float(acqs[1](X[b:b + 1])) == pytest.approx(float(want_l), rel=1e-4)
    with pytest.raises(ValueError, match="weights must have shape"):
        integrated_code_variance(m, mc, a[:1])


def test_the_closed_form_greedy_choice_is_botorchs(gp4):
    """greedy_draws (rank-1 updates) picks the same q-batch as BoTorch's
    optimize_acqf_discrete on the BoTorch acquisitions, with the same value."""
    from botorch.optim import optimize_acqf_discrete

    box, gp = gp4
    m = botorch_model(gp)
    g = torch.Generator().manual_seed(2)
    mc_u = 0.3 + 0.4 * torch.rand(30, 4, generator=g, dtype=torch.float64)
    cand_u = 0.2 + 0.6 * torch.rand(25, 4, generator=g, dtype=torch.float64)
    pend_u = 0.5 + 0.1 * torch.rand(2, 4, generator=g, dtype=torch.float64)
    mc, cand, pend = (box.from_unit(v) for v in (mc_u, cand_u, pend_u))
    y = gp.predict(box.from_unit(torch.full((1, 4), 0.45, dtype=torch.float64)))[0][0]
    sig = 0.05
    gr, M = loglik_terms(gp, mc, y, sig)
    for crit, acq in (("variance", integrated_code_variance(m, mc_u, observed_weights(gp, sig),
                                                            X_pending=pend_u)),
                      ("loglik", qIntegratedLogLikVariance(m, mc_u, gr, M, X_pending=pend_u))):
        Xb, _ = optimize_acqf_discrete(acq, 3, cand_u, unique=True)
        idx, val = greedy_draws(gp, crit, AcquisitionPoints(mc, cand, pend), 3, sig, y)
        torch.testing.assert_close(cand_u[idx], Xb)
        assert val == pytest.approx(float(acq(Xb[None])), rel=1e-4)


def _toy_posterior(gp: GPSurrogate, y: torch.Tensor, n: int = 400, seed: int = 0) -> Draws:
    """Exact posterior on a grid of the 1-D box (uniform prior, modular likelihood with the
    code variance), resampled to ``n`` draws."""
    with torch.no_grad():
        mu, var = gp.predict(GRID)
    ll = -0.5 * (((y - mu) ** 2) / (var + SIGMA**2) + torch.log(var + SIGMA**2)).sum(1)
    w = torch.softmax(ll, 0)
    idx = torch.multinomial(w, n, replacement=True,
                            generator=torch.Generator().manual_seed(seed))
    t = GRID[idx].sort(0).values
    return Draws(t, torch.full((n,), SIGMA, dtype=torch.float64))


def test_the_acquisition_puts_runs_where_the_posterior_is_not_where_the_prior_is():
    """1-D toy, data at t = 0.8: over the whole box, both criteria are best inside the
    posterior's range (a few hundredths wide), not in the rest of the prior box."""
    x = torch.tensor([[0.05], [0.3], [0.5], [0.7], [0.95]], dtype=torch.float64)
    gp = GPSurrogate(BOX1, output="batched", kernel="matern52").fit(x, f1(x))
    y = f1(torch.tensor([[0.8]], dtype=torch.float64))[0]
    d = _toy_posterior(gp, y)
    lo, hi = float(d.theta.min()), float(d.theta.max())
    assert hi - lo < 0.3  # a posterior narrower than the prior
    m = botorch_model(gp)
    g, M = loglik_terms(gp, d.theta, y, SIGMA)
    for acq in (integrated_code_variance(m, d.theta, observed_weights(gp, SIGMA)),
                qIntegratedLogLikVariance(m, d.theta, g, M)):
        vals = acq(GRID[:, None, :])  # (801,), q = 1 at every grid point
        best = float(GRID[int(vals.argmax()), 0])
        assert lo - 0.05 <= best <= hi + 0.05, (best, lo, hi)
        # and the proposer's q-batch from posterior draws lies in it, all distinct
        Xq, _ = propose(acq, 1, 3, "draws", candidates=d.theta)
        assert Xq.shape == (3, 1) and len(set(Xq[:, 0].tolist())) == 3
        assert bool(((Xq >= lo) & (Xq <= hi)).all())


def _toy_problem(bias: float = 0.0, calls: list | None = None, cache: dict | None = None):
    y = f1(torch.tensor([[0.8]], dtype=torch.float64))[0] \
        + SIGMA * torch.randn(12, generator=torch.Generator().manual_seed(4),
                              dtype=torch.float64)

    def fe(th):
        V = torch.empty(len(th), 12, dtype=torch.float64)
        for i, t in enumerate(th):
            key = round(float(t[0]), 12)
            if cache is not None and key in cache:
                V[i] = cache[key]
                continue
            if calls is not None:
                calls.append(key)
            V[i] = f1(t[None])[0]
            if cache is not None:
                cache[key] = V[i].clone()
        return V, torch.ones(len(th), dtype=torch.bool)

    def fit(X, Y):  # a biased surrogate learns outputs shifted by a smooth bias
        return GPSurrogate(BOX1, output="batched", kernel="matern52",
                           options=GPOptions(restarts=1)).fit(
            X, Y + bias * torch.cos(3 * X))

    return LoopProblem(BOX1, y, fe, fit, lambda gp, prev, final: _toy_posterior(gp, y))


def test_the_stopping_rule_stops_on_an_exact_surrogate_and_not_on_a_biased_one():
    s = LoopSettings(start=4, batch=2, check=3, budget=30, mc_points=100, candidates=200)
    res = run_loop(_toy_problem(), s, seed=0)
    assert res.reason == "converged" and res.converged
    last = res.rounds[-1]
    assert last.code_ok and last.fe_ok
    assert len(res.X) < s.budget
    # the posterior it stops on covers the truth
    assert float(res.draws.theta.min()) <= 0.8 <= float(res.draws.theta.max())
    biased = run_loop(_toy_problem(bias=0.05), s, seed=0)
    assert biased.reason == "budget" and "budget ran out" in biased.message
    assert not biased.rounds[-1].fe_ok
    assert len(biased.X) <= s.budget


def test_the_final_posterior_and_its_fe_check_use_the_data_they_are_given():
    """The rounds on the measured data, then other data (as the discretization correction
    returns them): the final posterior is drawn on those, and its FE check in every chain
    measures the FE against them: chi2 = |y' - FE|^2 / sigma^2 at each checked draw, to
    rounding (12 values of size ~1: 1e-12 relative), not against the rounds' data (a shift of
    half a noise sd per value changes it by n / 4 + sum_i (y_i - FE_i) / sigma: measured 2.5
    and 2.9 at the two checked draws; the test asks for 0.1)."""
    import dataclasses

    s = LoopSettings(start=4, batch=2, check=3, budget=30, mc_points=100, candidates=200)
    p = _toy_problem()
    rounds = design_rounds(p, s, seed=0)
    assert rounds.reason == "converged" and rounds.draws.checked is not None
    y2 = p.y - 0.5 * SIGMA
    finals: list[bool] = []

    def sample(gp, prev, final):
        finals.append(final)
        return _toy_posterior(gp, y2)

    res = final_posterior(dataclasses.replace(p, y=y2, sample=sample), rounds, s)
    assert finals == [True] and res.rounds[:-1] == rounds.rounds
    assert res.draws.checked is not None
    th, V, c2 = res.draws.checked
    want = (((y2 - V) / SIGMA) ** 2).sum(1).numpy()
    np.testing.assert_allclose(c2, want, rtol=1e-12, atol=0)
    old = (((p.y - V) / SIGMA) ** 2).sum(1).numpy()
    assert np.all(np.abs(old - c2) > 0.1), (old, c2)
    np.testing.assert_allclose(res.rounds[-1].fe_chi2, c2, rtol=0, atol=0)


def test_the_fe_check_adds_observation_side_offsets_as_the_surrogate_does():
    """Data with an observation-side offset (e.g. a Moire rigid shift, 0.3 um, known at every
    draw): an exact surrogate with the offset added to both sides converges; the FE check's
    chi-square at each checked draw equals the surrogate's to within the sampling sd."""
    shift = 0.3
    base = _toy_problem()
    y = base.y + shift

    def sample(gp, prev, final):
        d = _toy_posterior(gp, base.y)  # the FE part's posterior (the shift is known)
        d.offset = torch.full((len(d.theta), len(y)), shift, dtype=torch.float64)
        return d

    s = LoopSettings(start=4, batch=2, check=3, budget=30, mc_points=100, candidates=200)
    res = run_loop(LoopProblem(BOX1, y, base.fe, base.fit, sample), s, seed=0)
    last = res.rounds[-1]
    assert res.reason == "converged" and last.fe_ok
    assert max(last.fe_chi2) < 3 * len(y)  # ~ chi2(12), not ~ (2 x 0.3 / sigma)^2 per value


def test_the_final_posterior_is_checked_in_every_chain_and_an_island_is_refitted_away():
    """A surrogate that also "fits" the data at t = 0.2, where no FE run lies (an island only
    the surrogate likes; the FE misfits there by thousands in chi-square): the rounds' posterior
    does not reach it, the final one's second chain does. The FE check of every chain finds
    the gap, its runs join the design, the refitted surrogate has no island, and the final
    posterior drawn again is checked and agrees."""
    base = _toy_problem()
    y = base.y
    island = torch.tensor([[0.2]], dtype=torch.float64)

    def fit(X, Y):
        if bool(((X - 0.2).abs() < 0.02).any()):
            return base.fit(X, Y)  # an FE run there: the surrogate learns the misfit
        fake = torch.cat([X, island + torch.tensor([[-0.004], [0.0], [0.004]])])
        return base.fit(fake, torch.cat([Y, y.expand(3, -1)]))  # pretends y at t = 0.2

    finals = []

    def sample(gp, prev, final):
        with torch.no_grad():
            has_island = float((gp.predict(island)[0] - y).abs().max()) < 0.1
            mu, var = gp.predict(GRID)
        ll = -0.5 * (((y - mu) ** 2) / (var + SIGMA**2) + torch.log(var + SIGMA**2)).sum(1)
        ll[GRID[:, 0] < 0.4] = -math.inf  # short chains that never travel to t = 0.2
        idx = torch.multinomial(torch.softmax(ll, 0), 400, replacement=True,
                                generator=torch.Generator().manual_seed(0))
        d = Draws(GRID[idx].sort(0).values, torch.full((400,), SIGMA, dtype=torch.float64))
        if not final:
            return d
        finals.append(has_island)
        t = d.theta.clone()
        if has_island:  # the second chain sits in the island
            t[len(t) // 2:] = 0.2 + 0.001 * torch.randn(len(t) - len(t) // 2, 1,
                                                        generator=torch.Generator().manual_seed(1),
                                                        dtype=torch.float64)
        return Draws(t, d.sigma, chains=2)

    s = LoopSettings(start=4, batch=2, check=3, budget=40, mc_points=100, candidates=200)
    res = run_loop(LoopProblem(BOX1, y, base.fe, fit, sample), s, seed=0)
    assert finals == [True, False]  # drawn again once, without the island
    checks = [r for r in res.rounds if r.acquired == 0 and len(r.fe_chi2) == 4]
    assert len(checks) >= 2 and not checks[-2].fe_ok and checks[-1].fe_ok
    assert max(checks[-2].fe_chi2) > 1000 * len(y) ** 0.5  # the island, by the FE
    assert bool(((res.X - 0.2).abs() < 0.01).any())  # its runs joined the design
    assert float((res.draws.theta - 0.2).abs().min()) > 0.1  # the final draws left it
    assert res.reason == "converged" and "first reached where only the surrogate" in res.message


@pytest.mark.parametrize("model_fits", [False, True])
def test_a_model_that_cannot_fit_stops_the_design_at_its_misfit_check(model_fits):
    """The problem's misfit test runs from round ``misfit_check`` on and at most once after
    a verdict: a model whose own best fit misfits stops the loop there (reason "misfit", no
    runs acquired that round, the verdict kept, no full-length posterior drawn after it); one
    that fits lets the loop go on."""
    base = _toy_problem(bias=0.05)  # never converges: the loop would run to its budget
    seen: list[int] = []
    fars: list[bool] = []

    def misfit(d, chk, fe_c2, far):
        seen.append(len(chk))
        fars.append(far)
        return {"x": {"t": 0.8}, "chi2": 1e4, "rms_over_sigma": 29.0,
                "misfits": not model_fits}

    finals: list[bool] = []

    def sample(gp, prev, final):
        finals.append(final)
        return base.sample(gp, prev, final)

    s = LoopSettings(start=4, batch=2, check=3, budget=30, mc_points=100, candidates=200,
                     misfit_check=2)
    res = run_loop(LoopProblem(BOX1, base.y, base.fe, base.fit, sample, misfit), s,
                   seed=0)
    assert seen == [3]  # called once, in round 2, with the checked draws
    r2 = res.rounds[1]  # told whether that round is far from converged
    assert fars == [max(r2.code_chi2, r2.fe_gap) > s.far_tol * r2.tolerance]
    assert res.best_fit is not None and res.as_dict()["best_fit"]["chi2"] == 1e4
    if model_fits:
        assert res.reason == "budget" and finals[-1] is True
    else:
        assert res.reason == "misfit" and "misses something" in res.message
        assert len(res.rounds) == 2 and res.rounds[-1].acquired == 0
        # the FE's best fit is the result: the last round's draws stand for the posterior
        assert True not in finals and len(finals) == 2
        assert len(res.X) == 4 + 2 * 3 + 2  # start, two checks, round 1's acquisitions
    with pytest.raises(ValueError, match="design.misfit_check"):
        LoopSettings(misfit_check=-1).validate(1)
    with pytest.raises(ValueError, match="design.far_tol"):
        LoopSettings(far_tol=0).validate(1)


def test_a_model_that_can_fit_localizes_the_design_at_its_fe_best_fit():
    """When the misfit test finds that the FE's own best fit fits, its runs (best first)
    join the design in place of that round's acquisition: at most ``localize``, none closer
    than LOCAL_SPACING to another or to an earlier run (the fit's difference steps are
    near-duplicates); the next posterior is asked to start at the best fit; and the record
    keeps the verdict without the runs."""
    from solderpyro.design.loop import LOCAL_SPACING, spaced_rows

    base = _toy_problem(bias=0.05)
    runs = np.array([[0.8], [0.8008], [0.8012], [0.77], [0.2], [0.21], [0.55], [0.9]])
    starts: list = []

    def sample(gp, prev, final):
        starts.append(None if prev is None else prev.start)
        return base.sample(gp, prev, final)

    def misfit(d, chk, fe_c2, far):
        return {"x": {"t": 0.8}, "chi2": 11.0, "rms_over_sigma": 0.96, "misfits": False,
                "runs": runs}

    s = LoopSettings(start=4, batch=2, check=3, budget=30, mc_points=100, candidates=200,
                     misfit_check=2, localize=4)
    res = run_loop(LoopProblem(BOX1, base.y, base.fe, base.fit, sample, misfit), s, seed=0)
    kinds, rnd = np.asarray(res.kind), np.asarray(res.round)
    X = res.X.numpy()[:, 0]
    fit = np.flatnonzero(kinds == "fe_fit")
    before = X[:fit[0]]
    assert 1 <= len(fit) <= 4 and set(rnd[fit]) == {2}
    assert not np.any((kinds == "acquired") & (rnd == 2))  # localized instead of acquiring
    assert res.rounds[1].acquired == len(fit)
    for i in fit:  # each kept run is LOCAL_SPACING from every earlier run
        assert np.min(np.abs(X[:i] - X[i])) >= LOCAL_SPACING
    # exactly the rows the greedy rule keeps, in the fit's order
    keep = spaced_rows(runs, before[:, None], 4)
    np.testing.assert_array_equal(X[fit], runs[keep, 0])
    assert starts[2] == {"t": 0.8}  # round 3's posterior starts at the best fit
    assert "runs" not in res.as_dict()["best_fit"]
    # the rule itself: near-duplicates, rows near what is there and non-finite rows dropped
    got = spaced_rows(np.array([[0.5, 0.5], [0.505, 0.5], [np.nan, 0.1], [0.1, 0.1],
                                [0.9, 0.9]]), np.array([[0.1, 0.11]]), 5)
    np.testing.assert_array_equal(got, [0, 4])
    with pytest.raises(ValueError, match="design.localize"):
        LoopSettings(localize=-1).validate(1)


def test_a_recalibration_places_start_runs_along_the_known_refits_laplace_ridge():
    """``refit_design``: with a known FE best fit of the model (the diagnosis's refit), the
    start design gets runs around it: the point first, then draws of its Laplace
    approximation widened REFIT_WIDEN times. On a linear toy whose posterior is a thin ridge
    (correlation -0.995) the runs spread along the ridge and stay within the widened
    Laplace's 99.99 % ellipse across it, LOCAL_SPACING apart; no point, or one that misses a
    parameter, places nothing."""
    from types import SimpleNamespace

    from solderpyro.design.loop import LOCAL_SPACING
    from solderpyro.pipeline.adaptive import REFIT_WIDEN, refit_design

    box = Box(("a", "b"), (0.0, 10.0), (1.0, 30.0))
    A = np.array([[1.0, 1.0], [1.0, 1.02], [0.5, 0.5], [2.0, 2.01]]) * 4.0  # d y / d u
    sig = 0.01
    u_true = np.array([0.4, 0.55])

    def observed(rows):
        u = box.to_unit(torch.as_tensor(rows, dtype=torch.float64)).numpy()
        return u @ A.T

    y = torch.as_tensor(u_true @ A.T)
    sm = SimpleNamespace(space=box, gp_box=box, n_fe=2, y=y, observed=observed,
                         priors=SimpleNamespace(sigma_known=sig))
    x_true = box.from_unit(torch.as_tensor(u_true[None])).numpy()[0]
    point = {"a": float(x_true[0]), "b": float(x_true[1]), "sigma": sig}
    have = lhs(box, 6, 0)
    rows = refit_design(sm, point, have, 12, seed=1)
    assert rows is not None and 6 <= len(rows) <= 12
    u = box.to_unit(rows).numpy()
    np.testing.assert_allclose(u[0], u_true, atol=1e-6)  # the refit itself first
    H = A.T @ A / sig**2  # the exact Laplace precision of the linear toy
    d = u - u_true
    m2 = np.einsum("ij,jk,ik->i", d, H, d) / REFIT_WIDEN**2
    assert m2.max() < 18.4  # chi2(2) 99.99 %: inside the widened ellipse
    ridge = np.linalg.eigh(H)[1][:, 0]  # the weakest direction: along the ridge
    along, across = np.abs(d @ ridge), np.abs(d @ np.array([-ridge[1], ridge[0]]))
    assert along.max() > 20 * across.max()
    allu = np.vstack([box.to_unit(have).numpy(), u])
    dist = np.linalg.norm(allu[:, None] - allu[None], axis=-1) + np.eye(len(allu))
    assert dist.min() >= LOCAL_SPACING
    assert refit_design(sm, None, have, 12) is None
    assert refit_design(sm, {"a": point["a"]}, have, 12) is None
    assert refit_design(sm, point, have, 0) is None


def test_stop_rule_tolerance_is_the_chi_square_sampling_sd():
    s = LoopSettings()
    code_ok, fe_ok, tol = stop_rule(1.0, np.array([100.0]), np.array([100.0 + 19.9]), 200, s)
    assert tol == pytest.approx(math.sqrt(400)) and code_ok and fe_ok
    assert not stop_rule(21.0, np.array([1.0]), np.array([1.0]), 200, s)[0]
    assert not stop_rule(1.0, np.array([np.inf]), np.array([1.0]), 200, s)[1]


def test_stop_rule_rejects_a_gap_that_tilts_the_posterior():
    """A gap common to every checked draw only rescales the likelihood (the posterior is
    unchanged); one that varies by more than ``fe_spread`` across them moves the posterior:
    the weight of one draw against another is off by exp(spread / 2)."""
    s = LoopSettings()
    sur = np.array([2000.0, 2004.0, 2010.0, 2002.0])
    assert stop_rule(1.0, sur + 3.0, sur, 2232, s)[1]  # level only: the same posterior
    assert stop_rule(1.0, sur + np.array([-0.9, 0.0, 0.9, 0.5]), sur, 2232, s)[1]
    assert not stop_rule(1.0, sur + np.array([-2.5, -2.5, 3.7, -2.0]), sur, 2232, s)[1]
    with pytest.raises(ValueError, match="design.fe_spread"):
        LoopSettings(fe_spread=0.0).validate(2)
    with pytest.raises(ValueError, match="design.check_ends"):
        LoopSettings(check=4, check_ends=3).validate(2)


def test_check_draws_include_the_ends_of_a_ridge():
    """On an elongated cloud (a ridge along (1, 1) in the unit box) the two end checks are
    the draws at the 1 % and 99 % points along it; the rest spread through the chains; all
    distinct."""
    from solderpyro.design.loop import check_indices

    rng = np.random.default_rng(3)
    t = rng.standard_normal(8000)
    unit = 0.5 + np.column_stack([0.1 * t, 0.1 * t]) + 0.002 * rng.standard_normal((8000, 2))
    idx = check_indices(unit, 4, 2)
    assert len(idx) == 4 and len(set(idx.tolist())) == 4
    along = t[idx[:2]]
    assert sorted(along) == pytest.approx(np.quantile(t, [0.01, 0.99]), abs=0.05)
    assert not np.isin(idx[2:], idx[:2]).any()
    assert check_indices(unit, 4, 0).tolist() == [0, 2666, 5333, 7999]


def test_a_crash_between_rounds_loses_no_fe_run_and_the_rerun_continues_from_the_store():
    """The FE runs are kept as they finish (here: a cache standing in for the run store); a
    run that dies after round 1 and is started again proposes the same runs (every step is
    seeded) and solves only what round 1 did not."""
    s = LoopSettings(start=4, batch=2, check=2, budget=20, mc_points=100, candidates=200)
    full_calls: list = []
    full = run_loop(_toy_problem(bias=0.05, calls=full_calls, cache={}), s, seed=0)
    cache: dict = {}
    calls: list = []

    class Crash(Exception):
        pass

    def die(r):
        if len(r.rounds) == 1:
            raise Crash

    with pytest.raises(Crash):
        run_loop(_toy_problem(bias=0.05, calls=calls, cache=cache), s, seed=0, on_round=die)
    n_first = len(calls)
    assert n_first == s.start + s.check + s.batch  # nothing lost: all in the cache
    calls2: list = []
    again = run_loop(_toy_problem(bias=0.05, calls=calls2, cache=cache), s, seed=0)
    assert len(calls2) == len(full_calls) - n_first  # only the rounds not done before
    torch.testing.assert_close(again.X, full.X)


def test_bad_settings_name_the_field():
    with pytest.raises(ValueError, match="design.start"):
        LoopSettings(start=2).validate(4)
    with pytest.raises(ValueError, match="design.criterion"):
        LoopSettings(criterion="ei").validate(4)
    with pytest.raises(ValueError, match="design.budget"):
        LoopSettings(start=30, budget=10).validate(4)


def test_default_budget_grows_a_round_per_fe_parameter_past_five(monkeypatch):
    """The default budget: 110 runs up to five FE parameters, one round (batch + check runs)
    more per parameter past them; a budget that is set is kept as it is, and the loop runs
    under (says, and records) the budget for its own box's dimension."""
    from solderpyro.design.loop import BASE_BUDGET, BUDGET_DIMS

    s = LoopSettings()
    assert s.budget is None and (BASE_BUDGET, BUDGET_DIMS) == (110, 5)
    assert [s.runs_allowed(d) for d in (4, 5, 6, 9)] == [110, 110, 122, 158]
    assert LoopSettings(batch=4, check=2).runs_allowed(7) == 110 + 2 * 6
    assert LoopSettings(budget=80).runs_allowed(9) == 80
    assert LoopSettings(start=200).runs_allowed(4) == 204  # at least one round past the start
    import solderpyro.design.loop as loop_module

    monkeypatch.setattr(loop_module, "BASE_BUDGET", 20)  # a short toy run
    toy = _toy_problem(bias=0.05)  # never converges: runs to the budget of its dimension
    s = LoopSettings(start=4, batch=2, check=3, mc_points=100, candidates=200)
    res = design_rounds(toy, s, seed=0)
    allowed = s.runs_allowed(toy.box.dim)
    assert res.reason == "budget" and f"of {allowed} runs" in res.message
    assert allowed - (s.batch + s.check) < len(res.X) <= allowed
    # the record (run.json's design) says the budget used, not the setting's None
    assert res.budget == allowed == res.as_dict()["budget"]


def test_cli_config_overrides_reach_the_settings():
    """``solderpyro calibrate ... calibration.design.code_tol=X`` used to be accepted by the
    config and dropped by the command (the settings were built from the flags alone)."""
    from solderpyro.cli import _settings, _setup, _split_overrides, build_parser
    from solderpyro.config.settings import CalibrationSettings

    p = build_parser()
    argv = ["calibrate", "--data", "d.csv", "--out", "o", "--chains", "2",
            "calibration.design.code_tol=0.5", "calibration.sampler.draws=77",
            "calibration.exact.mode=off"]
    a, rest = p.parse_known_args(argv)
    ov = _split_overrides(rest)
    s = _settings(a, _setup(ov), ov)
    assert (s.design.code_tol, s.sampler.draws, s.exact.mode) == (0.5, 77, "off")
    assert s.sampler.chains == 2  # a flag still works beside the config
    a, rest = p.parse_known_args(["calibrate", "--data", "d.csv", "--out", "o",
                                  "--draws", "55", "calibration.sampler.draws=77"])
    ov = _split_overrides(rest)
    assert _settings(a, _setup(ov), ov).sampler.draws == 55  # the given flag wins
    a, rest = p.parse_known_args(["calibrate", "--data", "d.csv", "--out", "o",
                                  "surrogate.truncation=0.05"])  # was dropped too
    ov = _split_overrides(rest)
    assert _settings(a, _setup(ov), ov).surrogate.truncation == 0.05
    a, _ = p.parse_known_args(["calibrate", "--data", "d.csv", "--out", "o"])
    s0 = _settings(a, _setup([]), [])
    assert s0 == CalibrationSettings(surrogate=s0.surrogate, progress=s0.progress)


def test_the_final_posteriors_coordinates_and_ess_bar_are_settings():
    """The final posterior's NUTS options: the ridge map where it applies (as the design
    rounds) unless ``sampler.final_ridge`` is off; both settings reach the calibration from
    the config; so does the discretization correction's mode; bad values are named."""
    from solderpyro.cli import _settings, _setup, _split_overrides, build_parser
    from solderpyro.config.settings import CalibrationSettings, SamplerSettings
    from solderpyro.pipeline.posterior import nuts_options

    assert nuts_options(SamplerSettings(final_ridge=False), 0, False, True)["ridge"] == "never"
    final = nuts_options(SamplerSettings(), 0, False, final=True)
    assert "ridge" not in final and final["mapped_accept"] == 0.95
    assert "mapped_accept" not in nuts_options(SamplerSettings(), 0, False, final=False)
    assert "ridge" not in nuts_options(SamplerSettings(), 0, False, final=False)
    p = build_parser()
    a, rest = p.parse_known_args(["calibrate", "--data", "d.csv", "--out", "o",
                                  "calibration.sampler.min_ess=0",
                                  "calibration.sampler.max_rhat=1.02",
                                  "calibration.sampler.final_ridge=false"])
    ov = _split_overrides(rest)
    s = _settings(a, _setup(ov), ov)
    assert (s.sampler.min_ess, s.sampler.max_rhat, s.sampler.final_ridge) == (0, 1.02, False)
    assert SamplerSettings().max_rhat == 1.01  # the loop benchmark's bar, the default
    with pytest.raises(ValueError, match="sampler.min_ess"):
        CalibrationSettings(sampler=SamplerSettings(min_ess=-1)).validate()
    with pytest.raises(ValueError, match="sampler.max_rhat"):
        CalibrationSettings(sampler=SamplerSettings(max_rhat=0.99)).validate()
    with pytest.raises(ValueError, match="sampler.final_accept"):
        CalibrationSettings(sampler=SamplerSettings(final_accept=1.0)).validate()
    with pytest.raises(ValueError, match="sampler.final_ridge"):
        CalibrationSettings(sampler=SamplerSettings(final_ridge="yes")).validate()  # type: ignore
    # the discretization correction: on by default, "check" from the command line
    assert CalibrationSettings().discretization == "correct"
    a, rest = p.parse_known_args(["calibrate", "--data", "d.csv", "--out", "o",
                                  "calibration.discretization=check"])
    ov = _split_overrides(rest)
    assert _settings(a, _setup(ov), ov).discretization == "check"
    with pytest.raises(ValueError, match="discretization must be one of"):
        CalibrationSettings(discretization="fix").validate()
