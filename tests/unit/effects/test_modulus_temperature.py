"""modulus_temperature's hook (solderpyro.effects.modulus_temperature): the baseline at
k_E = 0, exponential softening above 25 degC, stiffening below, E25/10 at 125 degC at the
box's top, and Darveaux's linear law to first order."""

import math

import pytest
import torch

from solderpyro.effects import EFFECTS
from solderpyro.effects.modulus_temperature import K_MAX

F64 = torch.float64
EFF = EFFECTS["modulus_temperature"]
E25 = 32e3  # Sn37Pb, MPa


def _E(T, k):
    T = torch.as_tensor(T, dtype=F64)
    return EFF.modulus(torch.full_like(T, E25), T, torch.full((len(T), 1), k, dtype=F64))


def test_off_is_the_baseline_exactly():
    T = torch.tensor([-40.0, 25.0, 125.0, 183.0], dtype=F64)
    assert EFF.off == (0.0,)
    assert torch.equal(_E(T, 0.0), torch.full_like(T, E25))


def test_softens_with_temperature_in_the_right_amount():
    """k > 0: E falls monotonically with T, equals E25 at 25 degC, exceeds it below; at the
    box's top E(125) = E25/10 (1e-14); at k = 3.6e-3 /K E(125)/E25 = exp(-0.36) = 0.698,
    the module's "~0.70" (Darveaux) within 0.5 %; stays positive at 183 degC."""
    T = torch.linspace(-40.0, 183.0, 50, dtype=F64)
    E = _E(T, 3.6e-3)
    assert bool((E[1:] < E[:-1]).all()) and bool((E > 0).all())
    assert _E([25.0], 3.6e-3).item() == E25 and _E([0.0], 3.6e-3).item() > E25
    assert EFF.params.upper[0] == K_MAX == pytest.approx(math.log(10) / 100)
    assert _E([125.0], K_MAX).item() == pytest.approx(E25 / 10, rel=1e-14)
    r = _E([125.0], 3.6e-3).item() / E25
    assert r == pytest.approx(math.exp(-0.36), rel=1e-14) and abs(r / 0.70 - 1) < 5e-3
    # first order in k: d E / d k at k = 0 is -E25 (T - 25), the linear law's slope
    k = torch.zeros(1, 1, dtype=F64, requires_grad=True)
    out = EFF.modulus(torch.tensor([E25], dtype=F64), torch.tensor([100.0], dtype=F64), k)
    (g,) = torch.autograd.grad(out.sum(), k)
    assert g.item() == pytest.approx(-E25 * 75.0, rel=1e-14)
