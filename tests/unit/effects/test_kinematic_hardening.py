"""kinematic_hardening's hooks (solderpyro.effects.kinematic_hardening): the Prager modulus of
the solder's back stress, 0 at off (the isotropic update to the last bit, checked through the
FE in tests/unit/effects/test_effect_set.py), the member's C_k otherwise, added to any earlier
one; and its Armstrong-Frederick recovery gamma_k, a form (nuisance) parameter, 0 at off."""

import pytest
import torch

from solderpyro.effects import EFFECTS, EffectSet

F64 = torch.float64
EFF = EFFECTS["kinematic_hardening"]


def test_back_stress_modulus_is_the_members_C_k():
    q = torch.tensor([[0.0, 0.0], [300.0, 50.0], [2000.0, 200.0]], dtype=F64)
    Ck = EFF.back_stress_modulus(None, q)
    assert torch.equal(Ck, q[:, 0]) and EFF.off == (0.0, 0.0)
    assert torch.equal(EFF.back_stress_modulus(torch.full((3,), 100.0, dtype=F64), q),
                       q[:, 0] + 100.0)
    fx = EffectSet(["kinematic_hardening"])
    assert fx.kinematic and torch.equal(fx.back_stress_modulus(q), q[:, 0])
    assert not EffectSet(["thermal_lag"]).kinematic
    assert EffectSet(["thermal_lag"]).back_stress_modulus(torch.zeros(3, 1)) is None
    b = EFF.params
    assert (b.lower, b.upper, b.units) == ((0.0, 0.0), (2000.0, 200.0), ("MPa", "-"))


def test_back_stress_recovery_is_the_members_gamma_k_a_form_parameter():
    """gamma_k is the second column, a nuisance (form) parameter: C_k stays the size index."""
    q = torch.tensor([[0.0, 0.0], [300.0, 50.0], [2000.0, 200.0]], dtype=F64)
    assert torch.equal(EFF.back_stress_recovery(None, q), q[:, 1])
    fx = EffectSet(["kinematic_hardening"])
    assert fx.recovery and torch.equal(fx.back_stress_recovery(q), q[:, 1])
    assert not EffectSet(["thermal_lag"]).recovery
    assert EffectSet(["thermal_lag"]).back_stress_recovery(torch.zeros(3, 1)) is None
    assert EFF.nuisance == ("gamma_k",) and EFF.size_index == 0


def test_negative_modulus_and_recovery_are_rejected():
    with pytest.raises(ValueError, match="C_k must be >= 0 MPa"):
        EFF.check(torch.tensor([[-5.0, 0.0]], dtype=F64))
    with pytest.raises(ValueError, match="gamma_k .* must be >= 0, got -1"):
        EFF.check(torch.tensor([[5.0, -1.0]], dtype=F64))
    EFF.check(torch.tensor([[0.0, 0.0], [2000.0, 200.0]], dtype=F64))
