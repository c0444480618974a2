"""Anand viscoplasticity as pure functions (flow rule, hardening, closed forms).

Parameters come as a tensor ``p`` of shape ``(..., 9)`` in the order of
:data:`solderpyro.params.ANAND_NAMES` (s0, QR, A, xi, m, h0, s_hat, n, a), units MPa, K, 1/s.
Temperatures are in kelvin. All functions broadcast over leading dimensions.
"""

from __future__ import annotations

import math

import torch

LOG2 = math.log(2.0)


def unpack(p: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Split ``(..., 9)`` parameters into nine ``(...)`` tensors."""
    return tuple(p[..., i] for i in range(9))


def log_sinh(y: torch.Tensor) -> torch.Tensor:
    """``log(sinh(y))`` for ``y > 0`` without overflow: ``y + log(-expm1(-2y)) - log 2``.

    Exact to rounding for ``1e-300 < y < 1e300``.
    """
    return y + torch.log(-torch.expm1(-2.0 * y)) - LOG2


def saturation(rate: torch.Tensor, T: torch.Tensor,
               p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Closed-form saturation at constant inelastic rate and temperature (the Anand law of
    docs/configuration.md, "The reference case").

    Args:
        rate: equivalent inelastic strain rate, 1/s.
        T: temperature, K.
        p: ``(..., 9)`` Anand constants.
    Returns:
        ``(sigma_star, s_star)`` in MPa: ``s* = s_hat Z^n``, ``sigma* = (s*/xi) asinh(Z^m)``
        with ``Z = (rate/A) exp(QR/T)``.
    """
    _, QR, A, xi, m, _, s_hat, n, _ = unpack(p)
    logZ = torch.log(rate / A) + QR / T
    s_star = s_hat * torch.exp(n * logZ)
    return s_star / xi * torch.asinh(torch.exp(m * logZ)), s_star


def s_closed_form(eps_p: torch.Tensor, rate: torch.Tensor, T: torch.Tensor,
                  p: torch.Tensor) -> torch.Tensor:
    """Deformation resistance ``s(eps_p)`` at constant rate and temperature, MPa.

    The exact solution of ``ds/deps_p = h0 |1 - s/s*|^a sign(1 - s/s*)`` from ``s(0) = s0``
    with ``s*`` fixed: ``s = s* -+ [|s* - s0|^(1-a) + (a-1) h0 s*^(-a) eps_p]^(1/(1-a))``
    (``-`` for ``s0 < s*``, ``+`` above), and ``s = s* - (s* - s0) exp(-h0 eps_p / s*)`` for
    ``a == 1``.

    Valid for any ``a > 0``; for ``a == 1`` the exponential form is used; for ``a < 1`` s
    reaches ``s*`` at a finite strain and stays there.
    """
    s0, _, _, _, _, h0, _, _, a = unpack(p)
    _, s_star = saturation(rate, T, p)
    sign = torch.sign(s_star - s0)
    d0 = (s_star - s0).abs()
    a1 = (a - 1.0).abs() < 1e-12
    a_safe = torch.where(a1, torch.full_like(a, 2.0), a)
    # for a < 1, s reaches s* at a finite strain (inner = 0) and stays there
    inner = (d0 ** (1 - a_safe) + (a_safe - 1) * h0 * s_star ** (-a_safe) * eps_p).clamp_min(0)
    d_pow = inner ** (1.0 / (1 - a_safe))
    d_exp = d0 * torch.exp(-h0 * eps_p / s_star)
    return s_star - sign * torch.where(a1, d_exp, d_pow)


def hardening_residual(s: torch.Tensor, s_n: torch.Tensor, log_dep: torch.Tensor,
                       log_Z: torch.Tensor, p: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Backward-Euler residual of the s-equation and its partial derivatives.

    ``H = s - s_n - h0 * dep * |1 - s/s*|^a * sign(1 - s/s*)``, ``s* = s_hat * Z^n``.

    Args:
        s, s_n: end-of-step and start-of-step resistance, MPa.
        log_dep: log of the inelastic strain increment ``dep``.
        log_Z: log of ``(dep/dt/A) exp(QR/T)`` (Zener-Hollomon parameter).
        p: ``(..., 9)`` Anand constants.
    Returns:
        ``(H, dH/ds, dH/dlog_dep, s_star)``; ``dH/dlog_dep`` includes the dependence of
        ``s*`` on the rate (``dlogZ/dlog_dep = 1``).
    """
    _, _, _, _, _, h0, s_hat, n, a = unpack(p)
    s_star = s_hat * torch.exp(n * log_Z)
    r = 1.0 - s / s_star
    ar = r.abs().clamp_min(1e-300)
    phi = ar**a * torch.sign(r)
    dphi_dr = a * ar ** (a - 1.0)
    dep = torch.exp(log_dep)
    H = s - s_n - h0 * dep * phi
    dH_ds = 1.0 + h0 * dep * dphi_dr / s_star
    dH_dL = -h0 * dep * (phi + dphi_dr * n * s / s_star)
    return H, dH_ds, dH_dL, s_star
