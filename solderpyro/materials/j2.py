"""Rate-independent J2 (von Mises) plasticity with linear isotropic hardening, 3-D radial return.

For a linear elastic material made elasto-plastic (the copper next to the solder, effect
``copper_plasticity``). Mandel 4-vectors ``(xx, yy, zz, sqrt2*xy)`` as in :mod:`.integrate`.

    yield function   f = q - (sigma_y + H * ebar),   q = sqrt(3/2) |dev sigma|
    flow             deps_p = dgamma * (3/2) dev(sigma) / q,   d ebar = dgamma

Backward Euler is the closed-form radial return: with the trial deviator
``s_tr = 2G dev(eps - eps_p_n)`` (the isotropic thermal strain has no deviator) and
``q_tr = sqrt(3/2) |s_tr|``,

    dgamma = max(q_tr - sigma_y - H ebar_n, 0) / (3G + H),
    dev sigma = (1 - 3G dgamma / q_tr) s_tr,    p = K tr(eps - eps_p_n - eps_th m),

so on the plastic branch ``q = sigma_y + H (ebar_n + dgamma)`` exactly. On the elastic branch
``dgamma = 0`` and the factor is exactly 1: the update is the elastic law to the last bit. The
consistent tangent (Simo and Hughes, box 3.2) has the factored form of
:class:`~.integrate.Tangent3D`,

    C = K m m^T + 2G theta P_dev - 2G thetabar nb nb^T,
    theta = 1 - 3G dgamma / q_tr,   thetabar = 3G/(3G + H) - (1 - theta)  (0 when elastic),

``nb = s_tr/|s_tr|``. The update is a closed form, so autograd differentiates it directly
(w.r.t. strain, thermal strain, yield stress and state).

State (:class:`~.integrate.PointState`): ``eps_p`` the plastic strain (deviatoric), ``s`` the
accumulated equivalent plastic strain ``ebar`` (dimensionless), ``eps_zz`` the total
out-of-plane strain.
"""

from __future__ import annotations

import math

import torch

from solderpyro.materials.elastic import ZZ, bulk_shear
from solderpyro.materials.integrate import PointState, Tangent3D

SQRT32 = math.sqrt(1.5)


def j2_update(eps: torch.Tensor, state: PointState, eps_th, E: float, nu: float,
              sigma_y, H: float, tangent: bool = True):
    """Radial return for a given total strain.

    Args:
        eps: end-of-step total strain, Mandel ``(..., 4)``.
        state: start-of-step :class:`PointState`, leading shape ``(...)`` (``s`` = ebar).
        eps_th: free (isotropic) thermal strain, broadcastable to ``(...)``.
        E: Young's modulus, MPa; nu: Poisson's ratio.
        sigma_y: initial yield stress, MPa, broadcastable to ``(...)`` (e.g. ``(b, 1, 1)``).
        H: linear isotropic hardening modulus, MPa (>= 0).
        tangent: whether to return the consistent tangent (as a :class:`Tangent3D`).
    Returns:
        ``(sigma (..., 4) MPa, new_state, C (Tangent3D) or None, dgamma (...))``.
    """
    K, G = bulk_shear(E, nu)
    m = torch.tensor([1.0, 1.0, 1.0, 0.0], dtype=eps.dtype, device=eps.device)
    ee = eps - state.eps_p - torch.as_tensor(eps_th, dtype=eps.dtype)[..., None] * m
    tr = ee[..., :3].sum(-1)
    s_tr = 2.0 * G * (ee - tr[..., None] * m / 3.0)  # (..., 4)
    nrm = torch.sqrt((s_tr * s_tr).sum(-1) + torch.finfo(eps.dtype).tiny * 1e6)
    q_tr = SQRT32 * nrm
    f = q_tr - sigma_y - H * state.s
    dgamma = torch.clamp(f, min=0.0) / (3.0 * G + H)
    theta = 1.0 - 3.0 * G * dgamma / q_tr
    sigma = (K * tr)[..., None] * m + theta[..., None] * s_tr
    deps_p = (SQRT32 * dgamma / nrm)[..., None] * s_tr  # (3/2) dgamma s_tr / q_tr
    new = PointState(state.eps_p + deps_p, state.s + dgamma, eps[..., ZZ])
    C = None
    if tangent:
        with torch.no_grad():
            plastic = (f > 0).to(eps.dtype)
            th = theta.detach()
            coef = -2.0 * G * plastic * (3.0 * G / (3.0 * G + H) - (1.0 - th))
            C = Tangent3D(torch.full_like(th, K), 2.0 * G * th, coef,
                          (s_tr / nrm[..., None]).detach())
    return sigma, new, C, dgamma
