"""Misfit statistics: exact identities for linear models and their null distributions."""

import numpy as np
import pytest
from scipy import stats

from solderpyro.diagnose.stats import confusion, misfit, predictive_check, score_test


def _linear(rng, n=14, p=4, k=2):
    return rng.standard_normal((n, p)), rng.standard_normal((n, k))


def _chi2_refit(y, J, w):
    """min over beta of sum w (y - J beta)^2 (weighted least squares)."""
    sw = np.sqrt(w)
    beta = np.linalg.lstsq(sw[:, None] * J, sw * y, rcond=None)[0]
    return float((w * (y - J @ beta) ** 2).sum())


def test_score_equals_chi2_drop_for_linear_model():
    """For a linear model the score statistic is exactly the drop of the refitted chi-square."""
    rng = np.random.default_rng(0)
    Jt, Je = _linear(rng)
    w = rng.uniform(0.5, 2.0, 14)
    y = Jt @ rng.standard_normal(4) + Je @ np.array([0.7, -0.3]) + rng.standard_normal(14)
    theta_hat = rng.standard_normal(4)  # any linearisation point: P removes the offset
    r = y - Jt @ theta_hat
    sc = score_test("e", r, Jt, Je, w)
    drop = _chi2_refit(y, Jt, w) - _chi2_refit(y, np.hstack([Jt, Je]), w)
    assert sc.statistic == pytest.approx(drop, rel=1e-10)
    assert sc.dof == 2
    assert sc.chi2_after == pytest.approx(_chi2_refit(y, np.hstack([Jt, Je]), w), rel=1e-9)
    mf = misfit(r, Jt, w)
    assert mf.chi2 == pytest.approx(_chi2_refit(y, Jt, w), rel=1e-10)
    assert mf.dof == 10


def test_score_null_distribution_is_chi2():
    """Without the effect in the data, S ~ chi2(k): KS over 3000 replications."""
    rng = np.random.default_rng(1)
    Jt, Je = _linear(rng)
    w = np.full(14, 4.0)  # sigma = 0.5
    S = [score_test("e", Jt @ rng.standard_normal(4) + 0.5 * rng.standard_normal(14),
                    Jt, Je, w).statistic for _ in range(3000)]
    assert stats.kstest(S, stats.chi2(2).cdf).pvalue > 1e-3
    assert np.mean(S) == pytest.approx(2.0, abs=0.15)  # sd of the mean: 2/sqrt(3000) = 0.037


def test_confounded_effect_has_no_evidence():
    """An effect that the calibrated parameters can mimic exactly is not identifiable."""
    rng = np.random.default_rng(2)
    Jt, _ = _linear(rng)
    Je = Jt @ np.array([[1.0], [0.5], [0.0], [-2.0]])
    sc = score_test("e", rng.standard_normal(14), Jt, Je, np.ones(14))
    assert sc.identifiable < 1e-8 and sc.dof == 0 and sc.p_value == 1.0


def test_confusion_of_equivalent_and_orthogonal_effects():
    rng = np.random.default_rng(3)
    Jt, Je = _linear(rng, k=1)
    r, w = rng.standard_normal(14), np.ones(14)
    a = score_test("a", r, Jt, Je, w)
    b = score_test("b", r, Jt, 3.0 * Je + Jt[:, :1], w)  # same signature once theta refits
    assert confusion(a, b) == pytest.approx(1.0, abs=1e-10)
    P = np.eye(14) - Jt @ np.linalg.pinv(Jt)
    e2 = P @ rng.standard_normal(14)
    e2 -= (P @ Je[:, 0]) * ((P @ Je[:, 0]) @ e2) / ((P @ Je[:, 0]) @ (P @ Je[:, 0]))
    c = score_test("c", r, Jt, e2[:, None], w)
    assert confusion(a, c) < 1e-8


def test_predictive_check_calibrated_model_has_uniform_pit():
    """Data drawn from the predictive itself: PIT ~ U(0, 1) and p-values ~ U(0, 1)."""
    rng = np.random.default_rng(4)
    n, nd = 8, 400
    pits, ps = [], []
    for _ in range(150):
        mu = rng.standard_normal(n)
        process = mu + 0.1 * rng.standard_normal((nd, n))  # code uncertainty
        sigma = np.full(nd, 0.3)
        y = mu + 0.1 * rng.standard_normal(n) + 0.3 * rng.standard_normal(n)
        pc = predictive_check(y, process, sigma, seed=1)
        pits.append(pc.pit)
        ps.append(pc.p_value)
    assert stats.kstest(np.concatenate(pits), "uniform").pvalue > 1e-3
    # the ppp-value is conservative (not exactly uniform) but must not reject a true model
    assert np.mean(np.array(ps) < 0.05) < 0.08


def test_predictive_check_flags_shifted_data():
    rng = np.random.default_rng(5)
    process = 0.05 * rng.standard_normal((400, 8))
    y = np.full(8, 0.5)  # 10 noise sd away
    pc = predictive_check(y, process, np.full(400, 0.05))
    assert pc.p_value == 0.0 and np.all(pc.z > 5)


def test_predictive_check_rejects_bad_shapes():
    with pytest.raises(ValueError, match="process"):
        predictive_check(np.zeros(3), np.zeros((5, 4)), np.ones(5))
    with pytest.raises(ValueError, match="sigma"):
        predictive_check(np.zeros(3), np.zeros((5, 3)), np.zeros(5))


def test_likelihood_ratio_ladder_is_bounded_by_the_score_for_a_linear_effect():
    """For a linear effect the chi-square drop at any magnitude is at most the score statistic
    (the drop at the optimal magnitude) and equals it at that magnitude."""
    from solderpyro.diagnose.screen import likelihood_ratio

    rng = np.random.default_rng(6)
    Jt, Je = _linear(rng, k=1)
    w = np.full(14, 4.0)
    y = Jt @ rng.standard_normal(4) + 0.8 * Je[:, 0] + 0.5 * rng.standard_normal(14)
    sc = score_test("e", y, Jt, Je, w)
    mags = np.array([0.0, 0.5 * sc.delta[0], sc.delta[0], 2.0 * sc.delta[0]])
    lr = likelihood_ratio(misfit(y, Jt, w).chi2, y, mags[:, None] * Je[:, 0][None], Jt, w)
    assert lr[0] == pytest.approx(0.0, abs=1e-9)
    assert lr[2] == pytest.approx(sc.statistic, rel=1e-9)
    assert np.all(lr <= sc.statistic + 1e-9)
