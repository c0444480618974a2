"""The Anand pure functions (solderpyro.materials.anand): the overflow-free log sinh, the
closed-form s(eps_p) as the solution of the s-equation, and the backward-Euler residual's
derivatives. The Wang 2001 reference table and the FE update against the closed forms are in
tests/verification/test_anand_closed_form.py."""

import math

import pytest
import torch

from solderpyro.materials.anand import hardening_residual, log_sinh, s_closed_form, saturation
from solderpyro.params import LIU2008, WANG2001, anand_tensor

F64 = torch.float64


def test_log_sinh_equals_the_direct_form_and_never_overflows():
    """Where sinh is representable, log_sinh(y) = log(sinh(y)) to a few ulp of the result
    (|log sinh| >= ~1e-3 here, so relative 1e-13); at y = 1e5 (sinh overflows) it is
    y - log 2 to rounding; at y = 1e-8 it is log(y) (sinh y = y (1 + y^2/6))."""
    y = torch.logspace(-3, 2.5, 200, dtype=F64)
    direct = torch.log(torch.sinh(y))
    torch.testing.assert_close(log_sinh(y), direct, rtol=1e-13, atol=1e-14)
    big = torch.tensor([1e5, 1e200], dtype=F64)
    torch.testing.assert_close(log_sinh(big), big - math.log(2.0), rtol=1e-15, atol=0)
    small = torch.tensor([1e-8], dtype=F64)
    torch.testing.assert_close(log_sinh(small), torch.log(small), rtol=1e-12, atol=0)


def test_saturation_is_the_fixed_point_of_the_flow_rule():
    """At (sigma*, s*) the flow rule returns the rate it was built for:
    A exp(-Q/RT) sinh(xi sigma*/s*)^(1/m) = rate (1e-12 relative), over Liu's and Wang's
    constants, two temperatures and three rates."""
    for base in (LIU2008, WANG2001):
        p = anand_tensor(base=base, dtype=F64)
        for T in (298.15, 398.15):
            for rate in (1e-7, 1e-5, 1e-3):
                sig, s = saturation(torch.tensor(rate, dtype=F64), torch.tensor(T, dtype=F64), p)
                A, QR, xi, m = base["A"], base["QR"], base["xi"], base["m"]
                back = A * math.exp(-QR / T + log_sinh(xi * sig / s).item() / m)
                assert back == pytest.approx(rate, rel=1e-12)


@pytest.mark.parametrize("a", [0.6, 1.0, 1.3, 2.0])
@pytest.mark.parametrize("s0", [5.0, 30.0])  # below and above s* (16.5 MPa here)
def test_closed_form_solves_the_s_equation(a, s0):
    """s(eps_p) starts at s0, solves ds/deps_p = h0 |1 - s/s*|^a sign(1 - s/s*) (autograd
    derivative against the right-hand side, 1e-10 relative: both are evaluated exactly) and
    tends monotonically to s* (a > 1 algebraically, a = 1 exponentially; a < 1 reaches it
    at the finite strain |s* - s0|^(1-a) s*^a / ((1 - a) h0), beyond which the power form is
    not defined, so only a >= 1 is taken far out)."""
    p = anand_tensor({"a": a, "s0": s0}, dtype=F64)
    rate, T = torch.tensor(1e-4, dtype=F64), torch.tensor(348.15, dtype=F64)
    _, s_star = saturation(rate, T, p)
    assert 5.0 < s_star.item() < 30.0
    e = torch.linspace(0.0, 0.02, 21, dtype=F64)[1:].requires_grad_(True)
    s = s_closed_form(e, rate, T, p)
    (ds,) = torch.autograd.grad(s.sum(), e)
    r = 1.0 - s.detach() / s_star
    rhs = LIU2008["h0"] * r.abs() ** a * torch.sign(r)
    torch.testing.assert_close(ds, rhs, rtol=1e-10, atol=1e-12 * LIU2008["h0"])
    s_at0 = s_closed_form(torch.zeros((), dtype=F64), rate, T, p)
    assert s_at0.item() == pytest.approx(s0, rel=1e-13)
    d = (s.detach() - s_star).abs()
    assert bool((d[1:] <= d[:-1]).all()) and bool((d <= abs(s0 - s_star.item())).all())
    if a >= 1.0:  # a > 1: |s - s*| ~ (s*^a / ((a - 1) h0 eps))^(1/(a-1)), < 1e-3 s* at 50
        far = s_closed_form(torch.tensor(50.0, dtype=F64), rate, T, p)
        assert far.item() == pytest.approx(s_star.item(), rel=1e-3 if a > 1 else 1e-12)


def test_closed_form_is_continuous_in_a_through_one():
    """The power form at a = 1 +- 1e-6 approaches the exponential form of a = 1 (the
    difference is first order in a - 1: below 1e-4 MPa here)."""
    rate, T = torch.tensor(1e-5, dtype=F64), torch.tensor(323.15, dtype=F64)
    e = torch.tensor([1e-3, 5e-3, 2e-2], dtype=F64)
    one = s_closed_form(e, rate, T, anand_tensor({"a": 1.0}, dtype=F64))
    for a in (1.0 - 1e-6, 1.0 + 1e-6):
        near = s_closed_form(e, rate, T, anand_tensor({"a": a}, dtype=F64))
        assert (near - one).abs().max().item() < 1e-4


def test_hardening_residual_derivatives_match_autograd():
    """The residual's returned partials dH/ds and dH/dlog_dep (with s* depending on the rate
    through log Z, dlogZ/dlog_dep = 1) equal autograd's (1e-12 relative), for s below and
    above s*; at dep -> 0 the residual is s - s_n."""
    p = anand_tensor(dtype=F64)
    s = torch.tensor([10.0, 14.0, 25.0], dtype=F64, requires_grad=True)
    L = torch.full((3,), math.log(1e-4), dtype=F64, requires_grad=True)
    T, dt = 348.15, 10.0
    logZ = L - math.log(dt) - math.log(LIU2008["A"]) + LIU2008["QR"] / T
    s_n = torch.tensor([12.0, 12.0, 20.0], dtype=F64)
    H, dHs, dHL, s_star = hardening_residual(s, s_n, L, logZ, p)
    gs, gL = torch.autograd.grad(H.sum(), (s, L))
    torch.testing.assert_close(dHs, gs, rtol=1e-12, atol=0)
    torch.testing.assert_close(dHL, gL, rtol=1e-12, atol=0)
    torch.testing.assert_close(s_star, LIU2008["s_hat"] * torch.exp(LIU2008["n"] * logZ))
    H0 = hardening_residual(s, s_n, torch.full((3,), -800.0, dtype=F64), logZ, p)[0]
    torch.testing.assert_close(H0, s.detach() - s_n, rtol=0, atol=1e-12)


def test_below_a_of_one_s_reaches_saturation_at_a_finite_strain_and_stays():
    """For a < 1 the s-equation ds/de = h0 |1 - s/s*|^a reaches s* in finite strain
    e* = (s* - s0)^(1-a) s*^a / (h0 (1 - a)) and stays there: no NaN past it."""
    p = anand_tensor({"a": 0.6, "s0": 5.0}, dtype=torch.float64)
    rate = torch.tensor(1e-4, dtype=torch.float64)
    T = torch.tensor(300.0, dtype=torch.float64)
    _, s_star = saturation(rate, T, p)
    h0, a = p[..., 5], p[..., 8]
    d0 = s_star - 5.0
    e_star = d0 ** (1 - a) * s_star**a / ((1 - a) * h0)  # where inner = 0
    eps = torch.stack([0.5 * e_star, 0.999 * e_star, e_star, 2 * e_star, 100 * e_star])
    s = s_closed_form(eps, rate, T, p)
    assert torch.isfinite(s).all()
    assert float(s[0]) < float(s_star)
    assert torch.allclose(s[2:], s_star.expand(3), rtol=1e-12, atol=0)
