"""The calibration's own findings from its summary rows (solderpyro.pipeline.calibrate)."""

from __future__ import annotations

from solderpyro.pipeline.calibrate import pressed_constants

ANAND = ("s0", "QR", "xi", "m")


def _rows(kinds: dict[str, str]) -> list[dict]:
    return [{"parameter": p, "interval": kinds.get(p, "central")}
            for p in (*ANAND, "sigma", "T_sf")]


def test_constants_pressed_against_faces_are_a_finding_named_first():
    """The residual-stress field data (T_sf 100 degC, Newton cool-down) calibrated without the
    effect: s0 and Q/R at their upper faces, xi at its lower one (measured), at the noise
    level: the finding names all three and sends the user to diagnose."""
    text = pressed_constants(_rows({"s0": "upper face", "QR": "upper face",
                                    "xi": "lower face"}), ANAND)
    assert text.startswith("s0 (upper face), QR (upper face), xi (lower face)")
    assert "solderpyro diagnose" in text


def test_one_face_or_an_effect_parameter_is_no_finding():
    """One constant at a face can be a physical limit (the modulus(T) recalibration left xi at
    its lower face, measured), and effects' parameters (a cool-down at its face) are not
    material constants."""
    assert pressed_constants(_rows({"xi": "lower face"}), ANAND) == ""
    assert pressed_constants(_rows({"xi": "lower face", "T_sf": "upper face"}), ANAND) == ""
    assert pressed_constants(_rows({}), ANAND) == ""
    assert pressed_constants(_rows({"m": "model form", "s0": "model form"}), ANAND) == ""
