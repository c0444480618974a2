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
