"""What the data cannot rule out (diagnose.ruleout): on a linear model with a known answer.

Eight values, two constants with outputs J theta; an effect whose signature the constants can
mimic exactly (a multiple of J's first column) fits as well at any magnitude, and the constants
it implies are the posterior mean less what they absorb; an effect the constants cannot mimic
is rejected once its chi-square rise passes 3.84; an absorbed effect whose shift stays inside
the intervals is not reported; the intervals that admit a hidden effect hold the truth.
"""

import numpy as np
import pytest

from solderpyro.diagnose.ruleout import REJECT, Constants, admitting, cannot_rule_out, describe

SIGMA = 0.05


def consts(lower, upper, draws, intervals):
    """The constants "a" and "b" as the calibration reported them."""
    return Constants(["a", "b"], lower, upper, draws, intervals)
N = 8


def _case(seed: int = 0):
    rng = np.random.default_rng(seed)
    j = np.stack([np.linspace(1.0, 2.0, N), np.cos(np.arange(N))], 1)  # (8, 2) um per unit
    theta0 = np.array([1.0, 0.5])
    v0 = j @ theta0
    y = v0 + SIGMA * rng.standard_normal(N)
    lower, upper = np.array([-10.0, -10.0]), np.array([10.0, 10.0])
    # posterior draws of the linear-Gaussian model (flat prior; the box is far)
    cov = np.linalg.inv(j.T @ j / SIGMA**2)
    mean = theta0 + cov @ j.T @ (y - v0) / SIGMA**2
    draws = rng.multivariate_normal(mean, cov, 20000)
    q = np.quantile(draws, [0.025, 0.975], 0)
    intervals = {"a": (q[0, 0], q[1, 0]), "b": (q[0, 1], q[1, 1])}
    return j, theta0, v0, y, lower, upper, draws, intervals


def test_a_mimicked_effect_is_reported_with_the_constants_it_implies():
    j, theta0, v0, y, lower, upper, draws, intervals = _case()
    mags = np.array([0.1, 0.3, 1.0])
    lad = {"mimic": (mags, v0[None, :] + mags[:, None] * 0.2 * j[:, 0][None, :])}
    out = cannot_rule_out(y, v0, j, SIGMA, lad, consts(lower, upper, draws, intervals))
    assert [r["effect"] for r in out] == ["mimic"]
    r = out[0]
    assert r["value"] == 1.0 and abs(r["chi2_rise"]) < 1e-6  # absorbed entirely
    assert r["outside"] == ["a"]
    # the constant a absorbs 0.2 per unit magnitude: the true a is 0.2 lower (the box prior's
    # pull, variance 400/12 against the data's ~1e-3, is below 1e-4 of it)
    mean_a, moved_a, clipped = r["moves"]["a"]
    assert moved_a == pytest.approx(mean_a - 0.2, abs=1e-3) and not clipped
    assert r["moves"]["b"][1] == pytest.approx(r["moves"]["b"][0], abs=1e-3)
    assert "mimic at k = 1" in describe(r, "k", "")


def test_an_effect_the_constants_cannot_mimic_is_rejected_past_its_first_rungs():
    j, theta0, v0, y, lower, upper, draws, intervals = _case()
    e = np.zeros(N)
    e[::2], e[1::2] = 1.0, -1.0
    e -= j @ np.linalg.lstsq(j, e, rcond=None)[0]  # orthogonal to J's columns
    e /= np.linalg.norm(e)
    # chi2 rises by (a / sigma)^2 for a signature a e (unit norm): 0.5 sigma -> 0.25, far past
    # 3.84 at 10 sigma; a mimicked part 0.3 J[:, 1] rides along, outside b's interval
    mags = np.array([0.5, 10.0])
    rows = v0[None, :] + (mags[:, None] * SIGMA) * e[None, :] + 0.3 * j[:, 1][None, :]
    out = cannot_rule_out(y, v0, j, SIGMA, {"part": (mags, rows)},
                          consts(lower, upper, draws, intervals))
    assert len(out) == 1 and out[0]["value"] == 0.5  # the 10-sigma rung is rejected
    rise = out[0]["chi2_rise"]
    assert rise < REJECT and rise == pytest.approx(
        float((e @ (y - v0) * -2 * 0.5 * SIGMA + (0.5 * SIGMA) ** 2) / SIGMA**2), abs=1e-3)
    rows_far = v0[None, :] + (mags[:, None] * SIGMA) * e[None, :]
    far = cannot_rule_out(y, v0, j, SIGMA, {"part": (mags[1:], rows_far[1:])},
                          consts(lower, upper, draws, intervals))
    assert far == []


def test_a_small_absorbed_shift_inside_the_intervals_is_not_reported():
    j, theta0, v0, y, lower, upper, draws, intervals = _case()
    half_width = 0.5 * (intervals["a"][1] - intervals["a"][0])
    small = 0.2 * half_width  # moves a by a fifth of its half-width
    lad = {"small": (np.array([1.0]), (v0 + small * j[:, 0])[None, :])}
    assert cannot_rule_out(y, v0, j, SIGMA, lad, consts(lower, upper, draws, intervals)) == []


def test_a_shift_past_the_box_is_clipped_and_says_so():
    j, theta0, v0, y, lower, upper, draws, intervals = _case()
    lad = {"big": (np.array([1.0]), (v0 + 30.0 * j[:, 0])[None, :])}
    out = cannot_rule_out(y, v0, j, SIGMA, lad, consts(lower, upper, draws, intervals))
    mean_a, moved_a, clipped = out[0]["moves"]["a"]
    assert clipped and moved_a == lower[0]
    assert "the box's edge" in describe(out[0], "k", "MPa")


def test_below_a_rejected_first_rung_the_boundary_magnitude_is_found():
    """A signature the constants mimic in part (0.3 J[:, 1]) plus a part they cannot (e):
    at magnitude 1 the rise is far past 3.84, so the rung alone says nothing; with "off" at
    0 the magnitude where the rise reaches 3.84 is found (the rise is exactly quadratic in
    it here), and the mimicked part at that magnitude moves b outside its interval."""
    j, theta0, v0, y, lower, upper, draws, intervals = _case()
    e = np.zeros(N)
    e[::2], e[1::2] = 1.0, -1.0
    e -= j @ np.linalg.lstsq(j, e, rcond=None)[0]
    e /= np.linalg.norm(e)
    sig = 10.0 * SIGMA * e + 3.0 * j[:, 1]  # per unit magnitude
    lad = {"part": (np.array([1.0]), (v0 + sig)[None, :])}
    c = consts(lower, upper, draws, intervals)
    assert cannot_rule_out(y, v0, j, SIGMA, lad, c) == []  # the rung is rejected
    out = cannot_rule_out(y, v0, j, SIGMA, lad, c, offs={"part": 0.0})
    assert len(out) == 1 and out[0]["outside"] == ["b"]
    t = out[0]["value"]
    # brute force: the rise at t, by refitting the constants exactly (least squares, the box
    # prior negligible), is 0.999 x 3.84, and b moves by 3 t less what it absorbs (all of it)
    r0, r1 = y - v0, y - v0 - t * sig
    chi = [float(np.sum((r - j @ np.linalg.lstsq(j, r, rcond=None)[0]) ** 2)) / SIGMA**2
           for r in (r0, r1)]
    assert chi[1] - chi[0] == pytest.approx(0.999 * REJECT, rel=1e-3)
    assert out[0]["chi2_rise"] == pytest.approx(0.999 * REJECT, abs=2e-3)
    mean_b, moved_b, _ = out[0]["moves"]["b"]
    assert moved_b == pytest.approx(mean_b - 3.0 * t, abs=1e-3)


def test_the_intervals_that_admit_a_mimicked_hidden_effect_hold_the_truth():
    """Data made with the effect present (its signature 0.2 J[:, 0] per unit magnitude, at
    magnitude 1): fitted without it, a's interval sits 0.2 too high (about 4 of its sd) and
    misses the true a; the effect is named, and the interval admitting it (stretched down by
    the 0.2 it would move a) is the exact posterior's interval under "present" joined to
    "absent", so it holds the truth at 95 %. 200 noise seeds: binomial sd 0.015, bar 3 sd."""
    held, held_reported = 0, 0
    for seed in range(200):
        rng = np.random.default_rng(seed)
        j = np.stack([np.linspace(1.0, 2.0, N), np.cos(np.arange(N))], 1)
        theta0 = np.array([1.0, 0.5])
        y = j @ theta0 + 0.2 * j[:, 0] + SIGMA * rng.standard_normal(N)
        cov = np.linalg.inv(j.T @ j / SIGMA**2)
        mean = cov @ j.T @ y / SIGMA**2  # the fit without the effect, flat prior
        draws = rng.multivariate_normal(mean, cov, 4000)
        q = np.quantile(draws, [0.025, 0.975], 0)
        intervals = {"a": (q[0, 0], q[1, 0]), "b": (q[0, 1], q[1, 1])}
        v0 = j @ mean
        mags = np.array([0.3, 1.0])
        lad = {"mimic": (mags, v0[None, :] + mags[:, None] * 0.2 * j[:, 0][None, :])}
        c = consts(np.array([-10.0, -10.0]), np.array([10.0, 10.0]), draws, intervals)
        found = cannot_rule_out(y, v0, j, SIGMA, lad, c)
        assert [r["effect"] for r in found] == ["mimic"]
        adm = admitting(c, found)
        lo, hi = intervals["a"]
        assert adm["a"][0] == pytest.approx(lo - 0.2, abs=2e-3) and adm["a"][1] == hi
        assert adm["b"] == pytest.approx(intervals["b"], abs=2e-3)  # b is not moved
        held += adm["a"][0] <= theta0[0] <= adm["a"][1]
        held_reported += lo <= theta0[0] <= hi
    assert held / 200 > 0.95 - 0.045 and held_reported / 200 < 0.05


def test_nothing_to_admit_gives_no_intervals_and_the_box_bounds_them():
    j, theta0, v0, y, lower, upper, draws, intervals = _case()
    c = consts(lower, upper, draws, intervals)
    assert admitting(c, []) == {}
    lad = {"big": (np.array([1.0]), (v0 + 30.0 * j[:, 0])[None, :])}
    adm = admitting(c, cannot_rule_out(y, v0, j, SIGMA, lad, c))
    assert adm["a"][0] == lower[0] and adm["a"][1] == intervals["a"][1]
