"""Anand + Prager kinematic hardening at a material point against closed forms.

(b) constant inelastic rate and temperature, pure shear: sigma_eq = q_Anand(s(eps_p)) + C_k eps_p;
(c) Bauschinger effect: at the same s and rate, reverse flow needs a stress lower by 2 X_eq.
"""

import math
import sys
from pathlib import Path

import pytest
import torch

from solderpyro.materials.integrate import PointInputs, _solve_s, anand_update, initial_state
from solderpyro.materials.kinematic import equivalent, flow_stress_closed_form, strain_equivalent
from solderpyro.params import LIU2008, WANG2001, anand_tensor

sys.path.insert(0, str(Path(__file__).resolve().parent))
from shear_points import constant_rate_cases, shear  # noqa: E402

E, NU = 32000.0, 0.35
G = E / (2.0 * (1.0 + NU))
# (constants, T in C, eq. inelastic rate 1/s, C_k MPa, s0 / s*): s0 below and above s*
CASES = [(WANG2001, 25, 1e-4, 3000.0, 0.6), (WANG2001, 125, 1e-6, 500.0, 0.6),
         (LIU2008, 75, 1e-5, 1000.0, 0.5), (LIU2008, 75, 1e-5, 1000.0, 1.8),
         (LIU2008, 125, 1e-4, 20000.0, 0.5), (WANG2001, 25, 1e-4, 0.0, 0.6)]


def _drive_constant_rate(n, p, T, rate, Ck, eps_end):
    """Pure shear holding the equivalent inelastic rate: n steps of dep = h = eps_end/n.

    Step k's shear strain is the one at which the backward-Euler solution of the model has
    eps_p = k*h: s_k from the hardening equation with dep = h (as in the s-transient test),
    sigma_eq = (s_k/xi) asinh(Z^m) + C_k k h from the flow rule and X_eq = C_k eps_p, and
    gamma = sigma_eq/(sqrt3 G) + sqrt3 k h from elasticity. The update must then return
    dep = h and that stress. Returns the final sigma_eq and the worst relative step errors.
    """
    QR, A, xi, m = p[:, 1], p[:, 2], p[:, 3], p[:, 4]
    h = eps_end / n
    dt = h / rate
    c, L = torch.log(dt * A) - QR / T, torch.log(h)
    c_flow = torch.asinh(torch.exp(m * (torch.log(rate / A) + QR / T))) / xi
    st = initial_state((len(h),), p[:, 0], kinematic=True)
    s = p[:, 0].clone()
    err = torch.zeros(3)
    for k in range(1, n + 1):
        s, _, _ = _solve_s(L, c, s.clone(), s.clone(), p)
        target = c_flow * s + Ck * k * h
        gamma = target / (math.sqrt(3.0) * G) + math.sqrt(3.0) * k * h
        sig, st, _, dep, _ = anand_update(shear(gamma), st, p,
                                          PointInputs(T, dt, 0.0, E, NU, Ck), "strain",
                                          tangent=False)
        q = equivalent(sig)
        x_err = (equivalent(st.X) - Ck * strain_equivalent(st.eps_p)).abs() / target
        err = torch.maximum(err, torch.stack([((dep - h) / h).abs().max(),
                                              ((q - target) / target).abs().max(),
                                              x_err.max()]))
    return q, err


def test_constant_rate_flow_stress_matches_closed_form():
    """(b) sigma_eq(eps_p) = q_Anand(s(eps_p)) + C_k eps_p at constant rate and T.

    Every step: the update returns the discrete solution the driver asks for (dep to 1e-10,
    sigma_eq to 1e-10, X_eq = C_k eps_p to 1e-13: the solver's tolerances are R < 1e-11 on the
    log flow rule and 1e-13 on the hardening residual). At eps_p = 0.6 s*/h0 the only
    discretisation error is backward Euler's O(h) in s (the back stress is linear in eps_p and
    exact); Richardson extrapolation of n = 50, 100, 200 steps removes O(h) and O(h^2) and must
    meet the closed form to 1e-6 (measured ~5e-9). C_k from 0 to 20000 MPa, s0 < s* and > s*.
    """
    p, T, rate, Ck, eps_end = constant_rate_cases(CASES)
    (q1, e1), (q2, e2), (q4, e4) = (_drive_constant_rate(n, p, T, rate, Ck, eps_end)
                                    for n in (50, 100, 200))
    err = torch.maximum(torch.maximum(e1, e2), e4)
    assert err[0] < 1e-10 and err[1] < 1e-10 and err[2] < 1e-13
    r1, r2 = 2 * q2 - q1, 2 * q4 - q2
    rich = (4 * r2 - r1) / 3
    exact = flow_stress_closed_form(eps_end, rate, T, p, Ck)
    assert ((rich - exact) / exact).abs().max() <= 1e-6
    ratio = (q4 - exact) / (q1 - exact)
    assert torch.allclose(ratio, torch.full_like(ratio, 0.25), rtol=0.02)  # first order in h
    assert (Ck * eps_end / exact)[Ck > 0].min() > 0.01  # the back stress is a visible part


def _solve_rate(st, p, T, dt, Ck, gamma_n, bracket, h, iters=200):
    """Shear increment in ``bracket = (lo, hi) (n,)`` at which one step of ``dt`` gives dep = h
    (dep grows from lo to hi); bisection to rounding. Returns (sigma_eq signed, dep, s)."""
    lo, hi = bracket
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        _, _, _, dep, _ = anand_update(shear(gamma_n + mid), st, p,
                                       PointInputs(T, dt, 0.0, E, NU, Ck), "stress",
                                       tangent=False)
        lo, hi = torch.where(dep > h, lo, mid), torch.where(dep > h, mid, hi)
        if bool(((hi - lo).abs() <= 4e-16 * hi.abs()).all()):
            break
    sig, st1, _, dep, _ = anand_update(shear(gamma_n + 0.5 * (lo + hi)), st, p,
                                       PointInputs(T, dt, 0.0, E, NU, Ck), "stress",
                                       tangent=False)
    return math.sqrt(1.5) * sig[:, 3], dep, st1.s


@pytest.mark.parametrize("TC", [25.0, 125.0])
def test_bauschinger_offset_is_twice_back_stress(TC):
    """(c) After forward shear (constant total rate 1e-3/s to gamma = 0.04, plane stress), the
    stress needed for flow at the forward rate in reverse is lower by 2 X_eq = 2 C_k eps_p.

    From the end state (s_n, X_n) one more step is taken forward and one in reverse, each with
    the strain found by bisection so that dep equals the last forward increment. Both end with
    the same s (s depends on dep only) and q, so sigma_f = q + X_n + C_k h and
    sigma_r = X_n - C_k h - q (signed, shear sense): sigma_f + sigma_r = 2 X_n exactly. The
    bound 1e-9*sigma_f covers dep matched to ~1e-14 (d sigma/d log dep <= sigma) and the local
    solver tolerance (1e-11 on the log flow rule); measured ~1e-15. C_k = 0 is symmetric.
    """
    Ck = torch.tensor([0.0, 1000.0, 5000.0, 20000.0])
    p, T, dt = anand_tensor(base=LIU2008), TC + 273.15, 1.0
    st = initial_state((len(Ck),), p[0], kinematic=True)
    for k in range(1, 41):
        gamma_n = torch.full_like(Ck, 1e-3 * dt * k)
        sig, st, _, dep, _ = anand_update(shear(gamma_n), st, p,
                                          PointInputs(T, dt, 0.0, E, NU, Ck), "stress")
    ep = strain_equivalent(st.eps_p)
    assert torch.allclose(equivalent(st.X), Ck * ep, rtol=1e-13, atol=0)  # proportional
    zero_xi = (st.X[:, 3] - sig[:, 3]) / (math.sqrt(2.0) * G)  # increment with xi_tr = 0
    far = 4.0 * equivalent(sig) / G
    sf, dep_f, s_f = _solve_rate(st, p, T, dt, Ck, gamma_n, (zero_xi, zero_xi + far), dep)
    sr, dep_r, s_r = _solve_rate(st, p, T, dt, Ck, gamma_n, (zero_xi, zero_xi - far), dep)
    assert torch.allclose(dep_f, dep, rtol=1e-12) and torch.allclose(dep_r, dep, rtol=1e-12)
    assert torch.allclose(s_f, s_r, rtol=1e-12)
    offset = sf + sr  # = sigma_f - |sigma_r| while the reverse stress is negative
    assert torch.allclose(offset, 2.0 * Ck * ep, rtol=0, atol=1e-9 * sf.max().item())
    assert (2.0 * Ck * ep)[1:].min() > 0.5  # MPa: the effect is far above the tolerance
