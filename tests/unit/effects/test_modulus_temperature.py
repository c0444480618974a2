"""modulus_temperature's hook (solderpyro.effects.modulus_temperature): the baseline at
k_E = 0 (whatever the form n_E), exponential softening above 25 degC at n_E = 0 and stiffening
below, E25/10 at 125 degC at the box's top, Darveaux's linear law to first order, the linear
law at n_E = 1 (floored at R_MIN E25), a family smooth in n_E through its series near 0, and
the check of n_E's range."""

import math

import pytest
import torch

from solderpyro.effects import EFFECTS, EffectSet
from solderpyro.effects.modulus_temperature import K_MAX, R_MIN

F64 = torch.float64
EFF = EFFECTS["modulus_temperature"]
E25 = 32e3  # Sn37Pb, MPa
#: from the stress-free pre-history's 183 degC down to a -40 degC chamber
T_ALL = torch.linspace(-40.0, 183.0, 224, dtype=F64)


def _E(T, k, n=0.0):
    """E(T) MPa at k_E = ``k`` and n_E = ``n`` (a float or a ``(len(T),)`` tensor)."""
    T = torch.as_tensor(T, dtype=F64)
    n = torch.as_tensor(n, dtype=F64) * torch.ones_like(T)
    q = torch.stack([torch.full_like(T, k), n], 1)
    return EFF.modulus(torch.full_like(T, E25), T, q)


def test_off_is_the_baseline_exactly():
    T = torch.tensor([-40.0, 25.0, 125.0, 183.0], dtype=F64)
    assert EFF.off == (0.0, 0.0) and EFF.nuisance == ("n_E",)
    assert EFF.params.names == ("k_E", "n_E") and EFF.params.units == ("1/K", "-")
    assert torch.equal(_E(T, 0.0), torch.full_like(T, E25))


def test_softens_with_temperature_in_the_right_amount():
    """k > 0 (exponential form, n_E = 0): E falls monotonically with T, equals E25 at 25 degC,
    exceeds it below; at the box's top E(125) = E25/10 (1e-14); at k = 3.6e-3 /K
    E(125)/E25 = exp(-0.36) = 0.698, the module's "~0.70" (Darveaux) within 0.5 %; stays
    positive at 183 degC."""
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
    q = torch.cat([k, torch.zeros(1, 1, dtype=F64)], 1)
    out = EFF.modulus(torch.tensor([E25], dtype=F64), torch.tensor([100.0], dtype=F64), q)
    (g,) = torch.autograd.grad(out.sum(), k)
    assert g.item() == pytest.approx(-E25 * 75.0, rel=1e-14)


# ------------------------------------------------------------------ the form n_E

@pytest.mark.parametrize("k", [3.6e-3, 6e-3, K_MAX])
def test_n_E_1_is_the_linear_law_floored_and_0_the_exponential(k):
    """n_E = 1: E25 (1 - k (T - 25)) where that is above R_MIN E25, R_MIN E25 below it, to
    1e-14 relative (computed as exp(log z): a few ulps; <= 3.6e-16 measured). At the box's
    top the linear law reaches the floor at 68 degC, so both sides are exercised there.
    n_E = 0: E25 exp(-k (T - 25)) bit for bit (the series exp(-u - 0 u^2/2) is exp(-u)), and
    never floored in the box (>= 2.6 % of E25 at 183 degC). At k = 6e-3 /K the module's
    numbers: E(125 degC)/E25 = 0.40 linear against 0.55 exponential."""
    u = k * (T_ALL - 25.0)
    lin = E25 * torch.clamp(1.0 - u, min=R_MIN)
    E1 = _E(T_ALL, k, 1.0)
    assert ((E1 - lin).abs() / lin).max().item() <= 1e-14
    floored = 1.0 - u < R_MIN
    assert bool(floored.any()) == (k == K_MAX)
    assert torch.equal(_E(T_ALL, k, 0.0), E25 * torch.exp(-u))
    assert _E(T_ALL, k, 0.0).min().item() > 0.026 * E25
    if k == 6e-3:
        assert _E([125.0], k, 1.0).item() / E25 == pytest.approx(0.40, rel=1e-14)
        assert _E([125.0], k, 0.0).item() / E25 == pytest.approx(math.exp(-0.6), rel=1e-15)


def test_every_form_has_the_same_slope_at_25_degC_and_k_E_0_ignores_n_E():
    """k_E = 0: E = E25 at every T and n_E, bit for bit, and dE/dn_E = 0 exactly (the score
    test at "off" does not depend on the form). d E / d k_E at k_E = 0 is -E25 (T - 25) for
    every n_E (1e-14: one rounding)."""
    n = torch.tensor([0.0, 1e-7, 1e-6, 2e-6, 0.3, 1.0], dtype=F64)
    for T in (-40.0, 25.0, 100.0, 183.0):
        nr = n.clone().requires_grad_(True)
        kr = torch.zeros(len(n), dtype=F64, requires_grad=True)
        Tt = torch.full_like(n, T)
        E = EFF.modulus(torch.full_like(n, E25), Tt, torch.stack([kr, nr], 1))
        assert torch.equal(E.detach(), torch.full_like(n, E25)), T
        gk, gn = torch.autograd.grad(E.sum(), (kr, nr))
        assert torch.equal(gn, torch.zeros_like(n)), T
        assert torch.allclose(gk, torch.full_like(n, -E25 * (T - 25.0)), rtol=1e-14, atol=0.0)


def test_the_family_is_continuous_through_the_series_switch():
    """Below n_E = 1e-6 the power is evaluated by its series exp(-u - n u^2/2), above it
    directly. Just below and just above the switch (n = 1e-6 (1 -+ 1e-3)) each side must equal
    (1 - n u)^(1/n) (referenced as exp(log1p(-n u)/n), float64, exact to a few ulps) within
    the series' truncation: its next term n^2 u^3/3 <= 1.6e-11 relative at the box's top
    (u = 3.64 at 183 degC), so 2e-11; and the step between the two sides must be what the
    derivative predicts (d log E/dn = -u/(n (1 - n u)) - log1p(-n u)/n^2; up to 1.3e-8 of E
    here) within the same 2e-11. A jump larger than that would show in any finite difference
    across the switch."""
    for k, T in ((6e-3, T_ALL[T_ALL <= 125.0]), (K_MAX, T_ALL)):
        u = k * (T - 25.0)
        lo, hi = 1e-6 * (1 - 1e-3), 1e-6 * (1 + 1e-3)
        side = {}
        for n in (lo, hi):
            nt = torch.full_like(u, n)
            ref = E25 * torch.exp(torch.log1p(-nt * u) / nt)
            side[n] = _E(T, k, n)
            err = ((side[n] - ref).abs() / ref).max().item()
            assert err <= 2e-11, (k, n, err)
        nm = torch.full_like(u, 1e-6)
        dlog = -u / (nm * (1.0 - nm * u)) - torch.log1p(-nm * u) / nm ** 2
        pred = side[lo] * dlog * (hi - lo)
        jump = ((side[hi] - side[lo] - pred).abs() / side[lo]).max().item()
        assert jump <= 2e-11, (k, jump)


def test_derivative_in_n_E_matches_finite_differences():
    """Autograd d E / d n_E against finite differences, k_E = 6e-3 /K, -40..125 degC (above the
    floor for every n_E): at n_E = 0.5 central (h = 1e-5: truncation ~ h^2 u^2 / 6 < 1e-11,
    rounding ~ 1e-16 E / h ~ 1e-11 of it; 1.6e-10 measured), to 1e-8 of max|dE/dn|; at
    n_E = 0, the box's edge, the second-order one-sided (-3 f(0) + 4 f(h) - f(2h)) / 2h with
    h = 1e-3 (truncation ~ h^2 u^2 <= 3.6e-7 relative, u <= 0.6; 2.0e-7 measured), to 1e-6 of
    it; and there autograd is -u^2/2 E exactly, the series' derivative (1e-14)."""
    k = 6e-3
    T = T_ALL[T_ALL <= 125.0]
    u = k * (T - 25.0)
    n = torch.full_like(T, 0.5, requires_grad=True)
    (g,) = torch.autograd.grad(_E(T, k, n).sum(), n)
    h = 1e-5
    fd = (_E(T, k, 0.5 + h) - _E(T, k, 0.5 - h)) / (2 * h)
    assert g.abs().max().item() > 1e3  # MPa per unit n_E: the form matters here
    assert (g - fd).abs().max().item() <= 1e-8 * g.abs().max().item()
    n0 = torch.zeros_like(T, requires_grad=True)
    E0 = _E(T, k, n0)
    (g0,) = torch.autograd.grad(E0.sum(), n0)
    exact = -u * u / 2.0 * E0.detach()
    assert torch.allclose(g0, exact, rtol=1e-14, atol=0.0)
    h = 1e-3
    fd0 = (-3.0 * _E(T, k, 0.0) + 4.0 * _E(T, k, h) - _E(T, k, 2 * h)) / (2 * h)
    assert (g0 - fd0).abs().max().item() <= 1e-6 * g0.abs().max().item()


def test_n_E_outside_its_range_is_rejected_by_name():
    fx = EffectSet(["modulus_temperature"])
    fx.check(torch.tensor([[1e-3, 0.0], [1e-3, 1.0]], dtype=F64))  # the box's edges are fine
    for bad in (1.5, -0.1):
        with pytest.raises(ValueError, match="modulus_temperature: n_E .* within \\[0, 1\\]"):
            fx.check(torch.tensor([[1e-3, 0.5], [1e-3, bad]], dtype=F64))
