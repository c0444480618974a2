"""The calibration's settings: bad values are refused with the field's name."""

import pytest

from solderpyro.config.settings import CalibrationSettings, ExactSettings


@pytest.mark.parametrize("field, value, match", [
    ("extra_rounds", -1, "exact.extra_rounds"),
    ("rounds", 0, "rounds >= 1"),
    ("mode", "sometimes", "exact.mode"),
    ("profile_ci", "maybe", "exact.profile_ci"),
])
def test_a_bad_exact_setting_is_named(field, value, match):
    s = CalibrationSettings(exact=ExactSettings(**{field: value}))
    with pytest.raises(ValueError, match=match):
        s.validate()


def test_the_default_exact_settings_are_valid_and_allow_extra_rounds():
    s = CalibrationSettings().validate()
    assert s.exact.extra_rounds == 3 and s.exact.rounds == 3
