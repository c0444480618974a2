"""thermal_lag's hook (solderpyro.effects.thermal_lag): the program at tau = 0, and a member
temperature that trails the program by r tau on ramps (a delay of tau), catches up
exponentially on dwells, and is per member; the form ``split`` (two first-order stages in
series): split = 0 is the first-order lag, every split trails a settled ramp by r tau, the
split shapes the start of a ramp, the near-equal-stage branches join without a jump, and the
derivatives in split and at tau = 0 are right. The closed form against an ODE integration is
in tests/verification/test_effects_physics.py."""

import math

import mpmath
import pytest
import torch

from solderpyro.effects import EFFECTS, EffectSet
from solderpyro.effects.thermal_lag import _CLOSE, SPLIT_MAX, lag
from solderpyro.fem.loading import REFERENCE_CYCLE

F64 = torch.float64
EFF = EFFECTS["thermal_lag"]
C = REFERENCE_CYCLE
RATE = 5.0 / 60.0  # K/s
#: the split where the divided difference switches from its direct form to the expm1 one
#: (tau_1 - tau_2 = _CLOSE tau_1)
S_SWITCH = (1.0 - _CLOSE) / (2.0 - _CLOSE)
#: times through the whole reference cycle, and just after each of its knots
TIMES = sorted({*(float(t) for t in torch.linspace(0.0, C.end, 79, dtype=F64)),
                *(k + d for k in C.times[:-1] for d in (1e-3, 1.0, 10.0))})


def _T(t, taus, splits=None):
    taus = torch.tensor(taus, dtype=F64)
    splits = torch.zeros_like(taus) if splits is None else torch.tensor(splits, dtype=F64)
    q = torch.stack([taus, splits], 1)
    return EFF.temperature(torch.full((len(taus),), C(t), dtype=F64), t, C, q)


def _lag(t, tau, split):
    """``lag`` ``(b,)`` K at ``t`` for ``(b,)`` lists (or floats) of tau and split."""
    split = torch.as_tensor(split, dtype=F64).reshape(-1)
    tau = torch.as_tensor(tau, dtype=F64).reshape(-1) * torch.ones_like(split)
    return lag(C, t, tau, split)


def _old_first_order(t, tau):
    """The library's first-order closed form before the split existed:
    e = r tau + (e_a - r tau) exp(-(t - t_a)/tau) per segment."""
    e = 0.0
    for ta, tb, Ta, Tb in zip(C.times[:-1], C.times[1:], C.temps_C[:-1], C.temps_C[1:],
                              strict=True):
        if t <= ta:
            break
        r = (Tb - Ta) / (tb - ta)
        e = r * tau + (e - r * tau) * math.exp(-(min(t, tb) - ta) / tau)
    return e


def _lag_mp(t, tau, s):
    """The two-stage closed form per segment in 40 digits (mpmath), without the library's
    branches: (a1 - a2)/(tau_1 - tau_2) taken directly, its limit a dt/tau_1^2 at s = 1/2."""
    with mpmath.workdps(40):
        tau, s = mpmath.mpf(tau), mpmath.mpf(s)
        t1, t2 = (1 - s) * tau, s * tau
        e1 = e = mpmath.mpf(0)
        for ta, tb, Ta, Tb in zip(C.times[:-1], C.times[1:], C.temps_C[:-1], C.temps_C[1:],
                                  strict=True):
            if t <= ta:
                break
            r = mpmath.mpf(Tb - Ta) / (tb - ta)
            dt = mpmath.mpf(min(t, tb) - ta)
            a1 = mpmath.exp(-dt / t1)
            if t2 == 0:
                a2, g = mpmath.mpf(0), a1 / t1
            elif t1 == t2:
                a2, g = a1, a1 * dt / t1 ** 2
            else:
                a2 = mpmath.exp(-dt / t2)
                g = (a1 - a2) / (t1 - t2)
            e1, e = (r * t1 + (e1 - r * t1) * a1,
                     r * tau + (e - r * tau) * a2 + (e1 - r * t1) * t1 * g)
        return float(e)


def test_off_is_the_program_exactly():
    assert EFF.off == (0.0, 0.0) and EFF.nuisance == ("split",)
    assert EFF.params.names == ("tau", "split") and EFF.params.units == ("s", "-")
    assert SPLIT_MAX == 0.5 and EFF.params.lower == (0.0, 0.0)
    assert EFF.params.upper == (300.0, 0.5)
    for t in (0.0, 300.0, 600.0, 2500.0, 7000.0, 7800.0):
        assert torch.equal(_T(t, [0.0]), torch.tensor([C(t)], dtype=F64))
        # at tau = 0 the split changes nothing (a form of nothing)
        assert torch.equal(_T(t, [0.0, 0.0, 0.0], [0.0, 0.3, 0.5]),
                           torch.full((3,), C(t), dtype=F64))


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
        EffectSet(["thermal_lag"]).check(torch.tensor([[-1.0, 0.0]], dtype=F64))


# ------------------------------------------------------------------ the form: split

def test_split_0_is_the_first_order_lag():
    """split = 0 (and split None, the default) is the previous first-order closed form over
    the whole reference cycle, tau from 1 ms to the box's top: to 1e-12 K (the new form
    multiplies a1 by tau_1 / tau_1 and carries e1 beside e: a few ulps of r tau; 3.6e-15 K
    measured); on the first ramp it is r tau (1 - e^(-t/tau)) to 1e-12 K as well (absolute:
    for t << tau the closed form r tau + (0 - r tau) e^(-t/tau) cancels, leaving an error of
    ~eps r tau, 1e-11 relative at t = 1 ms, tau = 60 s)."""
    taus = [1e-3, 5.0, 60.0, 300.0]
    for t in TIMES:
        e = _lag(t, taus, [0.0] * 4)
        assert torch.equal(e, lag(C, t, torch.tensor(taus, dtype=F64)))
        for j, tau in enumerate(taus):
            assert abs(e[j].item() - _old_first_order(t, tau)) <= 1e-12, (t, tau)
            if 0.0 < t <= 600.0:
                ramp = RATE * tau * -math.expm1(-t / tau)
                assert abs(e[j].item() - ramp) <= 1e-12, (t, tau)


def test_every_split_trails_a_settled_ramp_by_r_tau():
    """First ramp from rest, tau = 60 s, t = 540 s (9 tau): the lag is
    r tau - r (tau_1^2 a_1 - tau_2^2 a_2)/(tau_1 - tau_2) (the cascade's ramp response;
    r tau - r (tau + t) a_1 for two equal stages), to 1e-12 relative; and r tau minus it,
    the settling error, is r E[(D - t)+] with D the cascade's delay (a sum of two independent
    exponentials of means tau_1, tau_2): in [0, r tau e^(-t/tau)] = [0, 6.2e-4 K] for every
    split, because a sum of exponentials is smaller in the convex order than the exponential
    of the same mean (the first-order lag, split 0, attains the bound; split 1/2 settles to
    7.6e-7 K)."""
    tau, t = 60.0, 540.0
    bound = RATE * tau * math.exp(-t / tau)
    splits = [0.0, 0.1, 0.2, 0.25, 0.3, 0.4, 0.45, 0.5]
    e = _lag(t, tau, splits)
    for j, s in enumerate(splits):
        t1, t2 = (1.0 - s) * tau, s * tau
        a1, a2 = math.exp(-t / t1), (math.exp(-t / t2) if t2 > 0 else 0.0)
        if s < 0.5:
            expect = RATE * tau - RATE * (t1 * t1 * a1 - t2 * t2 * a2) / (t1 - t2)
        else:
            expect = RATE * tau - RATE * (tau + t) * a1
        assert e[j].item() == pytest.approx(expect, rel=1e-12), s
        settle = RATE * tau - e[j].item()
        assert 0.0 <= settle <= bound * (1 + 1e-9), (s, settle, bound)
    assert RATE * tau - e[0].item() == pytest.approx(bound, rel=1e-9)
    assert RATE * tau - e[-1].item() < 1e-6  # two equal stages: 7.6e-7 K


def test_the_split_shapes_the_start_of_a_ramp():
    """At t = tau/4 into the first ramp (tau = 60 s) the first-order lag is
    r tau (1 - e^(-1/4)) = 1.106 K and the two-equal-stage one r tau (1 - 5/4 e^(-1/2)) =
    1.209 K (1e-12): the second-order specimen has hardly started to move, so it lags MORE
    early on (the lag is r E[min(D, t)], larger for the less variable delay D), by 0.10 K,
    and the lag at tau/4 grows with the split. Once settled the splits agree (above)."""
    tau, t = 60.0, 15.0
    splits = [0.0, 0.1, 0.2, 0.3, 0.4, 0.5]
    e = _lag(t, tau, splits)
    assert e[0].item() == pytest.approx(RATE * tau * -math.expm1(-0.25), rel=1e-12)
    assert e[-1].item() == pytest.approx(RATE * tau * (1 - 1.25 * math.exp(-0.5)), rel=1e-12)
    assert e[-1].item() - e[0].item() > 0.1
    assert bool((e[1:] > e[:-1]).all()), e


def test_the_near_equal_stage_branches_join_without_a_jump():
    """The divided difference (a1 - a2)/(tau_1 - tau_2) is taken directly for split below
    S_SWITCH = 0.49975, through expm1 above it, by a series where |x| < 1e-5, and by its limit
    at split 1/2. Across all of them (0.4, 0.4995, 0.49949, S_SWITCH -+ 1e-9, 0.5 - 1e-k up to
    k = 12, 0.5) and over the reference cycle, tau = 5, 60, 300 s, the lag equals the same
    closed form evaluated in 40 digits without branches to 1e-12 of r tau (the direct form's
    cancellation near the switch costs ~ eps tau_2 / (tau_1 - tau_2) ~ 1e-13; 3.4e-14
    measured). And straight across S_SWITCH the step is what autograd's d lag/d split
    predicts, to 1e-12 of r tau (3.4e-14 measured): no jump."""
    splits = [0.4, 0.4995, 0.49949, S_SWITCH * (1 - 1e-9), S_SWITCH * (1 + 1e-9), 0.5,
              *(0.5 - 10.0 ** -k for k in range(2, 13))]
    for tau in (5.0, 60.0, 300.0):
        tol = 1e-12 * RATE * tau
        for t in TIMES:
            e = _lag(t, tau, splits)
            for j, s in enumerate(splits):
                assert abs(e[j].item() - _lag_mp(t, tau, s)) <= tol, (tau, t, s)
            if t == 0.0:  # the lag is the constant 0 there
                continue
            s = torch.tensor([S_SWITCH], dtype=F64, requires_grad=True)
            (g,) = torch.autograd.grad(lag(C, t, torch.tensor([tau], dtype=F64), s).sum(), s)
            step = e[4] - e[3]
            assert abs((step - g[0] * 2e-9 * S_SWITCH).item()) <= tol, (tau, t)


@pytest.mark.parametrize("s0", [0.25, 0.4999])
@pytest.mark.parametrize("tau", [60.0, 300.0])
def test_derivative_in_split_matches_finite_differences(s0, tau):
    """Autograd d lag/d split against central differences over the reference cycle, to 1e-6
    of max|d lag/d split| (at 0.25: h = 1e-5, truncation and rounding eps r tau / h both
    ~1e-10 of it, 3.6e-10 measured; at 0.4999, the expm1 branch, where the derivative is
    small (odd about 1/2, where split and 1 - split are the same law): h = 1e-4, reaching
    split 1/2, rounding ~1e-15 r tau / h ~ 5e-8 of it, 3.8e-8 measured)."""
    h = 1e-5 if s0 == 0.25 else 1e-4
    g, fd = [], []
    for t in TIMES[1:]:  # t = 0: the lag is the constant 0
        s = torch.tensor([s0], dtype=F64, requires_grad=True)
        (gi,) = torch.autograd.grad(lag(C, t, torch.tensor([tau], dtype=F64), s).sum(), s)
        e = _lag(t, tau, [s0 + h, s0 - h])
        g.append(gi.item())
        fd.append((e[0] - e[1]).item() / (2 * h))
    g, fd = torch.tensor(g), torch.tensor(fd)
    scale = g.abs().max().item()
    # the split matters: max|d lag/d split| is 1.02 K (0.25) and 4.4e-4 K (0.4999) at
    # tau = 60 s, 5.4 K and 2.2e-3 K at 300 s; half of that at least (r tau / 5 K = tau / 60 s)
    assert scale > (0.5 if s0 == 0.25 else 2e-4) * RATE * tau / 5.0
    assert (g - fd).abs().max().item() <= 1e-6 * scale


@pytest.mark.parametrize("tau", [60.0, 300.0])
def test_derivative_in_split_at_0_is_the_two_stage_one_sided_derivative(tau):
    """At split = 0 (one lag, the box's lower edge, where a refit of the form starts) autograd
    must give the one-sided derivative of the two-stage law, not that of the one-stage formula
    alone (which misses the second stage's share and is about twice it): against the
    second-order one-sided difference (-3 f(0) + 4 f(h) - f(2h)) / 2h with h = 1e-6
    (truncation ~h^2 times the third derivative, ~1e-12 of it; rounding ~eps r tau / h, ~1e-9
    of it), to 1e-6 of max|d lag/d split|."""
    g, fd = [], []
    for t in TIMES[1:]:
        s = torch.zeros(1, dtype=F64, requires_grad=True)
        (gi,) = torch.autograd.grad(lag(C, t, torch.tensor([tau], dtype=F64), s).sum(), s)
        e = _lag(t, tau, [0.0, 1e-6, 2e-6])
        g.append(gi.item())
        fd.append(((-3.0 * e[0] + 4.0 * e[1] - e[2]) / 2e-6).item())
    g, fd = torch.tensor(g), torch.tensor(fd)
    scale = g.abs().max().item()
    assert scale > 0.1 * RATE * tau / 5.0  # the form matters where tau is large
    assert (g - fd).abs().max().item() <= 1e-6 * scale, (g, fd)


@pytest.mark.parametrize("split", [0.0, 0.3, 0.5])
def test_derivative_in_tau_at_tau_0_is_the_program_rate(split):
    """At tau = 0 the lag is 0 and its one-sided derivative in tau is the program's rate at t
    (r on a ramp, 0 on a dwell), for every split: the lag grows as r tau as tau leaves 0, the
    score a test at "off" uses. Autograd must give it exactly (1e-15), and the one-sided
    difference lag(h)/h with h = 1e-3 s agrees to 1e-12 K/s at times >= 10 s after a knot
    (the transients decay as e^(-10 s / h))."""
    for t in (10.0, 300.0, 1200.0, 2500.0, 4600.0, 7000.0):
        i = max(k for k, kn in enumerate(C.times) if kn < t)
        rate = (C.temps_C[i + 1] - C.temps_C[i]) / (C.times[i + 1] - C.times[i])
        tau = torch.zeros(1, dtype=F64, requires_grad=True)
        e = lag(C, t, tau, torch.tensor([split], dtype=F64))
        (g,) = torch.autograd.grad(e.sum(), tau)
        assert e.item() == 0.0
        assert abs(_lag(t, 1e-3, split).item() / 1e-3 - rate) <= 1e-12, (t, split)
        assert g.item() == pytest.approx(rate, rel=1e-15, abs=1e-15), (t, split, g.item())


def test_split_outside_its_range_is_rejected_by_name():
    fx = EffectSet(["thermal_lag"])
    fx.check(torch.tensor([[60.0, 0.0], [60.0, 0.5]], dtype=F64))  # the box's edges are fine
    for bad in (0.6, -0.1):
        with pytest.raises(ValueError, match=r"thermal_lag: split .* within \[0, 0.5\]"):
            fx.check(torch.tensor([[60.0, 0.2], [60.0, bad]], dtype=F64))
