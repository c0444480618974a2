"""Kinematic hardening on top of the Anand flow, linear (Prager) with optional Armstrong-Frederick
dynamic recovery: equations and closed forms.

The update itself lives in :func:`solderpyro.materials.integrate.return_map_3d` (the fields
``C_k`` and ``gamma_k`` of its ``PointInputs``, the state fields ``PointState.X`` and
``PointState.p_rate``); this module documents it and gives the closed forms the tests check it
against.

Notation (Mandel 4-vectors ``(xx, yy, zz, sqrt2*xy)``, so ``a:b = a.b`` and ``|a|`` is the
tensor norm): for a deviator ``a`` the von Mises equivalent is ``a_eq = sqrt(3/2)*|a|``; for an
inelastic strain increment ``d`` (deviatoric) the equivalent is ``d_eq = sqrt(2/3)*|d|``.

Model
    effective stress    xi = dev(sigma) - X                 (X the back stress, deviatoric)
    flow rule           deps_p = (3/2) * dep * xi / q,      q = xi_eq = sqrt(3/2)*|xi|
                        dep = dt*A*exp(-QR/T) * sinh(xi_A*q/s)^(1/m)   (Anand, with q for sigma)
    resistance          ds = h0*|1 - s/s*|^a sign(1 - s/s*) * dep      (unchanged)
    back stress         dX = (2/3) * C_k * deps_p                       (C_k in MPa)

Backward Euler, radial return on ``xi`` (von Mises + linear Prager keep it radial). With the
unit direction ``n = xi/|xi|``, ``deps_p = sqrt(3/2)*dep*n``, and the trial effective stress
``xi_tr = s_tr - X_n`` (``s_tr = 2G dev(eps - eps_p_n)``)::

    xi = s_tr - 2G*deps_p - X_n - (2/3)*C_k*deps_p
       = xi_tr - (2G + 2C_k/3) * sqrt(3/2) * dep * n

so ``n = xi_tr/|xi_tr|`` and, multiplying the norms by sqrt(3/2),

    q = q_tr - (3G + C_k) * dep,        q_tr = sqrt(3/2)*|xi_tr|.

This is the isotropic return with ``3G -> 3G + C_k``, i.e. ``G -> Gk = G + C_k/3``. The logit form
of :mod:`.integrate` carries over unchanged: ``q = q_tr*sigmoid(zeta)``,
``dep = q_tr*sigmoid(-zeta)/(3*Gk)``, and the flow and hardening residuals in ``(zeta, s)`` are
those of the isotropic model with ``Gk`` in ``log(dep)``. Then

    deps_p  = sigmoid(-zeta)/(2*Gk) * xi_tr                      (= (3/2) dep xi_tr/q_tr)
    X       = X_n + (2/3)*C_k*deps_p
    sigma   = K tr(eps - eps_th) m + sigmoid(zeta)*xi_tr + X      (dev(sigma) = xi + X)

With ``C_k = 0``: ``Gk = G + 0 = G`` and ``X = X_n + 0``, the isotropic update to the last bit.

Consistent tangent. ``dev(sigma) = X_n + phi*xi_tr`` with
``phi = sigmoid(zeta) + sigmoid(-zeta)*(C_k/3)/Gk = 1 - sigmoid(-zeta)*G/Gk``;
``d xi_tr = 2G P_dev d eps`` and ``zeta`` depends on ``eps`` only through ``log q_tr``
(``d log q_tr = 2G nb.d eps/|xi_tr|``, ``nb = xi_tr/|xi_tr|``). Hence the same factored form
``C = K m m^T + g2 P_dev + coef nb nb^T`` as without back stress, with

    g2   = 2G * phi,
    coef = 2G * (G/Gk) * sigmoid(zeta)*sigmoid(-zeta)*dzeta/dlog(q_tr),

and ``sigmoid*sigmoid'*dzeta/dlog q_tr`` is the closed-form bracket of the isotropic tangent
(``log(3Gk)`` is a constant of the residual, so the bracket is unchanged in form).

Elastic predictor (plane stress ``eps_zz``): without new flow ``sigma = C_el(eps - eps_p -
eps_th)``; ``X`` does not enter, so :func:`.integrate.ezz_predictor` is unchanged.

Closed form at constant inelastic rate and temperature, proportional (e.g. pure shear or
uniaxial) loading from ``X = 0``: ``X`` stays collinear with ``xi``, ``X_eq = C_k*eps_p_eq`` and

    sigma_eq(eps_p) = q_Anand(s(eps_p)) + C_k*eps_p,   q_Anand = (s/xi_A)*asinh(Z^m)

with ``s(eps_p)`` the closed-form transient of :func:`.anand.s_closed_form`. Reversing the
direction at the same rate and the same ``s`` needs ``xi = -q`` instead of ``+q``: the reverse
flow stress is lower in magnitude by ``2*X_eq`` (Bauschinger effect).

Armstrong-Frederick dynamic recovery
    back stress         dX = (2/3) * C_k * deps_p - gamma_k * X * dp,   dp = sqrt(2/3)*|deps_p|

with ``gamma_k >= 0`` dimensionless (``gamma_k = 0``: Prager). Under monotonic proportional
loading from ``X = 0``, ``dX_eq/deps_p = C_k - gamma_k X_eq``, so

    X_eq(eps_p) = (C_k/gamma_k) * (1 - exp(-gamma_k*eps_p))      (-> C_k*eps_p as gamma_k -> 0)

saturates at ``C_k/gamma_k`` (initial slope ``C_k`` as in Prager).

Backward Euler of the recovery term, ``X = X_n + (2/3) C_k Deps_p - gamma_k X Dp``, gives

    X = a * (X_n + (2/3)*C_k*Deps_p),           a = 1/(1 + gamma_k*Dp),

which for a GIVEN factor ``a`` is the Prager update with ``X_n -> a X_n`` and ``C_k -> a C_k``:

    xi = s_tr - 2G*Deps_p - a X_n - (2/3)*a C_k*Deps_p
       = (s_tr - a X_n) - (2G + (2/3)*a C_k) * sqrt(3/2) * Dp * n,

radial along ``s_tr - a X_n``, ``q = sqrt(3/2)|s_tr - a X_n| - (3G + a C_k)*Dp``. The fully
implicit scheme has ``a`` depend on the unknown ``Dp``, so the trial direction itself would
move with ``Dp``: a third unknown in the local solve, a new consistent tangent (``da/deps``) and
another C kernel. Instead ``a`` is LAGGED: it is taken from the point's equivalent inelastic
strain rate of the previous step, ``p_rate = Dp_prev/dt_prev`` (1/s, ``PointState.p_rate``),

    a = 1/(1 + gamma_k * p_rate * dt),

so within the step ``a`` is a constant and the step is exactly the Prager return above on
``(a X_n, a C_k)`` (:func:`solderpyro.materials.integrate.lagged_prager`): its solve, its
closed-form consistent tangent (consistent with this scheme: ``a`` does not vary with the
step's strain) and the native kernel apply unchanged. After the step the state stores
``p_rate = Dp/dt`` (``Dp = sqrt(2/3)|eps_p - eps_p_n|``, the return's ``dep``). A rate, not
``Dp`` itself, is stored so that a step of another length (a halved sub-step, an SDIRK stage,
the growing pre-history steps) estimates its own ``Dp ~ p_rate*dt``. The virgin state has
``p_rate = 0`` (None): the first inelastic step is a Prager step.

Order. Where the rate is steady across steps the lagged ``a`` is the implicit one and the
scheme is backward Euler. Elsewhere the estimate is off by ``(p_rate_prev - p_rate)*dt``, which
is ``O(dt^2)`` per step where the rate is smooth (``O(dt)`` globally) and ``O(Dp)`` once in a
step where it jumps (the first inelastic step, a reversal): the scheme is first order in the
step, the order of backward Euler itself. Since ``0 < a <= 1`` at any step the recovery never
amplifies ``X``. At constant ``Dp = h`` from the virgin state the recursion
``X_1 = C_k h``, ``X_k = (X_(k-1) + C_k h)/(1 + gamma_k h)`` (equivalents) has the closed form

    X_eq,n = (C_k/gamma_k) * (1 - (1 - gamma_k h) * (1 + gamma_k h)^-(n-1)),   eps_p = n h,

whose error against the exact ``X_eq`` is ``-(h/2)*C_k*gamma_k*eps_p*exp(-gamma_k eps_p)
+ O(h^2)``: first order, with the same leading term as the fully implicit scheme (the lagged
first step costs ``O(h^2)`` there). With ``gamma_k = 0`` (``a = 1/(1 + 0) = 1`` exactly) or
``C_k = 0`` the numbers are those of Prager, resp. the isotropic model, to the last bit.
"""

from __future__ import annotations

import math

import torch

from solderpyro.materials.anand import s_closed_form, saturation


def equivalent(a: torch.Tensor) -> torch.Tensor:
    """Von Mises equivalent ``sqrt(3/2)*|dev a|`` of a Mandel ``(..., 4)``, ``(...)``."""
    m = torch.tensor([1.0, 1.0, 1.0, 0.0], dtype=a.dtype, device=a.device)
    d = a - a[..., :3].sum(-1, keepdim=True) / 3.0 * m
    return math.sqrt(1.5) * d.norm(dim=-1)


def strain_equivalent(d: torch.Tensor) -> torch.Tensor:
    """Equivalent ``sqrt(2/3)*|d|`` of a deviatoric Mandel strain ``(..., 4)``, ``(...)``."""
    return math.sqrt(2.0 / 3.0) * d.norm(dim=-1)


def back_stress_closed_form(eps_p: torch.Tensor, C_k: torch.Tensor | float,
                            gamma_k: torch.Tensor | float = 0.0) -> torch.Tensor:
    """Equivalent back stress ``X_eq`` ``(...)`` MPa under monotonic proportional loading from
    ``X = 0``: ``(C_k/gamma_k)*(1 - exp(-gamma_k*eps_p))``, evaluated as
    ``-C_k*expm1(-gamma_k*eps_p)/gamma_k`` (no cancellation for small ``gamma_k*eps_p``) and
    ``C_k*eps_p`` (Prager) where ``gamma_k = 0``.

    Args:
        eps_p: equivalent inelastic strain ``(...)``; C_k: modulus, MPa; gamma_k: recovery
            (dimensionless, >= 0); all broadcastable.
    """
    eps_p = torch.as_tensor(eps_p)
    g = torch.as_tensor(gamma_k, dtype=eps_p.dtype, device=eps_p.device)
    pos = g > 0
    gs = torch.where(pos, g, torch.ones_like(g))
    return C_k * torch.where(pos, -torch.expm1(-gs * eps_p) / gs, eps_p)


def flow_stress_closed_form(eps_p: torch.Tensor, rate: torch.Tensor, T: torch.Tensor,
                            p: torch.Tensor, C_k: torch.Tensor | float,
                            gamma_k: torch.Tensor | float = 0.0) -> torch.Tensor:
    """Von Mises stress at constant inelastic rate and temperature, proportional loading, MPa.

    ``sigma_eq = (s(eps_p)/xi)*asinh(Z^m) + X_eq(eps_p)``, ``Z = (rate/A) exp(QR/T)``, with
    ``X_eq`` of :func:`back_stress_closed_form` (``C_k*eps_p`` at ``gamma_k = 0``).

    Args:
        eps_p: equivalent inelastic strain (from the virgin state), ``(...)``.
        rate: equivalent inelastic strain rate, 1/s; T: temperature, K (broadcastable).
        p: ``(..., 9)`` Anand constants; C_k: Prager modulus, MPa; gamma_k: Armstrong-Frederick
            recovery, dimensionless (broadcastable).
    Returns:
        ``(...)`` flow stress in MPa.
    """
    sigma_star, s_star = saturation(rate, T, p)
    s = s_closed_form(eps_p, rate, T, p)
    return sigma_star * s / s_star + back_stress_closed_form(eps_p, C_k, gamma_k)
