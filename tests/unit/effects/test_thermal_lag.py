"""thermal_lag's hook (solderpyro.effects.thermal_lag): the program at tau = 0, and a member
temperature that trails the program by r tau on ramps (a delay of tau), catches up
exponentially on dwells, and is per member. The closed form against an ODE integration is in
tests/verification/test_effects_physics.py."""

import math

import pytest
import torch

from solderpyro.effects import EFFECTS, EffectSet
from solderpyro.fem.loading import REFERENCE_CYCLE

F64 = torch.float64
EFF = EFFECTS["thermal_lag"]
C = REFERENCE_CYCLE
RATE = 5.0 / 60.0  # K/s


def _T(t, taus):
    q = torch.tensor(taus, dtype=F64)[:, None]
    return EFF.temperature(torch.full((len(taus),), C(t), dtype=F64), t, C, q)


def test_off_is_the_program_exactly():
    for t in (0.0, 300.0, 600.0, 2500.0, 7000.0, 7800.0):
        assert torch.equal(_T(t, [0.0]), torch.tensor([C(t)], dtype=F64))


def test_member_temperature_is_the_program_delayed_by_tau_on_a_ramp():
    """First ramp (heating), tau = 60 s: after ~10 tau the member lags by r tau = 5 K, i.e.
    it is at the program's temperature tau earlier (exact up to e^-(t/tau): 1e-4 K at 540 s);
    during cooling it is above the program by the same amount."""
    tau = 60.0
    T = _T(540.0, [tau]).item()
    assert C(540.0) - T == pytest.approx(RATE * tau * (1 - math.exp(-9.0)), rel=1e-12)
    assert T == pytest.approx(C(540.0 - tau), abs=1e-2)
    Tc = _T(7500.0, [tau]).item()  # cooling 6600 -> 7800 s
    assert Tc - C(7500.0) == pytest.approx(RATE * tau, rel=1e-5)


def test_dwell_catches_up_exponentially_and_the_box_top_is_22_K_short():
    """tau = 300 s (box top): at the end of the first ramp the lag is r tau (1 - e^-2) =
    21.6 K ("~22 K short"); during the dwell it decays as e^(-(t - 600)/tau)."""
    tau = EFF.params.upper[0]
    assert tau == 300.0
    e600 = C(600.0) - _T(600.0, [tau]).item()
    assert e600 == pytest.approx(RATE * tau * (1 - math.exp(-2.0)), rel=1e-12)
    assert 21.0 < e600 < 22.0
    e1200 = C(1200.0) - _T(1200.0, [tau]).item()
    assert e1200 == pytest.approx(e600 * math.exp(-2.0), rel=1e-12)


def test_members_lag_independently_and_negative_tau_is_rejected():
    """One batch with tau = 0, 30, 120 s: each equals its single evaluation; a longer tau lags
    more on the first ramp."""
    lags = C(300.0) - _T(300.0, [0.0, 30.0, 120.0])
    for i, tau in enumerate([0.0, 30.0, 120.0]):
        assert lags[i].item() == (C(300.0) - _T(300.0, [tau])).item()
    assert lags[0] == 0 and 0 < lags[1] < lags[2]
    with pytest.raises(ValueError, match="tau must be >= 0"):
        EffectSet(["thermal_lag"]).check(torch.tensor([[-1.0]], dtype=F64))
