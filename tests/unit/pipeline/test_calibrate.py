"""The calibration's own findings from its summary rows (solderpyro.pipeline.calibrate)."""

from __future__ import annotations

from solderpyro.params import Box
from solderpyro.pipeline.calibrate import pressed_constants

BOX = Box(("s0", "QR", "xi", "m"), (5.0, 7000.0, 1.0, 0.05), (25.0, 13000.0, 5.0, 0.5))


def _rows(ivs: dict[str, tuple[float, float]]) -> list[dict]:
    mid = {"s0": (10.0, 20.0), "QR": (9000.0, 11000.0), "xi": (1.5, 3.0), "m": (0.1, 0.3),
           "sigma": (0.049, 0.051), "T_sf": (90.0, 110.0)}
    return [{"parameter": p, "lo95": ivs.get(p, v)[0], "hi95": ivs.get(p, v)[1],
             "interval": "central"} for p, v in mid.items()]


def test_constants_pressed_against_faces_are_a_finding_named_first():
    """The residual-stress field data (T_sf 100 degC, Newton cool-down) calibrated without the
    effect, at 1.02 noise sd, as measured from the FE-exact posterior: s0 [22.35, 25],
    Q/R [12,506, 12,981] and xi [1.002, 1.161], 13, 8 and 4 % of their boxes, the last two
    ending just short of their faces (true 10, 11,000, 1.5): the finding names all three and
    sends the user to diagnose."""
    text = pressed_constants(_rows({"s0": (22.35, 25.0), "QR": (12506.1, 12981.4),
                                    "xi": (1.0019, 1.1607)}), BOX)
    assert text.startswith("s0 (upper face), QR (upper face), xi (lower face)")
    assert "solderpyro diagnose" in text


def test_wide_or_inner_intervals_one_constant_or_an_effect_parameter_are_no_finding():
    """A posterior spread over most of the box touches faces without pressing on them (the
    correct residual-stress recalibration, measured: s0 [5.1, 23.7], xi [1.03, 3.81]); narrow
    intervals away from the faces are a well-determined fit; one constant at a face can be a
    physical limit; effects' parameters are not material constants."""
    assert pressed_constants(_rows({"s0": (5.11, 23.66), "xi": (1.028, 3.81)}), BOX) == ""
    assert pressed_constants(_rows({"s0": (12.0, 13.0), "QR": (10400.0, 10800.0)}), BOX) == ""
    assert pressed_constants(_rows({"xi": (1.0, 1.1)}), BOX) == ""
    assert pressed_constants(_rows({"xi": (1.0, 1.1), "T_sf": (170.0, 183.0)}), BOX) == ""
    assert pressed_constants(_rows({}), BOX) == ""


def test_the_nearness_and_width_are_measured_on_the_box_scale():
    """m on a log-scale box (a decade): [0.05, 0.08] spans log(1.6) / log(10) = 20 % of it
    (pressed), though only 7 % of its linear width; [0.05, 0.15] spans 48 % (not pressed);
    [0.051, 0.08] ends 0.9 % of the log box above the face (pressed), and [0.06, 0.08] 7.9 %
    (not)."""
    box = Box(BOX.names, BOX.lower, BOX.upper, log_scale=(False, False, False, True))
    qr = {"QR": (12600.0, 13000.0)}
    assert pressed_constants(_rows({**qr, "m": (0.05, 0.08)}), box)
    assert not pressed_constants(_rows({**qr, "m": (0.05, 0.15)}), box)
    assert pressed_constants(_rows({**qr, "m": (0.051, 0.08)}), box)
    assert not pressed_constants(_rows({**qr, "m": (0.06, 0.08)}), box)


def test_the_report_names_the_acquisition_that_ran():
    """The default (closed-form greedy choice among posterior draws) is named as such, never
    as BoTorch; BoTorch's optimizer is named where it ran; both name the settings."""
    from solderpyro.design.loop import LoopSettings
    from solderpyro.pipeline.calibrate import acquisition_text

    default = acquisition_text(LoopSettings())
    assert "closed form among the posterior draws" in default and "BoTorch" not in default
    assert "criterion=loglik" in default and "optimizer=draws" in default
    other = acquisition_text(LoopSettings(criterion="variance", optimizer="optimize"))
    assert "optimize_acqf" in other and "integrated variance" in other


def test_where_neither_posterior_holds_the_fe_best_fit_is_reported(tmp_path):
    """The design's budget ran out with the FE misfitting the surrogate's posterior (3.5 noise
    sd at its draws) and the FE-exact weights unreliable: the report gives the FE's own best
    fit, from the better of the FE-exact step's fit and its best importance sample. On a line
    fitted to a line with noise that is the least-squares optimum (numpy.polyfit), at about 1
    noise sd, so no misfit remains: the surrogate's misfit line and its model-form file go,
    its summary is kept in summary_surrogate.csv, and the trust line says what is reported."""
    from dataclasses import replace
    from types import SimpleNamespace

    import numpy as np
    import torch

    from solderpyro.config.settings import CalibrationSettings
    from solderpyro.pipeline.calibrate import (
        FeChecked,
        Reported,
        RunOutputs,
        remaining_misfit,
        unconfirmed_stage,
    )

    s_ = np.linspace(0.0, 1.0, 200)
    box = Box(("a", "b"), (0.0, 0.0), (2.0, 2.0))

    def line(rows: np.ndarray) -> np.ndarray:
        return rows[:, :1] + rows[:, 1:2] * s_

    rng = np.random.default_rng(3)
    y = 1.0 + 0.7 * s_ + 0.05 * rng.standard_normal(s_.size)
    cp = SimpleNamespace(space=box, y=torch.as_tensor(y), observed=line,
                         setup=SimpleNamespace(space=SimpleNamespace(defaults={})))
    checked = FeChecked(0.05, np.zeros((4, 2)), np.arange(4), np.zeros((4, 200)),
                        {"ok": False, "rms_over_sigma": 3.5, "n": 200})
    w = RunOutputs(None, None, tmp_path, replace(CalibrationSettings(), seed=0), None, cp,
                   SimpleNamespace(budget=110), None, torch.zeros(200), checked, {}, None, None)
    stale = remaining_misfit(3.5, 200, 2)
    (tmp_path / "model_form.json").write_text("{}")
    surrogate_rows = [{"parameter": nm, "q2.5": 0.1, "median": 0.2, "mean": 0.2,
                       "q97.5": 0.3, "lo95": 0.1, "hi95": 0.3, "interval": "central",
                       "r_hat": 1.0, "ess_bulk": 400.0, "ess_tail": 400.0}
                      for nm in ("a", "b", "sigma")]
    rep = Reported(surrogate_rows, None, ["the design's budget ran out", stale], "surrogate")
    # the FE-exact step's LM fit is far off; one importance sample lies near the optimum
    samples = np.array([[0.3, 1.8], [1.02, 0.66], [1.9, 0.1]])
    ssr = ((line(samples) - y) ** 2).sum(1)
    ex = SimpleNamespace(samples=samples, result=SimpleNamespace(extra={"ssr": ssr}))
    info = {"best_fit": {"x": [1.6, 0.1], "ssr_um2": float(((line(
        np.array([[1.6, 0.1]])) - y) ** 2).sum())}}
    w2, out = unconfirmed_stage(w, rep, ex, info)
    b, a = np.polyfit(s_, y, 1)
    np.testing.assert_allclose(w2.fit.x, [a, b], atol=2e-3)  # a linear model: LM's optimum
    assert [r["median"] for r in out.rows[:2]] == list(w2.fit.x)
    assert all(np.isnan(r["r_hat"]) for r in out.rows)
    assert out.trust.startswith("the FE's own best fit (") and "3.50 noise sd" in out.trust
    assert "raise --budget (it was 110 FE runs) for a posterior" in out.trust
    assert stale not in out.problems and "the design's budget ran out" in out.problems
    assert not (tmp_path / "model_form.json").exists()  # no misfit remains at ~1 noise sd
    assert (tmp_path / "summary_surrogate.csv").exists()
    # the FE's predictive at the fit and its Laplace draws: the fit's own line first
    np.testing.assert_allclose(out.bands.draws[0].numpy(), line(w2.fit.x[None])[0])
    assert out.bands.draws.shape[0] >= 2


def test_a_surrogate_posterior_misses_the_fe_best_fit_by_more_than_its_own_spread():
    """A posterior draw's chi-square exceeds the optimum's by chi2(dim) near a Gaussian mode:
    8 parameters, 2,240 values: 4,775 against 2,770 (the forms benchmark's linear modulus with
    a lag) misses; 20 more than the fit (inside chi2(8)'s 99.9 % point, 26.1) does not; a
    check that misfits always does."""
    import numpy as np

    from solderpyro.pipeline.calibrate import misses_best_fit

    n = 2240

    def rms(c2: float) -> float:
        return float(np.sqrt(c2 / n))

    fit = {"rms_over_sigma": rms(2770.0)}
    assert misses_best_fit({"ok": True, "n": n, "rms_over_sigma": rms(4775.0)}, fit, 8)
    assert not misses_best_fit({"ok": True, "n": n, "rms_over_sigma": rms(2790.0)}, fit, 8)
    assert misses_best_fit({"ok": True, "n": n, "rms_over_sigma": rms(2800.0)}, fit, 8)
    assert misses_best_fit({"ok": False, "n": n, "rms_over_sigma": rms(2771.0)}, fit, 8)
