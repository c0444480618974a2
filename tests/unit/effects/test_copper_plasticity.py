"""copper_plasticity's hooks (solderpyro.effects.copper_plasticity): the elastic copper
(infinite yield stress, baseline path) at and above the off value, the member's own yield
stress below it, the band's settings, and the bounds' checks."""

import math

import pytest
import torch

from solderpyro.effects import EFFECTS, EffectSet
from solderpyro.effects.base import PlasticBand
from solderpyro.effects.copper_plasticity import CopperPlasticity

F64 = torch.float64
EFF = EFFECTS["copper_plasticity"]


def test_yield_stress_is_infinite_at_off_and_the_members_own_below():
    """sigma_y_cu >= 400 MPa (off): inf, an elastic band (the baseline path); below: the value
    itself, per member, through the EffectSet seam too."""
    assert EFF.off == (400.0,)
    q = torch.tensor([[400.0], [1e4], [399.0], [15.0]], dtype=F64)
    sy = EFF.yield_stress(q)
    assert torch.isinf(sy[:2]).all() and sy[2].item() == 399.0 and sy[3].item() == 15.0
    assert torch.equal(EffectSet(["copper_plasticity"]).yield_stress(q), sy)


def test_band_settings_and_log_prior_box():
    """The band: copper within 1.75 mm of the solder, H = 1000 MPa, elastic at 400 MPa; the
    prior is log-uniform on [15, 400] MPa, so its unit-cube midpoint is sqrt(15 * 400)."""
    assert EFF.plastic_band() == PlasticBand("copper", 1.75, 1000.0, 400.0)
    b = EFF.params
    assert b.lower == (15.0,) and b.upper == (400.0,) and b.log_scale == (True,)
    mid = b.from_unit(torch.tensor([[0.5]], dtype=F64)).item()
    assert mid == pytest.approx(math.sqrt(15.0 * 400.0), rel=1e-12)


def test_bad_values_are_rejected():
    with pytest.raises(ValueError, match="sigma_y_cu must be > 0"):
        EFF.check(torch.tensor([[0.0]], dtype=F64))
    with pytest.raises(ValueError, match="need depth > 0, H >= 0, sigma_off > 0"):
        CopperPlasticity(depth=0.0)
    with pytest.raises(ValueError, match="need depth > 0"):
        CopperPlasticity(H=-1.0)
