"""The FE check's arithmetic (solderpyro.pipeline.fe_check) on given arrays: the ranking of
draws, chi-square and RMS of the best one, the misfit rule at both of its thresholds, and the
refined problem of the discretization check. The ok/not-ok cases over draws are in
tests/unit/diagnose/test_hidden.py, the refinement's effect on the FE in
tests/verification/test_discretization.py."""

import dataclasses

import numpy as np
import pytest
import torch
from scipy.stats import chi2 as chi2_dist

from solderpyro.fem.loading import TimeStepping
from solderpyro.fem.mesh import Layer, MeshSpec
from solderpyro.pipeline.fe_check import (
    FE_CHECK_QUANTILE,
    FE_CHECK_RMS,
    fe_check,
    misfits,
    ranked,
    refined,
)


def test_ranked_orders_by_squared_residual_with_failed_rows_last():
    y = np.zeros(3)
    V = np.array([[0.3, 0.0, 0.0], [np.nan, 0.0, 0.0], [0.1, 0.1, 0.1],  # 0.09, nan, 0.03
                  [0.0, 0.0, 0.1], [0.0, 0.1, 0.0]])  # 0.01, 0.01 (tie: stable order)
    np.testing.assert_array_equal(ranked(V, y), [3, 4, 2, 0, 1])
    np.testing.assert_array_equal(ranked(V[2], y), [0])  # one row


def test_fe_check_reports_the_best_draws_chi2_and_rms():
    """chi2 = sum((V_best - y)/sigma)^2, rms_um = sqrt(chi2/n) sigma (the RMS residual), its
    ratio to sigma, the best row's index, the draw count (1e-12 relative)."""
    rng = np.random.default_rng(0)
    y = rng.standard_normal(10)
    r_best = 0.04 * rng.standard_normal(10)
    V = np.stack([y + 0.3, y + r_best, np.full(10, np.nan)])
    out = fe_check(V, torch.as_tensor(y), 0.05)
    c2 = float(((r_best / 0.05) ** 2).sum())
    assert out["best"] == 1 and out["draws"] == 3 and out["n"] == 10
    assert out["chi2"] == pytest.approx(c2, rel=1e-12)
    assert out["rms_um"] == pytest.approx(np.sqrt(np.mean(r_best**2)), rel=1e-12)
    assert out["rms_over_sigma"] == pytest.approx(out["rms_um"] / 0.05, rel=1e-12)
    assert out["ok"] is (not misfits(c2, 10))
    none = fe_check(np.full((2, 10), np.nan), torch.as_tensor(y), 0.05)
    assert none["chi2"] == float("inf") and np.isnan(none["rms_um"]) and not none["ok"]


@pytest.mark.parametrize("n", [4, 1000])
def test_misfit_needs_both_the_rms_and_the_chi2_quantile(n):
    """Small n: the chi2(n) 0.999 quantile is the binding limit (RMS 1.5 sd is chi2 = 2.25 n
    = 9 < 18.47 at n = 4); large n: the RMS limit binds (2.25 n = 2250 > 1143 at n = 1000).
    Just below the binding limit passes, just above misfits."""
    q = chi2_dist.ppf(FE_CHECK_QUANTILE, n)
    rms_limit = FE_CHECK_RMS**2 * n
    limit = max(q, rms_limit)
    assert (q > rms_limit) == (n == 4)
    assert not misfits(limit * (1 - 1e-6), n)
    assert misfits(limit * (1 + 1e-6), n)
    assert misfits(float("nan"), n) and not misfits(0.0, n)


@dataclasses.dataclass(frozen=True)
class _Problem:
    """The fields of fem.problem.Problem that ``refined`` changes, and one it keeps."""

    layers: tuple
    mesh: MeshSpec
    stepping: TimeStepping
    plane: str = "stress"


def test_refined_multiplies_elements_and_divides_step_limits():
    """Element rows and columns times 1.5, rounded, at least one more (1 -> 2, 2 -> 3,
    4 -> 6, 30 -> 45); dT_max, dt_max and dwell_dt0 divided by 1.5; the rest unchanged."""
    pr = _Problem((Layer("cu", "copper", -4, 0, 4, 0.25, "top"), Layer("sn", "solder", 0, .5, 1),
                   Layer("st", "steel", .5, 4.5, 2)), MeshSpec(nx=30), TimeStepping())
    fine = refined(pr)
    assert [lay.ny for lay in fine.layers] == [6, 2, 3] and fine.mesh.nx == 45
    assert fine.layers[0].grading == 0.25 and fine.mesh.x_grading == pr.mesh.x_grading
    st, fs = pr.stepping, fine.stepping
    assert (fs.dT_max, fs.dt_max, fs.dwell_dt0) == pytest.approx(
        (st.dT_max / 1.5, st.dt_max / 1.5, st.dwell_dt0 / 1.5), rel=1e-15)
    assert (fs.growth, fs.dep_max, fs.scheme) == (st.growth, st.dep_max, st.scheme)
    assert fine.plane == "stress"
    assert refined(pr, 2.0).mesh.nx == 60


def test_a_misfit_remains_beyond_the_99_percent_point_of_chi2_n_minus_p():
    """The remaining-misfit rule: chi2 at its expectation n - p is no misfit, beyond the 99 %
    point of chi2(n - p) is (here the residual-stress case's 2,613 on 2,232 values, 4
    parameters: RMS 1.08 noise sd, inside the FE check's 1.5 bound); the trust line says so."""
    from scipy.stats import chi2 as chi2_dist

    from solderpyro.pipeline.calibrate import remaining_misfit
    from solderpyro.pipeline.fe_check import misfit_remains

    n, p = 2232, 4
    assert misfit_remains(n - p, n, p) == (False, pytest.approx(chi2_dist.ppf(0.99, n - p)))
    assert misfit_remains(2613.0, n, p)[0]
    assert not misfit_remains(chi2_dist.ppf(0.985, n - p), n, p)[0]
    assert misfit_remains(float("nan"), n, p)[0] is False
    with pytest.raises(ValueError, match="more values than parameters"):
        misfit_remains(3.0, 4, 4)
    text = remaining_misfit((2613.0 / n) ** 0.5, n, p)
    assert "misfit remains" in text and "2228 dof" in text and "diagnose" in text
    assert remaining_misfit(1.0, n, p) == "" and remaining_misfit(None, n, p) == ""


def test_the_discretization_error_is_estimated_where_the_fe_fits_best():
    """At the best checked draw, unless the checked draws miss the design's own FE best fit
    (worse by more than chi2(dim)'s 99.9 % point, 26.1 for 8): then at that fit (its values in
    the order asked); a fit 20 better, an incomplete or a missing one leave the draw; no
    finite draw and no fit: nowhere."""
    import numpy as np

    from solderpyro.params import Box
    from solderpyro.pipeline.adaptive import correction_point

    def box(*names):
        return Box(names, (0.0,) * len(names), (1e5,) * len(names))

    c2 = np.array([50_935.0, np.inf, 48_000.0])
    fit = {"x": {"s0": 23.2, "QR": 13_000.0, "k_E": 0.02}, "chi2": 3_026.6}
    at = correction_point(c2, fit, box("s0", "QR"), 8)
    assert isinstance(at, np.ndarray) and at.tolist() == [23.2, 13_000.0]
    assert correction_point(c2, {**fit, "chi2": 47_980.0}, box("s0", "QR"), 8) == 2
    assert correction_point(c2, {**fit, "chi2": 47_970.0}, box("s0", "QR"), 8) is not None
    assert correction_point(c2, fit, box("s0", "xi"), 8) == 2  # the fit lacks xi
    assert correction_point(c2, None, box("s0"), 8) == 2
    assert correction_point(np.array([np.inf]), None, box("s0"), 8) is None
