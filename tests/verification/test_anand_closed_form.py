"""Anand material point against its closed forms (relative error <= 1e-6): the saturation
stress sigma* = (s_hat / xi) Z^n asinh(Z^m) and s* = s_hat Z^n (docs/configuration.md)."""

import math

import pytest
import torch

from solderpyro.materials.anand import s_closed_form, saturation
from solderpyro.materials.integrate import (
    PointInputs,
    _solve_s,
    anand_update,
    initial_state,
)
from solderpyro.params import LIU2008, WANG2001, anand_tensor

# reference table (Wang 2001 60Sn40Pb constants, params.WANG2001):
# T (C), rate (1/s), sigma* (MPa), s* (MPa)
TABLE = [(25, 1e-4, 36.461, 102.724), (25, 1e-6, 21.118, 92.358),
         (125, 1e-4, 9.297, 83.205), (125, 1e-6, 2.571, 74.808)]


@pytest.mark.parametrize("TC,rate,sig_ref,s_ref", TABLE)
def test_closed_form_matches_reference_table(TC, rate, sig_ref, s_ref):
    p = anand_tensor(base=WANG2001)
    sig, s = saturation(torch.tensor(rate), torch.tensor(TC + 273.15), p)
    assert sig.item() == pytest.approx(sig_ref, abs=6e-4)  # table rounded to 3 decimals
    assert s.item() == pytest.approx(s_ref, abs=6e-4)


def _shear_drive(p, TC, rate, eps_total, n_steps, plane="stress"):
    """Pure shear at constant equivalent rate through the FE material update."""
    T = TC + 273.15
    st = initial_state((1,), p[0])
    gdot = math.sqrt(3.0) * rate  # engineering shear rate giving eq. inelastic rate at saturation
    dt = eps_total / rate / n_steps
    for k in range(1, n_steps + 1):
        g = gdot * dt * k
        eps = torch.tensor([[0.0, 0.0, g / math.sqrt(2.0)]])  # Mandel sqrt2*eps_xy
        sig, st, _, _, _ = anand_update(eps, st, p, PointInputs(T, dt, 0.0, 32000.0, 0.35),
                                        plane)
    return math.sqrt(1.5) * sig[0].norm().item(), st.s.item()


@pytest.mark.parametrize("TC,rate", [(25, 1e-4), (25, 1e-6), (75, 1e-5), (125, 1e-4),
                                     (125, 1e-6)])
@pytest.mark.parametrize("plane", ["stress", "strain"])
def test_saturation_reached_by_fe_update(TC, rate, plane):
    """After eps_p = 60 at constant rate the implicit update sits on the saturation point.

    Backward Euler is exact at steady state (s = s*, dep = rate*dt), so the error is the
    remaining algebraic transient, (2.1*eps_p)^(-2.9) ~ 1e-6 of s* for a = 1.34.
    """
    p = anand_tensor(base=WANG2001)
    q, s = _shear_drive(p, TC, rate, 60.0, 300, plane)
    sig_ref, s_ref = saturation(torch.tensor(rate), torch.tensor(TC + 273.15), p)
    assert q == pytest.approx(sig_ref.item(), rel=1e-6)
    assert s == pytest.approx(s_ref.item(), rel=1e-6)


@pytest.mark.parametrize("base,TC,rate,a", [
    (WANG2001, 25, 1e-4, None), (WANG2001, 125, 1e-6, None), (LIU2008, 75, 1e-5, None),
    (LIU2008, 125, 1e-4, 1.0), (WANG2001, 25, 1e-5, 1.0), (LIU2008, 100, 1e-3, 0.8)])
@pytest.mark.parametrize("s0_factor", [0.4, 1.8])
def test_transient_s_matches_closed_form(base, TC, rate, a, s0_factor):
    """s(eps_p) at constant rate: implicit hardening update vs the closed form.

    The update is backward Euler in eps_p (first order); Richardson extrapolation of three
    step sizes removes the O(h) and O(h^2) terms, leaving an error far below 1e-6. Both
    s0 < s* and s0 > s*, a != 1, a = 1 and a < 1 (non-Lipschitz at s*).
    """
    vals = dict(base)
    if a is not None:
        vals["a"] = a
    p = anand_tensor(base=vals)
    T = torch.tensor(TC + 273.15)
    _, s_star = saturation(torch.tensor(rate), T, p)
    s0 = s0_factor * s_star.item()
    p = anand_tensor({"s0": s0}, base=vals)
    eps_end = 0.6 * s_star.item() / p[5].item()  # about half way to saturation
    QR, A = p[1], p[2]

    def integrate(n):
        h = eps_end / n
        dt = h / rate
        c = torch.log(torch.tensor(dt) * A) - QR / T
        L = torch.tensor(math.log(h))
        s = torch.tensor(s0)
        for _ in range(n):
            s, _, _ = _solve_s(L, c, s.clone(), s.clone(), p)
        return s.item()

    s1, s2, s4 = integrate(1000), integrate(2000), integrate(4000)
    r1 = 2 * s2 - s1
    r2 = 2 * s4 - s2
    s_rich = (4 * r2 - r1) / 3
    exact = s_closed_form(torch.tensor(eps_end), torch.tensor(rate), T, p).item()
    assert abs(s_rich - exact) / exact <= 1e-6
    assert abs(s4 - exact) / abs(s1 - exact) == pytest.approx(0.25, rel=0.1)  # first order


@pytest.mark.parametrize("xi_sigma_over_s", [1e-3, 1.0, 10.0, 50.0])
@pytest.mark.parametrize("m", [0.05, 0.3, 1.0])
def test_flow_rule_identity_no_overflow(xi_sigma_over_s, m):
    """One update: returned (dep, q, s) satisfy the flow rule in the closed form sigma = c*s.

    Covers xi*sigma/s up to 50 and m down to 0.05 (rates up to sinh(50)^20 ~ 1e425 in linear
    form) without overflow or NaN.
    """
    p = anand_tensor({"m": m, "h0": 0.0})  # h0 = 0 keeps s fixed: s = s0
    s0, xi = p[0].item(), p[3].item()
    G = 32000.0 / (2 * 1.35)
    q_tr = xi_sigma_over_s * s0 / xi + 3 * G * 1e-3
    g = q_tr / (math.sqrt(3.0) * G)  # pure-shear total strain with that trial stress
    eps = torch.tensor([[0.0, 0.0, g / math.sqrt(2.0)]])
    st = initial_state((1,), p[0])
    dt, T = 10.0, 350.0
    sig, st1, C, dep, _ = anand_update(eps, st, p, PointInputs(T, dt, 0.0, 32000.0, 0.35),
                                       "strain")
    assert torch.isfinite(sig).all() and torch.isfinite(C).all()
    q = math.sqrt(1.5) * sig[0].norm().item()
    rate = dep.item() / dt
    Z = rate / p[2].item() * math.exp(p[1].item() / T)
    assert q == pytest.approx(s0 / xi * math.asinh(Z**m), rel=1e-9)
    assert q + 3 * G * dep.item() == pytest.approx(q_tr, rel=1e-12)
