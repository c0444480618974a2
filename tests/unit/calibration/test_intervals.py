"""The reported 95 % interval: central, or from a box face the posterior piles against."""

import arviz as az
import numpy as np
import pytest
from scipy import stats

from solderpyro.calibration.intervals import (
    CENTRAL,
    LOWER_FACE,
    UPPER_FACE,
    credible_interval,
    reported_interval,
    weighted_quantiles,
    with_intervals,
    with_monte_carlo_error,
)
from solderpyro.params import Box


def test_a_posterior_away_from_the_faces_keeps_its_central_interval() -> None:
    x = np.random.default_rng(0).normal(5.0, 0.5, 20_000)
    iv = credible_interval(x, 0.0, 10.0)
    assert iv.kind == CENTRAL
    assert (iv.lo, iv.hi) == pytest.approx(tuple(np.quantile(x, [0.025, 0.975])), rel=1e-12)


@pytest.mark.parametrize("face", ["lower", "upper"])
def test_a_posterior_piled_against_a_face_starts_there_and_is_arvizs_hdi(face: str) -> None:
    # an exponential marginal falling from the face: its shortest 95 % interval (the HDI)
    # runs from the face to the 95 % point; ArviZ's HDI of the draws is the same interval but
    # for the face itself, which no draw reaches
    e = np.random.default_rng(1).exponential(0.3, 40_000)
    e = e[e < 3.0]
    x = 2.0 + e if face == "lower" else 5.0 - e
    iv = credible_interval(x, 2.0, 5.0)
    hdi = az.hdi(x, hdi_prob=0.95)
    if face == "lower":
        assert iv.kind == LOWER_FACE and iv.lo == 2.0
        assert iv.hi == pytest.approx(np.quantile(x, 0.95), rel=1e-12)
    else:
        assert iv.kind == UPPER_FACE and iv.hi == 5.0
        assert iv.lo == pytest.approx(np.quantile(x, 0.05), rel=1e-12)
    # the same interval as the HDI, within the draws' spacing at its far end (~0.3 / 40,000
    # * 20 * a few) and the gap between the face and the nearest draw (~1e-5)
    assert iv.lo == pytest.approx(hdi[0], abs=0.01) and iv.hi == pytest.approx(hdi[1], abs=0.01)
    # the central interval would exclude the face, where the density is highest
    assert not (np.quantile(x, 0.025) <= (2.0 if face == "lower" else 5.0)
                <= np.quantile(x, 0.975))


def test_a_ridge_that_only_runs_toward_a_face_keeps_its_central_interval() -> None:
    # mode inside (0.7), the upper tail cut by the face at 1: the shortest 95 % interval
    # (ArviZ's HDI) runs to the face and gives up the lower tail, though the face is not where
    # the posterior is densest; the reported interval stays central (the Q/R ridge of the
    # copper recalibration, docs/calibration.md)
    x = stats.truncnorm.rvs(-3.5, 1.5, loc=0.7, scale=0.2, size=40_000,
                            random_state=np.random.default_rng(7))
    iv = credible_interval(x, 0.0, 1.0)
    assert iv.kind == CENTRAL
    hdi = az.hdi(x, hdi_prob=0.95)
    assert hdi[1] > 0.995 and hdi[0] > iv.lo + 0.05  # 0.365 against 0.304


def test_the_densest_half_is_sought_on_the_boxs_log_scale() -> None:
    # log-uniform between 15 and 400 is flat on the box's scale: the central interval stays;
    # in plain units the densest half would be the one at 15 MPa
    x = np.exp(np.random.default_rng(2).uniform(np.log(15.0), np.log(400.0), 50_000))
    assert credible_interval(x, 15.0, 400.0, log_scale=True).kind == CENTRAL
    # and a marginal falling from 15 MPa on the log scale starts at 15
    y = 15.0 * np.exp(np.random.default_rng(3).exponential(0.01, 20_000))
    iv = credible_interval(y, 15.0, 400.0, log_scale=True)
    assert iv.kind == LOWER_FACE and iv.holds(15.0)


def test_a_marginal_flat_at_the_face_starts_there_whichever_first_window_noise_makes_narrowest(
) -> None:
    # 60 % of the draws flat over the first 1 % (log scale) above 15 MPa, the rest falling
    # beyond: the windows holding half the draws that start within the flat part tie, and with
    # this seed the narrowest starts at the 2.5 % point (without the tie the rule
    # keeps the central interval, which excludes the face the density is highest at)
    rng = np.random.default_rng(0)
    u = np.concatenate([rng.uniform(0.0, 0.01, 12_000), 0.01 + rng.exponential(0.01, 8_000)])
    y = 15.0 * np.exp(u)
    p = np.linspace(0.0, 0.5, 101)
    q = np.quantile(np.log(y), np.concatenate([p, p + 0.5]))
    width = q[101:] - q[:101]
    assert int(np.argmin(width)) > 0 and width[0] <= 1.02 * width.min()
    iv = credible_interval(y, 15.0, 400.0, log_scale=True)
    assert iv.kind == LOWER_FACE and iv.holds(15.0)
    assert iv.hi == pytest.approx(np.quantile(y, 0.95), rel=1e-12)


def test_weighted_draws_give_the_resampled_interval() -> None:
    rng = np.random.default_rng(4)
    x = rng.uniform(0.0, 1.0, 200_000)
    w = np.exp(-x / 0.1)  # importance weights of an exponential target on the uniform draws
    w /= w.sum()
    iv = credible_interval(x, 0.0, 1.0, weights=w)
    exact_q95 = -0.1 * np.log(1.0 - 0.95 * (1.0 - np.exp(-10.0)))  # truncated exponential
    assert iv.kind == LOWER_FACE and iv.lo == 0.0
    assert iv.hi == pytest.approx(exact_q95, rel=0.02)


def test_the_reported_intervals_cover_truths_drawn_from_the_prior_at_95_percent() -> None:
    """Each candidate holds 95 % of the posterior, so choosing among them by the draws keeps
    the coverage of prior-drawn truths at 95 %: a uniform prior on [0, 1], y ~ N(mu, 0.3),
    exact truncated-normal posteriors (about half of them piled against a face)."""
    rng = np.random.default_rng(5)
    reps, s = 2000, 0.3
    hits, faces, hits_at_face = 0, 0, 0
    for _ in range(reps):
        mu = rng.uniform()
        y = rng.normal(mu, s)
        a, b = (0.0 - y) / s, (1.0 - y) / s
        x = stats.truncnorm.rvs(a, b, loc=y, scale=s, size=4000, random_state=rng)
        iv = credible_interval(x, 0.0, 1.0)
        # every reported interval is a 95 % credible set (4,000 draws: quantile steps 2.5e-4)
        assert abs(np.mean((x >= iv.lo) & (x <= iv.hi)) - 0.95) < 1e-3
        hits += iv.holds(mu)
        faces += iv.kind != CENTRAL
        # a truth at the face the data point toward (the copper case's geometry)
        hits_at_face += iv.holds(0.0 if y < 0.5 else 1.0) if iv.kind != CENTRAL else 0
    # binomial sd of the coverage over 2,000 replications: 0.0049; 3 sd
    assert abs(hits / reps - 0.95) < 0.015
    assert faces > 0.2 * reps  # the face-anchored intervals are really exercised
    assert hits_at_face == faces  # every face-anchored interval holds its face


def test_with_intervals_adds_the_columns_and_leaves_the_noise_sd_central() -> None:
    box = Box(("a", "b"), (0.0, 1.0), (1.0, 100.0), log_scale=(False, True))
    rng = np.random.default_rng(6)
    th = np.column_stack([rng.exponential(0.01, 5000) % 1.0,
                          np.exp(rng.uniform(np.log(20.0), np.log(30.0), 5000))])
    rows = [{"parameter": "a", "q2.5": 0.0003, "q97.5": 0.037},
            {"parameter": "sigma", "q2.5": 0.04, "q97.5": 0.06},
            {"parameter": "b", "q2.5": 20.2, "q97.5": 29.8}]
    out = with_intervals(rows, th, box)
    assert [r["interval"] for r in out] == [LOWER_FACE, CENTRAL, CENTRAL]
    assert out[0]["lo95"] == 0.0 and reported_interval(out[1]) == (0.04, 0.06)
    assert "lo95" not in rows[0]  # the input rows are not changed
    assert reported_interval({"q2.5": "1", "q97.5": "2"}) == (1.0, 2.0)  # older runs


@pytest.mark.parametrize("kw, msg", [
    ({"x": np.array([])}, "no draws"),
    ({"level": 1.0}, "level"),
    ({"lower": 0.6}, "outside the box"),
    ({"lower": -1.0, "log_scale": True}, "lower > 0"),
])
def test_bad_input_is_named(kw: dict, msg: str) -> None:
    args = {"x": np.linspace(0.5, 0.9, 10), "lower": 0.0, "upper": 1.0, **kw}
    with pytest.raises(ValueError, match=msg):
        credible_interval(**args)


def test_weighted_quantiles_match_repeated_samples():
    x = np.array([1.0, 2.0, 3.0, 4.0])
    # equal weights: the median is the ordinary median
    assert abs(weighted_quantiles(x, np.ones(4), (0.5,))[0] - 2.5) < 1e-12
    # weight 3 on 4.0 (as if it were drawn three times) moves the median to 4.0's side
    assert weighted_quantiles(x, np.array([1.0, 1.0, 1.0, 3.0]), (0.5,))[0] > 3.0


def _rows(theta: np.ndarray, box: Box) -> list[dict]:
    q = np.quantile(theta, [0.025, 0.975], axis=0)
    return with_intervals([{"parameter": nm, "q2.5": q[0, k], "q97.5": q[1, k]}
                           for k, nm in enumerate(box.names)], theta, box)


def test_the_likelihood_hull_leaves_a_normal_posterior_alone():
    """Draws of a 3-d normal posterior (flat prior, correlated) and their exact log-likelihood:
    no draw whose log-likelihood is within 1.92 of the best lies beyond 1.96 sd in any
    parameter (its own term alone is 1.92 there), so no interval widens beyond
    LIKELIHOOD_GAIN."""
    from solderpyro.calibration.intervals import LIKELIHOOD, likelihood_hull

    rng = np.random.default_rng(3)
    cov = np.array([[1.0, 0.6, 0.2], [0.6, 1.0, 0.3], [0.2, 0.3, 1.0]])
    x = rng.multivariate_normal(np.zeros(3), cov, size=4000)
    ll = -0.5 * np.einsum("ij,jk,ik->i", x, np.linalg.inv(cov), x)
    box = Box(("a", "b", "c"), (-10.0,) * 3, (10.0,) * 3, (False,) * 3)
    rows = _rows(x, box)
    out = likelihood_hull(rows, x, ll, box)
    assert [r["interval"] for r in out] == [r["interval"] for r in rows]
    assert all(r["interval"] != LIKELIHOOD for r in out)
    assert [(r["lo95"], r["hi95"]) for r in out] == [(r["lo95"], r["hi95"]) for r in rows]


def test_the_likelihood_hull_holds_the_low_end_of_a_ridge_the_prior_volume_leaves_out():
    """A ridge the data leave open: the likelihood is flat in a over [0, 1] (b is what the data
    measure), while the draws pile toward a = 1 (density 4 a^3, as the box's volume along a
    ridge makes them). The central interval starts near a = 0.4 and misses a truth at 0.2;
    the hull holds every draw, down to the smallest (about 0.03 for 3,000 draws)."""
    from solderpyro.calibration.intervals import LIKELIHOOD, likelihood_hull

    rng = np.random.default_rng(4)
    n = 3000
    a = rng.random(n) ** 0.25  # density 4 a^3 on [0, 1]
    b = 0.5 + 0.01 * rng.standard_normal(n)
    x = np.column_stack([a, b])
    ll = -0.5 * ((b - 0.5) / 0.01) ** 2
    box = Box(("a", "b"), (0.0, 0.0), (1.0, 1.0), (False, False))
    rows = _rows(x, box)
    assert rows[0]["lo95"] > 0.3  # the credible interval misses a = 0.2
    out = likelihood_hull(rows, x, ll, box)
    assert out[0]["interval"] == LIKELIHOOD
    keep = ll >= ll.max() - 1.92
    assert out[0]["lo95"] == pytest.approx(a[keep].min(), abs=0) and out[0]["lo95"] < 0.2
    assert out[1] == rows[1]  # b's interval is the data's: unchanged
    with pytest.raises(ValueError, match="likelihood_hull"):
        likelihood_hull(rows, x, ll[:-1], box)


def test_the_profile_hull_holds_the_fes_profile_where_the_surrogates_interval_is_off():
    """A mean a measured by n = 400 values of noise sd 1 (the truth 0): the FE's profile
    interval is exactly the mean +- 1.96 / 20. A surrogate posterior biased by 3 of its sd
    (0.15) misses the truth; the hull with the profile holds it, is marked ``profile`` and
    is no narrower. A profile inside the interval, or one that adds less than
    LIKELIHOOD_GAIN of its width, leaves the row alone; a parameter without a profile (the
    noise sd) is unchanged."""
    from solderpyro.calibration.intervals import LIKELIHOOD_GAIN, PROFILE, profile_hull

    rng = np.random.default_rng(5)
    y = rng.standard_normal(400)
    half = 1.959963984540054 / 20.0
    prof = (float(y.mean() - half), float(y.mean() + half))
    assert prof[0] < 0.0 < prof[1]
    sur = y.mean() + 0.15 + half * rng.standard_normal(4000) / 1.96  # biased by 3 sd
    box = Box(("a",), (-5.0,), (5.0,))
    rows = _rows(sur[:, None], box) + [{"parameter": "sigma", "lo95": 0.9, "hi95": 1.1,
                                        "interval": CENTRAL}]
    assert rows[0]["lo95"] > 0.0  # the surrogate's interval misses the truth
    out = profile_hull(rows, {"a": prof})
    assert out[0]["interval"] == PROFILE and out[0]["lo95"] == prof[0] < 0.0
    assert out[0]["hi95"] == rows[0]["hi95"] and out[1] == rows[1]
    inner = (rows[0]["lo95"] + 1e-3, rows[0]["hi95"] - 1e-3)
    assert profile_hull(rows, {"a": inner}) == rows
    w = rows[0]["hi95"] - rows[0]["lo95"]
    small = (rows[0]["lo95"] - 0.5 * LIKELIHOOD_GAIN * w, rows[0]["hi95"])
    assert profile_hull(rows, {"a": small})[0] == rows[0]


def _normal_importance_rows(rng: np.random.Generator, n: int, scale: float
                            ) -> tuple[list[dict], np.ndarray, np.ndarray, Box]:
    """Importance samples of N(0, 1) from N(0, scale^2): rows with the weighted central
    interval, the draws ``(n, 1)``, their normalized weights, a box far around them."""
    x = rng.normal(0.0, scale, n)
    w = np.exp(stats.norm.logpdf(x) - stats.norm.logpdf(x, scale=scale))
    w /= w.sum()
    box = Box(("a",), (-20.0,), (20.0,))
    q = weighted_quantiles(x, w, (0.025, 0.975))
    rows = with_intervals([{"parameter": "a", "q2.5": q[0], "q97.5": q[1]}], x[:, None], box,
                          weights=w)
    return rows, x[:, None], w, box


def test_interval_ends_at_a_small_ess_are_moved_out_by_their_monte_carlo_error() -> None:
    """At a Kish ESS near 50 the weighted 2.5 % point lies inside the exact one about half
    the time; moved out by its Monte Carlo standard error it holds it about 84 % of the time
    (one standard error, one side). 400 replications: binomial sd 0.025 at 0.5, 0.018 at
    0.84; the bars are 4 sd from the expected rates."""
    rng = np.random.default_rng(11)
    z = stats.norm.ppf(0.975)
    reps, held, held_raw, ess = 400, np.zeros(2), np.zeros(2), []
    for _ in range(reps):
        rows, x, w, box = _normal_importance_rows(rng, 100, 2.5)
        ess.append(1.0 / (w @ w))
        moved = with_monte_carlo_error(rows, x, w, box)[0]
        held += [moved["lo95"] <= -z, moved["hi95"] >= z]
        held_raw += [rows[0]["lo95"] <= -z, rows[0]["hi95"] >= z]
        assert moved["lo95"] <= rows[0]["lo95"] and moved["hi95"] >= rows[0]["hi95"]
    assert 40 < np.median(ess) < 70  # the regime of the FE-exact posteriors it is for
    assert np.all(held / reps > 0.84 - 0.07)
    assert np.all(held_raw / reps < 0.5 + 0.1)


def test_the_monte_carlo_move_is_arvizs_quantile_mcse_for_equal_weights() -> None:
    """Equal weights of iid draws (ESS = n): the move is ArviZ's ``mcse(method="quantile")``
    of the same end (both read the spread of the order statistics within one binomial sd of
    the end's probability; ArviZ rounds them outward to whole ranks: 2,000 draws, 2 % of the
    move) and vanishes as n grows like 1 / sqrt(n)."""
    rng = np.random.default_rng(12)
    box = Box(("a",), (-20.0,), (20.0,))
    moves = {}
    for n in (2000, 32000):
        x = rng.normal(size=n)
        w = np.full(n, 1.0 / n)
        rows = with_intervals([{"parameter": "a", "q2.5": 0.0, "q97.5": 0.0}], x[:, None], box)
        moved = with_monte_carlo_error(rows, x[:, None], w, box)[0]
        moves[n] = rows[0]["lo95"] - moved["lo95"]
        if n == 2000:
            ref = float(az.mcse(x[None], method="quantile", prob=0.025))
            assert moves[n] == pytest.approx(ref, rel=0.15)
    assert moves[32000] == pytest.approx(moves[2000] / 4.0, rel=0.3)


def test_a_face_is_not_moved_and_a_moved_end_stays_in_the_box() -> None:
    rng = np.random.default_rng(13)
    x = np.abs(rng.normal(0.0, 0.2, 400))[:, None]  # piled against the lower face at 0
    box = Box(("a",), (0.0,), (1.0,))
    w = np.full(400, 1.0 / 400)
    rows = with_intervals([{"parameter": "a", "q2.5": 0.0, "q97.5": 0.0}], x, box)
    assert rows[0]["interval"] == LOWER_FACE
    moved = with_monte_carlo_error(rows, x, w, box)[0]
    assert moved["lo95"] == 0.0 and moved["hi95"] > rows[0]["hi95"]
    # an upper bound between the end and where it would move to: the end stops there
    top = 0.5 * (rows[0]["hi95"] + moved["hi95"])
    clipped = with_monte_carlo_error(rows, x, w, Box(("a",), (0.0,), (top,)))[0]
    assert clipped["hi95"] == top
    with pytest.raises(ValueError, match="weights"):
        with_monte_carlo_error(rows, x, np.zeros(400), box)
    with pytest.raises(ValueError, match="theta has shape"):
        with_monte_carlo_error(rows, x, w[:10], box)
