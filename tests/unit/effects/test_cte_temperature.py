"""cte_temperature's hook (solderpyro.effects.cte_temperature): the baseline at c_alpha = 0,
and the integral of alpha(T) = alpha25 (1 + c (T - 25)) from the stress-free temperature."""

from types import SimpleNamespace

import pytest
import torch

from solderpyro.effects import EFFECTS, EffectSet

F64 = torch.float64
EFF = EFFECTS["cte_temperature"]
ALPHA = 23.5e-6  # Sn37Pb, 1/K (the reference case (docs/configuration.md))


def _args(T, T_ref, c):
    T = torch.as_tensor(T, dtype=F64)
    return (ALPHA * (T - T_ref), ALPHA, T, torch.full_like(T, T_ref),
            torch.full((len(T), 1), c, dtype=F64))


def test_off_is_the_baseline_exactly():
    eps, a, T, Tr, q = _args([25.0, 75.0, 125.0, -40.0], 25.0, 0.0)
    assert EFF.off == (0.0,) and torch.equal(EFF.thermal_strain(eps, a, T, Tr, q), eps)


def test_strain_is_the_integral_of_the_rising_cte():
    """For c > 0 heating from 25 degC the strain grows by alpha c/2 (T - 25)^2 over the
    baseline (+15 % at 125 degC and the box's top c = 3e-3); it equals Simpson's rule of
    alpha(T) (exact for the linear integrand, rounding 1e-12) from any T_ref, and its
    T-derivative is alpha(T) = alpha (1 + c (T - 25))."""
    c = EFF.params.upper[0]
    assert c == 3e-3
    eps, a, T, Tr, q = _args([125.0], 25.0, c)
    out = EFF.thermal_strain(eps, a, T, Tr, q)
    assert (out / eps).item() == pytest.approx(1 + c / 2 * 100.0, rel=1e-12)  # 1.15
    for T1, T0 in ((125.0, 60.0), (30.0, 100.0), (-20.0, 25.0)):
        eps, a, T, Tr, q = _args([T1], T0, c)
        got = EFF.thermal_strain(eps, a, T, Tr, q).item()
        mid = 0.5 * (T1 + T0)

        def alpha(t):
            return ALPHA * (1 + c * (t - 25.0))

        simpson = (T1 - T0) / 6 * (alpha(T0) + 4 * alpha(mid) + alpha(T1))
        assert got == pytest.approx(simpson, rel=1e-12)
    T = torch.tensor([80.0], dtype=F64, requires_grad=True)
    out = EFF.thermal_strain(ALPHA * (T - 25.0), ALPHA, T, torch.tensor([25.0], dtype=F64),
                             torch.tensor([[c]], dtype=F64))
    (g,) = torch.autograd.grad(out.sum(), T)
    assert g.item() == pytest.approx(ALPHA * (1 + c * 55.0), rel=1e-12)


def test_effect_set_applies_it_per_member_to_the_law():
    """Through EffectSet.thermal_strain (the solver's seam): member 0 off is the law's own
    strain, member 1 with c = 1e-3 adds alpha c/2 (75-25)^2."""
    law = SimpleNamespace(alpha=ALPHA, thermal_strain=lambda T, Tr: ALPHA * (T - Tr))
    fx = EffectSet(["cte_temperature"])
    T, Tr = torch.full((2,), 75.0, dtype=F64), torch.full((2,), 25.0, dtype=F64)
    out = fx.thermal_strain(law, T, Tr, torch.tensor([[0.0], [1e-3]], dtype=F64))
    assert out[0].item() == ALPHA * 50.0
    assert out[1].item() == pytest.approx(ALPHA * (50.0 + 0.5e-3 * 2500.0), rel=1e-14)
