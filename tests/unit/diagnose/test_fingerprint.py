"""Fingerprints of candidate effects (solderpyro.diagnose.fingerprint) with refits for some
candidates and not for others, on point data: each candidate's source, the decomposition
residual = fingerprint + residual after, and the Pearson shape correlation. The denoised
full-field case and the all-refit case are in tests/unit/diagnose/test_denoise.py."""

from types import SimpleNamespace

import numpy as np
import pytest

from solderpyro.diagnose.fingerprint import fingerprints


def test_mixed_refit_and_linearised_candidates_on_point_data():
    """With a baseline refit, a candidate with its own refit gets V_c - V_0 (source
    "refit") and one without gets its score-test pattern (source "linearised"); both against
    the residual y - V_0, whatever linearised residual is passed; residual = fingerprint +
    after exactly for both; the correlation is Pearson's over the values (scale-free: a
    fingerprint 3x the residual's shape correlates 1, its negative -1)."""
    rng = np.random.default_rng(0)
    n = 8
    y = rng.standard_normal(n)
    V0 = y - np.linspace(-1.0, 1.0, n)  # residual y - V0 = linspace(-1, 1)
    res = y - V0
    meas = SimpleNamespace(x_mm=np.full(n, 15.0), y_mm=np.zeros(n), time_s=np.arange(n) * 600.0,
                           value_um=y)
    scores = [SimpleNamespace(effect="refit_one", pattern=np.zeros(n)),
              SimpleNamespace(effect="lin_one", pattern=-3.0 * res)]
    preds = {"baseline": V0, "refit_one": V0 + 3.0 * res}
    fp = fingerprints(meas, rng.standard_normal(n), scores, 0.05, preds=preds, field_data=False)
    assert fp.source == {"refit_one": "refit", "lin_one": "linearised"}
    np.testing.assert_allclose(fp.residual, res, rtol=0, atol=1e-15)
    np.testing.assert_allclose(fp.signature["refit_one"], 3.0 * res, rtol=0, atol=1e-14)
    np.testing.assert_array_equal(fp.signature["lin_one"], -3.0 * res)
    for e in ("refit_one", "lin_one"):
        np.testing.assert_allclose(fp.signature[e] + fp.after[e], fp.residual, atol=1e-14)
    assert fp.correlation["refit_one"] == pytest.approx(1.0, abs=1e-14)
    assert fp.correlation["lin_one"] == pytest.approx(-1.0, abs=1e-14)
    assert fp.smooth is None and fp.smooth_after == {}


def test_without_refits_everything_is_linearised_against_the_given_residual():
    """No predictions: the residual shown is the linearised one passed in, every candidate's
    fingerprint its pattern, and a constant fingerprint correlates 0 (no shape) to rounding."""
    n = 6
    r = np.array([0.1, -0.2, 0.3, 0.0, 0.05, -0.1])
    meas = SimpleNamespace(x_mm=np.zeros(n), y_mm=np.zeros(n), time_s=np.zeros(n),
                           value_um=np.ones(n))
    scores = [SimpleNamespace(effect="flat", pattern=np.full(n, 0.2)),
              SimpleNamespace(effect="half", pattern=0.5 * r)]
    fp = fingerprints(meas, r, scores, 0.05, preds=None, field_data=False)
    np.testing.assert_array_equal(fp.residual, r)
    assert set(fp.source.values()) == {"linearised"}
    np.testing.assert_allclose(fp.after["half"], 0.5 * r, atol=1e-16)
    assert abs(fp.correlation["flat"]) < 1e-12  # rounding of the mean of equal values
    assert fp.correlation["half"] == pytest.approx(1.0, abs=1e-14)
