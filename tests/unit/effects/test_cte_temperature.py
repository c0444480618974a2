"""cte_temperature's hook (solderpyro.effects.cte_temperature): the baseline at c_alpha = 0,
and the integral of alpha(T) = alpha25 (1 + n c (T - 25))^(1/n) from the stress-free
temperature, for the linear (n = 1), exponential (0), hyperbolic (-1) and square-root (2)
forms and between."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from solderpyro.effects import EFFECTS, EffectSet
from solderpyro.effects.cte_temperature import excess_strain

F64 = torch.float64
EFF = EFFECTS["cte_temperature"]
ALPHA = 23.5e-6  # Sn37Pb, 1/K (the reference case (docs/configuration.md))


def _args(T, T_ref, c, n=1.0):
    T = torch.as_tensor(T, dtype=F64)
    return (ALPHA * (T - T_ref), ALPHA, T, torch.full_like(T, T_ref),
            torch.tensor([[c, n]], dtype=F64).expand(len(T), 2))


def _gauss(f, a: float, b: float) -> float:
    """40-point Gauss-Legendre of ``f`` over [a, b]: exact to rounding for these analytic
    integrands (their Taylor series converge far beyond the interval)."""
    x, w = np.polynomial.legendre.leggauss(40)
    v = a + 0.5 * (b - a) * (x + 1.0)
    return float(0.5 * (b - a) * (w * f(v)).sum())


def _ratio(c: float, n: float):
    """alpha(25 + v) / alpha25 of the family, numpy (through log1p: the power of 1 + n c v
    at a small n c v would lose its digits)."""
    return (lambda v: np.exp(c * v)) if n == 0.0 else (lambda v: np.exp(np.log1p(n * c * v) / n))


def test_off_is_the_baseline_exactly_whatever_the_form():
    for n in (-1.0, 0.0, 0.5, 1.0, 2.0):
        eps, a, T, Tr, q = _args([25.0, 75.0, 125.0, -40.0], 25.0, 0.0, n)
        assert EFF.off == (0.0, 1.0) and torch.equal(EFF.thermal_strain(eps, a, T, Tr, q), eps)


@pytest.mark.parametrize("n", [-1.0, -0.99995, -0.9, -1e-7, 0.0, 1e-7, 0.3, 1.0, 1.7, 2.0])
def test_strain_is_the_integral_of_the_rising_cte(n):
    """The strain from any T_ref to T is alpha25 times the integral of the family's ratio
    (Gauss-Legendre; the closed form's cancellation costs at most 2 eps / |c u| ~ 4e-13, so
    1e-11 of the excess, the series below |c u| = 1e-3 as much), across c from 1e-7 to the
    box's top and from below 0 degC to the pre-history's 183 degC."""
    for c in (1e-7, 1e-5, 9.99e-4, 1e-3, 3e-3):
        for T1, T0 in ((125.0, 60.0), (30.0, 100.0), (-20.0, 25.0), (183.0, 25.0),
                       (25.2, 25.0)):
            eps, a, T, Tr, q = _args([T1], T0, c, n)
            got = EFF.thermal_strain(eps, a, T, Tr, q).item()
            ref = ALPHA * _gauss(_ratio(c, n), T0 - 25.0, T1 - 25.0)
            excess = abs(ref - ALPHA * (T1 - T0))
            assert abs(got - ref) <= 1e-11 * excess + 1e-15 * abs(ref), (c, T1, T0, got, ref)


def test_linear_and_exponential_forms_are_their_closed_forms():
    """n = 1: alpha c/2 (T - 25)^2 over the baseline heating from 25 degC (+15 % at 125 degC
    and the box's top c = 3e-3); n = 0: alpha ((exp(c u) - 1)/c - u)."""
    c = EFF.params.upper[0]
    assert c == 3e-3 and EFF.params.names == ("c_alpha", "n_alpha")
    eps, a, T, Tr, q = _args([125.0], 25.0, c, 1.0)
    assert (EFF.thermal_strain(eps, a, T, Tr, q) / eps).item() == pytest.approx(
        1 + c / 2 * 100.0, rel=1e-13)
    eps, a, T, Tr, q = _args([125.0], 25.0, c, 0.0)
    assert (EFF.thermal_strain(eps, a, T, Tr, q) - eps).item() == pytest.approx(
        ALPHA * (np.expm1(c * 100.0) / c - 100.0), rel=1e-12)


@pytest.mark.parametrize("n", [-1.0, 0.0, 1.0, 2.0])
def test_every_form_has_the_slope_c_at_25_degC_and_finite_gradients_at_off(n):
    """d eps / dT = alpha(T): at 25 degC alpha25, and its T-derivative there alpha25 c for
    every form (the score test at "off" sees the same effect); d/dc at c = 0 is u^2 / 2, the
    linear law's, and d/dn is 0 there (finite: the masked branches)."""
    c = 2e-3
    T = torch.tensor([25.0, 80.0], dtype=F64, requires_grad=True)
    q = torch.tensor([[c, n]], dtype=F64).expand(2, 2)
    out = EFF.thermal_strain(ALPHA * (T - 25.0), ALPHA, T, torch.full((2,), 25.0, dtype=F64), q)
    (g,) = torch.autograd.grad(out.sum(), T, create_graph=True)
    assert g[0].item() == pytest.approx(ALPHA, rel=1e-12)
    assert g[1].item() == pytest.approx(ALPHA * _ratio(c, n)(55.0), rel=1e-11)
    (h,) = torch.autograd.grad(g[0], T)
    assert h[0].item() == pytest.approx(ALPHA * c, rel=1e-6)
    cq = torch.zeros(1, dtype=F64, requires_grad=True)
    nq = torch.full((1,), n, dtype=F64, requires_grad=True)
    G = excess_strain(torch.tensor([100.0], dtype=F64), cq, nq)
    gc, gn = torch.autograd.grad(G.sum(), (cq, nq))
    assert gc.item() == pytest.approx(5000.0, rel=1e-12) and gn.item() == 0.0


def test_bad_forms_are_named():
    with pytest.raises(ValueError, match="n_alpha"):
        EFF.check(torch.tensor([[1e-3, 2.5]], dtype=F64))
    with pytest.raises(ValueError, match="n_alpha"):
        EFF.check(torch.tensor([[1e-3, -1.5]], dtype=F64))
    with pytest.raises(ValueError, match="CTE would vanish"):
        EFF.check(torch.tensor([[0.01, 2.0]], dtype=F64))  # 1 + 2 * 0.01 * (-90) < 0
    with pytest.raises(ValueError, match="CTE would vanish"):
        EFF.check(torch.tensor([[0.01, -1.0]], dtype=F64))  # 1 - 0.01 * 158 < 0
    EFF.check(torch.tensor([[3e-3, 2.0], [3e-3, -1.0], [0.0, 0.0]], dtype=F64))  # corners


def test_effect_set_applies_it_per_member_to_the_law():
    """Through EffectSet.thermal_strain (the solver's seam): member 0 off is the law's own
    strain, member 1 with c = 1e-3 (linear) adds alpha c/2 (75-25)^2."""
    law = SimpleNamespace(alpha=ALPHA, thermal_strain=lambda T, Tr: ALPHA * (T - Tr))
    fx = EffectSet(["cte_temperature"])
    T, Tr = torch.full((2,), 75.0, dtype=F64), torch.full((2,), 25.0, dtype=F64)
    out = fx.thermal_strain(law, T, Tr, torch.tensor([[0.0, 1.0], [1e-3, 1.0]], dtype=F64))
    assert out[0].item() == ALPHA * 50.0
    assert out[1].item() == pytest.approx(ALPHA * (50.0 + 0.5e-3 * 2500.0), rel=1e-14)
