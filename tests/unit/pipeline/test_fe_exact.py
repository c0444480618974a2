"""The automatic FE-exact step stops at the FE's own best fit when the model cannot fit the
data (pipeline.fe_exact: ``stop_if_misfit``), and runs on when it can."""

import numpy as np
import torch

from solderpyro.calibration import Priors
from solderpyro.exact.coords import UnitCoords
from solderpyro.params import Box
from solderpyro.pipeline.fe_check import FE_CHECK_RMS, misfits
from solderpyro.pipeline.fe_exact import ExactRun, fe_exact

BOX = Box(("a", "b"), (0.0, 0.0), (2.0, 2.0))
S = np.linspace(0.0, 1.0, 200)


def _fun(rows: np.ndarray) -> np.ndarray:
    """A two-parameter line a + b s on 200 points: ``(k, 2) -> (k, 200)``."""
    return rows[:, :1] + rows[:, 1:2] * S


def _run(y: np.ndarray):
    starts = np.array([[1.0, 1.0], [0.8, 1.2]])
    return fe_exact(_fun, UnitCoords(BOX), torch.as_tensor(y), Priors(sigma_known=0.05), None,
                    starts, ExactRun(32, 1, 0, seed=0, n_draws=200, stop_if_misfit=True))


def test_a_model_that_cannot_fit_stops_at_its_best_fit():
    rng = np.random.default_rng(0)
    # a curvature the line lacks: 2 s^2 leaves an RMS 2 / sqrt(180) = 0.15 um (3 noise sd)
    y = 1.0 + 0.5 * S + 2.0 * S**2 + 0.05 * rng.standard_normal(S.size)
    ex, info = _run(y)
    assert ex is None and "misses something" in info["stopped"]
    assert info["best_fit"]["rms_over_sigma"] > FE_CHECK_RMS
    assert "rounds" not in info and "ess" not in info  # no importance-sampling round ran


def test_with_sigma_unknown_the_rule_measures_the_misfit_in_the_noise_sd():
    """Without a known sigma the fits use the RMS at the first start as their noise sd, in
    which no best fit can misfit; the rule takes the posterior's noise sd instead."""
    rng = np.random.default_rng(0)
    y = 1.0 + 0.5 * S + 2.0 * S**2 + 0.05 * rng.standard_normal(S.size)
    ex, info = fe_exact(_fun, UnitCoords(BOX), torch.as_tensor(y), Priors(sigma_max=1.0), None,
                        np.array([[1.0, 1.0], [0.8, 1.2]]),
                        ExactRun(32, 1, 0, seed=0, n_draws=200, stop_if_misfit=True,
                                 noise_sd=0.05))
    assert ex is None and info["best_fit"]["rms_over_sigma"] > FE_CHECK_RMS


def test_a_model_that_fits_runs_the_exact_posterior():
    rng = np.random.default_rng(1)
    y = 1.0 + 0.7 * S + 0.05 * rng.standard_normal(S.size)
    ex, info = _run(y)
    assert ex is not None and "stopped" not in info
    assert info["best_fit"]["rms_over_sigma"] < 1.2  # noise only: about 1
    assert info["fe_runs"] >= 32


def test_misfit_rule_needs_both_a_large_rms_and_a_large_chi2():
    n = 2240
    assert not misfits(1.0 * n, n)  # noise
    assert misfits(4.0 * n, n)  # 2 noise sd RMS
    assert misfits(float("inf"), n)
    assert not misfits(3.0 * 4, 4)  # RMS 1.7 sd on 4 values: inside chi2(4)'s 99.9 %


def test_a_model_that_cannot_fit_reports_its_best_fit_with_a_widened_spread():
    """For a model that misfits, the reported result is the FE's own least-squares fit with
    the Laplace covariance scaled by chi2 / (n - dim): on a line fitted to a parabola that is
    the ordinary least-squares answer (numpy.polyfit's scaled covariance)."""
    from solderpyro.pipeline.fe_exact import BestFitOptions, best_fit_posterior

    rng = np.random.default_rng(2)
    y = 1.0 + 0.5 * S + 2.0 * S**2 + 0.05 * rng.standard_normal(S.size)
    box = Box(("a", "b"), (0.0, 0.0), (3.0, 4.0))  # the optimum (0.67, 2.5) inside
    # from near the optimum (the design's LM fit): one more step finds it (a linear model)
    fit = best_fit_posterior(_fun, UnitCoords(box), np.array([0.7, 2.4]), y, 0.05,
                             BestFitOptions(n_draws=4000, seed=0))
    (b, a), cov = np.polyfit(S, y, 1, cov=True)  # cov scaled by the residual variance
    assert np.allclose(fit.x, [a, b], atol=2e-3)  # LM from a near start: the LS optimum
    chi2 = float(np.sum((y - a - b * S) ** 2)) / 0.05**2
    assert abs(fit.scale - np.sqrt(chi2 / (S.size - 2))) < 1e-2 * fit.scale
    sd = np.sqrt(np.diag(cov))[::-1]  # (a, b)
    half = np.array([(r["q97.5"] - r["q2.5"]) / 2 for r in fit.rows[:2]])
    # 4000 draws: the 95 % half-width to ~3 %
    np.testing.assert_allclose(half, 1.96 * sd, rtol=0.08)
    assert [r["median"] for r in fit.rows[:2]] == list(fit.x)
    assert fit.rows[-1]["parameter"] == "sigma"
    assert abs(fit.sigma[0] - 0.05 * fit.scale) < 1e-12


def test_profile_intervals_are_not_attempted_where_every_profile_is_flat():
    """12 parameters on 8 values (point data with the Moire offsets): each profile refits 11
    parameters to 8 values, flat at every value; 5 on 8 (copper plasticity) and 8 on 8 can be
    profiled."""
    from solderpyro.pipeline.calibrate import unprofilable

    msg = unprofilable(12, 8)
    assert msg is not None and "12 parameters on 8 values" in msg
    assert unprofilable(9, 8) is not None
    assert unprofilable(5, 8) is None and unprofilable(8, 8) is None


def test_automatic_profile_intervals_stop_where_they_would_cost_thousands_of_fe_runs():
    """Eight parameters (four constants and two two-parameter effects) are profiled by
    default; sixteen (three effects with the Moire offsets) would take about 7,200 FE runs and
    are not, and the reason names how to ask for them."""
    from solderpyro.pipeline.calibrate import PROFILE_RUNS, too_costly_to_profile

    assert too_costly_to_profile(6) == "" and too_costly_to_profile(8) == ""
    msg = too_costly_to_profile(16)
    assert f"{16 * PROFILE_RUNS:,} FE runs" in msg and "--profile-ci" in msg
    # a misfit remains (model-form intervals): no automatic profiles, whatever the count
    msg = too_costly_to_profile(6, model_form=True)
    assert "misfit remains" in msg and "--profile-ci" in msg


def test_the_unreliable_trust_line_names_profile_intervals_only_where_they_are_computed():
    """With unreliable FE-exact weights the trust line points to profile_ci.csv only where the
    profiles run: not with profile_ci=off, and with the reason where they would cost too
    much."""
    from solderpyro.pipeline.calibrate import too_costly_to_profile, unreliable_trust

    assert "profile_ci.csv" in unreliable_trust("", "auto")
    off = unreliable_trust("", "off")
    assert "profile_ci.csv" not in off and "profile_ci=off" in off
    costly = too_costly_to_profile(16)
    assert unreliable_trust(costly, "auto").endswith(costly)
    assert "raise --budget (it was 158 FE runs)" in unreliable_trust("", "auto", 158)


class _Sliver(UnitCoords):
    """The unit cube, but only a sliver of it (|u_a - u_b| < 1e-6) counts as inside: a box
    that the best fit's Laplace spread barely reaches, as the flow-stress coordinates' box does
    at a corner of the Anand constants."""

    def inside(self, w: np.ndarray) -> np.ndarray:
        w = np.atleast_2d(w)
        return super().inside(w) & (np.abs(w[:, 0] - w[:, 1]) < 1e-6)


def test_a_best_fit_whose_spread_barely_reaches_inside_the_box_still_reports_intervals():
    """The line's least-squares optimum (5, 4) lies outside the box [0, 2]^2: the fit ends at
    its corner, and hardly any Laplace draw lands inside the sliver. The draws are then clipped
    to the box: every one inside it, the intervals holding the corner, none of them empty."""
    from solderpyro.pipeline.fe_exact import BestFitOptions, best_fit_posterior

    y = 5.0 + 4.0 * S
    fit = best_fit_posterior(_fun, _Sliver(BOX), np.array([1.5, 1.5]), y, 0.05,
                             BestFitOptions(n_draws=500, seed=0))
    np.testing.assert_allclose(fit.x, [2.0, 2.0], atol=1e-9)
    assert len(fit.theta) >= 500 and np.isfinite(fit.theta).all()
    assert (fit.theta >= 0.0).all() and (fit.theta <= 2.0).all()
    for r in fit.rows[:2]:
        assert r["q2.5"] <= 2.0 <= r["q97.5"] and r["lo95"] <= 2.0 <= r["hi95"]


def test_an_effects_own_parameters_are_profiled_where_the_data_leave_its_form_open():
    """The parameters that size an effect are profiled where one of its form parameters is
    weakly identified, and only those; none for an effect without a form parameter."""
    from solderpyro.effects import EffectSet
    from solderpyro.pipeline.calibrate import form_open_parameters

    fx = EffectSet(["stress_free_temperature", "thermal_lag", "moire_rigid_motion"])
    assert form_open_parameters(fx, ["cooldown_shape"]) == ["T_sf"]
    assert form_open_parameters(fx, ["split", "cooldown", "s0"]) == ["T_sf", "tau"]
    assert form_open_parameters(fx, ["T_sf", "s0", "QR"]) == []  # no form left open
    assert form_open_parameters(None, ["cooldown_shape"]) == []


def test_a_reliable_posterior_that_is_too_narrow_is_widened_to_the_profile_of_the_named_parameter(
        tmp_path):
    """profile_stage with named parameters after a reliable FE-exact posterior: on a line
    a + b s (200 points, sd 0.05) the profile interval of ``a`` is the least-squares
    a-hat +- 1.96 sd; a reported interval of ``a`` a fifth as wide becomes the hull, kind
    ``profile``, and the trust line says so; ``b``, not named, keeps its interval, and
    profile_ci.csv holds ``a`` alone."""
    import csv
    from types import SimpleNamespace

    from solderpyro.calibration.intervals import PROFILE
    from solderpyro.pipeline.calibrate import Reported, profile_stage

    rng = np.random.default_rng(3)
    y = 1.0 + 0.7 * S + 0.05 * rng.standard_normal(S.size)
    A = np.stack([np.ones_like(S), S], 1)
    xhat = np.linalg.lstsq(A, y, rcond=None)[0]
    cov = 0.05**2 * np.linalg.inv(A.T @ A)
    sd = np.sqrt(np.diag(cov))
    draws = rng.multivariate_normal(xhat, cov, 256)
    ssr = ((y - _fun(draws)) ** 2).sum(1)
    rows = [{"parameter": nm, "q2.5": xhat[k] - 0.4 * sd[k], "q97.5": xhat[k] + 0.4 * sd[k],
             "lo95": xhat[k] - 0.4 * sd[k], "hi95": xhat[k] + 0.4 * sd[k],
             "interval": "central"} for k, nm in enumerate(("a", "b"))]
    cp = SimpleNamespace(space=BOX, y=torch.as_tensor(y), observed=_fun,
                         priors=Priors(sigma_known=0.05))
    ex = SimpleNamespace(samples=draws, sigma=np.full(256, 0.05), reliable=True,
                         result=SimpleNamespace(extra={"ssr": ssr}))
    info: dict = {}
    rep = profile_stage(cp, tmp_path, Reported(rows, None, [], "the FE-exact posterior"),
                        ex, info, ["a"])
    with open(tmp_path / "profile_ci.csv") as f:
        written = [r["parameter"] for r in csv.DictReader(f)]
    assert written == ["a"] and [p["parameter"] for p in info["profile_ci"]] == ["a"]
    a, b = rep.rows
    assert a["interval"] == PROFILE and b == rows[1]
    # the linear model's profile is a-hat +- 1.96 sd; its ends are interpolated between the
    # grid's points of an exact parabola (0.2 % of the half-width measured; 1 % allowed)
    np.testing.assert_allclose([a["lo95"], a["hi95"]], xhat[0] + np.array([-1.96, 1.96]) * sd[0],
                               atol=0.02 * 1.96 * sd[0])
    assert "the intervals of a hold the FE's profile intervals" in rep.trust
