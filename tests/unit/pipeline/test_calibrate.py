"""The calibration's own findings from its summary rows (solderpyro.pipeline.calibrate)."""

from __future__ import annotations

from solderpyro.params import Box
from solderpyro.pipeline.calibrate import pressed_constants

BOX = Box(("s0", "QR", "xi", "m"), (5.0, 7000.0, 1.0, 0.05), (25.0, 13000.0, 5.0, 0.5))


def _rows(ivs: dict[str, tuple[float, float, str]]) -> list[dict]:
    mid = {"s0": (10.0, 20.0), "QR": (9000.0, 11000.0), "xi": (1.5, 3.0), "m": (0.1, 0.3),
           "sigma": (0.049, 0.051), "T_sf": (90.0, 110.0)}
    out = []
    for p, (lo, hi) in mid.items():
        lo, hi, kind = ivs.get(p, (lo, hi, "central"))
        out.append({"parameter": p, "lo95": lo, "hi95": hi, "interval": kind})
    return out


def test_constants_pressed_against_faces_are_a_finding_named_first():
    """The residual-stress field data (T_sf 100 degC, Newton cool-down) calibrated without the
    effect, as measured: s0 [22.1, 25], Q/R [12,556, 13,000], xi [1, 1.13] (14, 7 and 3 % of
    their boxes, each from a face) at 1.02 noise sd: the finding names all three and sends
    the user to diagnose."""
    text = pressed_constants(_rows({"s0": (22.14, 25.0, "upper face"),
                                    "QR": (12555.7, 13000.0, "upper face"),
                                    "xi": (1.0, 1.129, "lower face")}), BOX)
    assert text.startswith("s0 (upper face), QR (upper face), xi (lower face)")
    assert "solderpyro diagnose" in text


def test_wide_intervals_at_faces_one_face_or_an_effect_parameter_are_no_finding():
    """A posterior spread over most of the box touches faces without pressing on them (the
    correct residual-stress recalibration, measured: s0 from its lower face over 87 % of the
    box, xi over 52 %); one constant at a face can be a physical limit; effects' parameters are
    not material constants; a widened interval is not a face."""
    assert pressed_constants(_rows({"s0": (5.0, 22.4, "lower face"),
                                    "xi": (1.0, 3.08, "lower face")}), BOX) == ""
    assert pressed_constants(_rows({"xi": (1.0, 1.1, "lower face")}), BOX) == ""
    assert pressed_constants(_rows({"xi": (1.0, 1.1, "lower face"),
                                    "T_sf": (170.0, 183.0, "upper face")}), BOX) == ""
    assert pressed_constants(_rows({"s0": (24.0, 25.0, "model form"),
                                    "m": (0.05, 0.06, "model form")}), BOX) == ""
    assert pressed_constants(_rows({}), BOX) == ""


def test_the_width_is_measured_on_the_box_scale():
    """m on a log-scale box: [0.05, 0.08] spans log(1.6)/log(10) = 20 % of it (pressed), though
    only 7 % of its linear width; [0.05, 0.15] spans 48 % (not pressed)."""
    box = Box(BOX.names, BOX.lower, BOX.upper, log_scale=(False, False, False, True))
    qr = {"QR": (12600.0, 13000.0, "upper face")}
    assert pressed_constants(_rows({**qr, "m": (0.05, 0.08, "lower face")}), box)
    assert not pressed_constants(_rows({**qr, "m": (0.05, 0.15, "lower face")}), box)
