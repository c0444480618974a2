"""modulus_temperature's hook (solderpyro.effects.modulus_temperature): the baseline at
k_E = 0 (whatever the forms n_E and r_E), exponential softening above 25 degC at n_E = 0 and
stiffening below, Darveaux's linear law to first order, the linear law at n_E = 1 and the
quickening one at n_E = 2 (each floored at its plateau r_E E25), the exponential's approach to
the plateau, a family smooth in n_E through its series near 0, and the checks of n_E's and
r_E's ranges."""

import math

import pytest
import torch

from solderpyro.effects import EFFECTS, EffectSet
from solderpyro.effects.modulus_temperature import K_MAX, N_MAX, R_MAX, R_MIN

F64 = torch.float64
EFF = EFFECTS["modulus_temperature"]
E25 = 32e3  # Sn37Pb, MPa
#: from the stress-free pre-history's 183 degC down to a -40 degC chamber
T_ALL = torch.linspace(-40.0, 183.0, 224, dtype=F64)


def _E(T, k, n=0.0, r=R_MIN):
    """E(T) MPa at k_E = ``k``, n_E = ``n`` (a float or a ``(len(T),)`` tensor) and r_E =
    ``r`` (likewise)."""
    T = torch.as_tensor(T, dtype=F64)
    n = torch.as_tensor(n, dtype=F64) * torch.ones_like(T)
    r = torch.as_tensor(r, dtype=F64) * torch.ones_like(T)
    q = torch.stack([torch.full_like(T, k), n, r], 1)
    return EFF.modulus(torch.full_like(T, E25), T, q)


def test_off_is_the_baseline_exactly():
    T = torch.tensor([-40.0, 25.0, 125.0, 183.0], dtype=F64)
    assert EFF.off == (0.0, 0.0, R_MIN) and EFF.nuisance == ("n_E", "r_E")
    assert EFF.params.names == ("k_E", "n_E", "r_E")
    assert EFF.params.units == ("1/K", "-", "-")
    assert EFF.params.lower == (0.0, 0.0, R_MIN) and EFF.params.upper == (K_MAX, N_MAX, R_MAX)
    for n, r in ((0.0, R_MIN), (1.0, 0.3), (N_MAX, R_MAX)):
        assert torch.equal(_E(T, 0.0, n, r), torch.full_like(T, E25)), (n, r)


def test_softens_with_temperature_in_the_right_amount():
    """k > 0 (exponential form, n_E = 0, the default plateau): E falls monotonically with T,
    equals E25 at 25 degC, exceeds it below; at the box's top E(125) = R_MIN + (1 - R_MIN)
    exp(-ln(10) / (1 - R_MIN)) E25, about E25/10 (1e-14); at k = 3.6e-3 /K
    E(125)/E25 = 0.698, the module's "~0.70" (Darveaux) within 0.5 %; stays positive at
    183 degC."""
    T = torch.linspace(-40.0, 183.0, 50, dtype=F64)
    E = _E(T, 3.6e-3)
    assert bool((E[1:] < E[:-1]).all()) and bool((E > 0).all())
    assert _E([25.0], 3.6e-3).item() == E25 and _E([0.0], 3.6e-3).item() > E25
    assert EFF.params.upper[0] == K_MAX == pytest.approx(math.log(10) / 100)
    top = R_MIN + (1 - R_MIN) * math.exp(-math.log(10) / (1 - R_MIN))
    assert _E([125.0], K_MAX).item() == pytest.approx(E25 * top, rel=1e-14)
    assert abs(top / 0.1 - 1) < 0.07  # 0.1067: the plateau adds 1 % of E25 and stretches u
    r = _E([125.0], 3.6e-3).item() / E25
    ref = R_MIN + (1 - R_MIN) * math.exp(-0.36 / (1 - R_MIN))
    assert r == pytest.approx(ref, rel=1e-14) and abs(r / 0.70 - 1) < 5e-3
    # first order in k: d E / d k at k = 0 is -E25 (T - 25), the linear law's slope
    k = torch.zeros(1, 1, dtype=F64, requires_grad=True)
    q = torch.cat([k, torch.tensor([[0.0, R_MIN]], dtype=F64)], 1)
    out = EFF.modulus(torch.tensor([E25], dtype=F64), torch.tensor([100.0], dtype=F64), q)
    (g,) = torch.autograd.grad(out.sum(), k)
    assert g.item() == pytest.approx(-E25 * 75.0, rel=1e-14)


# ------------------------------------------------------------------ the forms n_E and r_E

def _plateau_law(u, n, r):
    """Reference ``E / E25``: ``r + (1 - r) g(u / (1 - r))`` with g written out per form
    (exponential, linear, square root), floored at 0 by ``clamp``."""
    v = u / (1.0 - r)
    g = {0.0: torch.exp(-v), 1.0: torch.clamp(1.0 - v, min=0.0),
         2.0: torch.sqrt(torch.clamp(1.0 - 2.0 * v, min=0.0))}[n]
    return r + (1.0 - r) * g


@pytest.mark.parametrize("k", [3.6e-3, 6e-3, K_MAX])
@pytest.mark.parametrize("r", [R_MIN, 0.05, R_MAX])
def test_the_forms_are_the_linear_exponential_and_square_root_laws_with_a_plateau(k, r):
    """n_E = 1 is E25 max(r_E, 1 - k (T - 25)) (the linear law floored at the plateau);
    n_E = 0 the exponential approach to the plateau r + (1 - r) exp(-k (T - 25) / (1 - r));
    n_E = 2 the square root r + (1 - r) sqrt(1 - 2 k (T - 25) / (1 - r)), floored at the
    plateau: each to 1e-14 relative (exp(log1p) against the closed forms: a few ulps). At
    the box's top k the linear law reaches its plateau inside the cycle (at 68 degC for
    r = 1 %), so both sides are exercised. At k = 6e-3 /K and the default plateau the module's
    numbers: E(125 degC)/E25 = 0.40 linear against about 0.55 exponential."""
    u = k * (T_ALL - 25.0)
    lin = E25 * torch.clamp(1.0 - u, min=r)
    for n in (0.0, 1.0, 2.0):
        E = _E(T_ALL, k, n, r)
        ref = E25 * _plateau_law(u, n, r)
        assert ((E - ref).abs() / ref).max().item() <= 1e-14, n
    assert ((_E(T_ALL, k, 1.0, r) - lin).abs() / lin).max().item() <= 1e-14
    if k == K_MAX:
        assert bool((1.0 - u < r).any())
        assert _E([183.0], k, 1.0, r).item() == pytest.approx(r * E25, rel=1e-14)
    assert bool((_E(T_ALL, k, 0.0, r) > r * E25).all())  # the exponential only approaches it
    if k == 6e-3 and r == R_MIN:
        assert _E([125.0], k, 1.0, r).item() / E25 == pytest.approx(0.40, rel=1e-14)
        assert abs(_E([125.0], k, 0.0, r).item() / E25 - math.exp(-0.6)) < 0.01


def test_every_form_has_the_same_slope_at_25_degC_and_k_E_0_ignores_the_form():
    """k_E = 0: E = E25 at every T, n_E and r_E, bit for bit, and dE/dn_E = dE/dr_E = 0 exactly
    (the score test at "off" does not depend on the form). d E / d k_E at k_E = 0 is
    -E25 (T - 25) for every form (1e-14: one rounding)."""
    n = torch.tensor([0.0, 1e-7, 1e-6, 2e-6, 0.3, 1.0, 2.0], dtype=F64)
    r = torch.tensor([R_MIN, 0.05, 0.2, R_MIN, 0.3, R_MAX, 0.05], dtype=F64)
    for T in (-40.0, 25.0, 100.0, 183.0):
        nr, rr = n.clone().requires_grad_(True), r.clone().requires_grad_(True)
        kr = torch.zeros(len(n), dtype=F64, requires_grad=True)
        Tt = torch.full_like(n, T)
        E = EFF.modulus(torch.full_like(n, E25), Tt, torch.stack([kr, nr, rr], 1))
        assert torch.equal(E.detach(), torch.full_like(n, E25)), T
        gk, gn, gr = torch.autograd.grad(E.sum(), (kr, nr, rr))
        assert torch.equal(gn, torch.zeros_like(n)) and torch.equal(gr, torch.zeros_like(r)), T
        assert torch.allclose(gk, torch.full_like(n, -E25 * (T - 25.0)), rtol=1e-14, atol=0.0)


def test_the_family_is_continuous_through_the_series_switch():
    """Below n_E = 1e-6 the power g is evaluated by its series exp(-v - n v^2/2), above it
    directly (v = u / (1 - r_E), the default plateau here). Just below and just above the
    switch (n = 1e-6 (1 -+ 1e-3)) each side must equal r + (1 - r) (1 - n v)^(1/n) (the power
    referenced as exp(log1p(-n v)/n), float64, exact to a few ulps) within the series'
    truncation: its next term n^2 v^3/3 <= 1.7e-11 relative at the box's top (v = 3.68 at
    183 degC), so 2e-11; and the step between the two sides must be what the derivative
    predicts ((E - r E25) d log g/dn, d log g/dn = -v/(n (1 - n v)) - log1p(-n v)/n^2; up to
    1.3e-8 of E here) within the same 2e-11. A jump larger than that would show in any
    finite difference across the switch."""
    for k, T in ((6e-3, T_ALL[T_ALL <= 125.0]), (K_MAX, T_ALL)):
        u = k * (T - 25.0)
        lo, hi = 1e-6 * (1 - 1e-3), 1e-6 * (1 + 1e-3)
        side = {}
        for n in (lo, hi):
            nt = torch.full_like(u, n)
            v = u / (1.0 - R_MIN)
            ref = E25 * (R_MIN + (1.0 - R_MIN) * torch.exp(torch.log1p(-nt * v) / nt))
            side[n] = _E(T, k, n)
            err = ((side[n] - ref).abs() / ref).max().item()
            assert err <= 2e-11, (k, n, err)
        nm, v = torch.full_like(u, 1e-6), u / (1.0 - R_MIN)
        dlog = -v / (nm * (1.0 - nm * v)) - torch.log1p(-nm * v) / nm ** 2
        pred = (side[lo] - R_MIN * E25) * dlog * (hi - lo)
        jump = ((side[hi] - side[lo] - pred).abs() / side[lo]).max().item()
        assert jump <= 2e-11, (k, jump)


def test_derivative_in_n_E_matches_finite_differences():
    """Autograd d E / d n_E against finite differences, k_E = 6e-3 /K, -40..125 degC (above the
    plateau for every n_E up to 1.5): at n_E = 0.5 central (h = 1e-5: truncation ~ h^2 v^2 / 6
    < 1e-11, rounding ~ 1e-16 E / h ~ 1e-11 of it), to 1e-8 of max|dE/dn|; at n_E = 0, the
    box's edge, the second-order one-sided (-3 f(0) + 4 f(h) - f(2h)) / 2h with h = 1e-3
    (truncation ~ h^2 v^2 <= 3.7e-7 relative, v <= 0.61), to 1e-6 of it; and there autograd is
    -v^2/2 (E - r E25) exactly, the series' derivative (1e-14). d E / d r_E at r_E = 0.2,
    n_E = 0.5 central (h = 1e-5; the same truncation and rounding), to 1e-8 of its largest."""
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
    v = u / (1.0 - R_MIN)
    exact = -v * v / 2.0 * (E0.detach() - R_MIN * E25)
    assert torch.allclose(g0, exact, rtol=1e-14, atol=0.0)
    h = 1e-3
    fd0 = (-3.0 * _E(T, k, 0.0) + 4.0 * _E(T, k, h) - _E(T, k, 2 * h)) / (2 * h)
    assert (g0 - fd0).abs().max().item() <= 1e-6 * g0.abs().max().item()
    r = torch.full_like(T, 0.2, requires_grad=True)
    (gr,) = torch.autograd.grad(_E(T, k, 0.5, r).sum(), r)
    fdr = (_E(T, k, 0.5, 0.2 + h * 1e-2) - _E(T, k, 0.5, 0.2 - h * 1e-2)) / (2 * h * 1e-2)
    assert gr.abs().max().item() > 1e3  # MPa per unit r_E: the plateau matters here
    assert (gr - fdr).abs().max().item() <= 1e-8 * gr.abs().max().item()


def test_forms_outside_their_ranges_are_rejected_by_name():
    fx = EffectSet(["modulus_temperature"])
    fx.check(torch.tensor([[1e-3, 0.0, R_MIN], [1e-3, N_MAX, R_MAX]], dtype=F64))  # edges: fine
    for bad in (2.5, -0.1):
        with pytest.raises(ValueError, match="modulus_temperature: n_E .* within \\[0, 2\\]"):
            fx.check(torch.tensor([[1e-3, 0.5, 0.1], [1e-3, bad, 0.1]], dtype=F64))
    for bad in (0.0, 1.0, -0.1):
        with pytest.raises(ValueError, match="modulus_temperature: r_E .* within \\(0, 1\\)"):
            fx.check(torch.tensor([[1e-3, 0.5, 0.1], [1e-3, 0.5, bad]], dtype=F64))
