"""Fully implicit (backward-Euler) Anand update at Gauss points, 3-D, plane stress or strain.

Unknowns per point: the return variable ``zeta`` (``q = q_tr*sigmoid(zeta)``, the logit of the
relaxed fraction of the trial von Mises stress), the deformation resistance ``s``, and in plane
stress the out-of-plane strain ``eps_zz`` (iterated until sigma_zz = 0). The flow rule is enforced
in log form,

    R = log(dep) - log(dt*A) + QR/T - log(sinh(xi*q/s))/m = 0,

which is asymptotically linear in ``zeta`` at both ends (elastic and fully relaxed). A joint
Newton on ``(zeta, s)`` from a warm start solves most points; the few it leaves unconverged fall
back to a bracketed Newton on ``zeta`` with ``s(zeta)`` solved exactly inside, which converges for
any ``xi*q/s`` and ``m`` (no overflow: ``log sinh`` is evaluated in log form). In plane stress
:func:`anand_update` iterates ``eps_zz`` locally; the FE solver instead updates it together with
the displacements.
The consistent tangent is closed form. When autograd is on, the converged values are corrected
by one Newton step with the graph attached, which gives exact first derivatives with respect to
the inputs (implicit-function theorem) without differentiating through the iterations.

Optional linear (Prager) kinematic hardening, ``C_k`` (MPa) of :class:`PointInputs` and the back
stress ``X`` of :class:`PointState`: the flow is driven by ``xi = dev(sigma) - X`` and the return
above runs on ``xi`` with ``3G`` replaced by ``3G + C_k`` (derivation in :mod:`.kinematic`).
``C_k = None`` and ``X = None`` is the isotropic model; ``C_k = 0`` gives the same numbers to the
last bit. Optional Armstrong-Frederick recovery of that back stress, ``gamma_k`` of
:class:`PointInputs` and the lagged equivalent inelastic strain rate ``p_rate`` of
:class:`PointState`: the step is the Prager return with ``X_n -> a X_n`` and ``C_k -> a C_k``,
``a = 1/(1 + gamma_k*p_rate*dt)`` fixed by the previous step (:func:`lagged_prager`; derivation,
and why lagged, in :mod:`.kinematic`); ``gamma_k = None`` or 0 is the Prager update to the last
bit.

On the CPU in float64 without autograd, :func:`return_map_3d` runs the same algorithm point by
point in C (:mod:`solderpyro._native`, compiled at first use; ``SOLDERPYRO_NATIVE=0`` or no
compiler: this torch code), with results equal to rounding; the torch code serves every other
device and dtype, and the implicit-function correction with the graph attached.

Shapes: strains and stresses are Mandel 4-vectors ``(..., 4)`` = (xx, yy, zz, sqrt2*xy).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, NamedTuple

import torch

from solderpyro import _native
from solderpyro.materials.anand import hardening_residual, unpack
from solderpyro.materials.elastic import ZZ, condense_zz

ZETA_MAX = 700.0


def _logsigmoid(z: torch.Tensor) -> torch.Tensor:
    """``log(sigmoid(z))``, stable. (``F.logsigmoid``'s CPU kernel parallelises with grain 1,
    which makes small calls wait on every thread under load: 10-40x slower here.)"""
    return torch.minimum(z, torch.zeros_like(z)) - torch.log1p(torch.exp(-z.abs()))


def _log_sinh_of_log(ly: torch.Tensor) -> torch.Tensor:
    """``log(sinh(exp(ly)))``, stable for any real ``ly``."""
    y = torch.exp(ly.clamp(max=700.0))
    small = ly < -18.0
    ys = torch.where(small, torch.ones_like(y), y)
    big = ys + torch.log(-torch.expm1(-2.0 * ys)) - 0.6931471805599453
    return torch.where(small, ly + y * y / 6.0, big)


def _y_coth(ly: torch.Tensor) -> torch.Tensor:
    """``y*coth(y)`` with ``y = exp(ly)``, stable (-> 1 as y -> 0)."""
    y = torch.exp(ly.clamp(max=700.0))
    small = ly < -9.0
    ys = torch.where(small, torch.ones_like(y), y)
    return torch.where(small, 1.0 + y * y / 3.0, ys / torch.tanh(ys))


@dataclass
class PointState:
    """Internal state at Gauss points.

    Attributes:
        eps_p: inelastic strain, Mandel ``(..., 4)``.
        s: deformation resistance, MPa, ``(...)``.
        eps_zz: total out-of-plane strain (plane stress; zero in plane strain), ``(...)``.
        X: back stress (deviatoric), MPa, Mandel ``(..., 4)``; ``None`` means zero (no kinematic
            hardening so far). Optional, so ``PointState(eps_p, s, eps_zz)`` keeps working.
        p_rate: equivalent inelastic strain rate of the last step, ``sqrt(2/3)|Delta eps_p| /
            dt`` (1/s), ``(...)``: what the Armstrong-Frederick recovery of the next step is
            lagged on (:func:`lagged_prager`); ``None`` means zero (no recovery so far).
    """

    eps_p: torch.Tensor
    s: torch.Tensor
    eps_zz: torch.Tensor
    X: torch.Tensor | None = None
    p_rate: torch.Tensor | None = None

    def index(self, idx) -> PointState:
        """The state of the points ``idx`` (any torch index of the leading dimensions)."""
        return PointState(self.eps_p[idx], self.s[idx], self.eps_zz[idx],
                          None if self.X is None else self.X[idx],
                          None if self.p_rate is None else self.p_rate[idx])

    def detach(self) -> PointState:
        """The same state cut from the autograd graph."""
        return PointState(self.eps_p.detach(), self.s.detach(), self.eps_zz.detach(),
                          None if self.X is None else self.X.detach(),
                          None if self.p_rate is None else self.p_rate.detach())


class PointInputs(NamedTuple):
    """The step's conditions of the Anand update at the points, each broadcastable to the
    points' shape ``(...)`` (floats, or tensors such as ``(b, 1, 1)`` per batch member).

    Attributes:
        T: end-of-step temperature, K.
        dt: step, s.
        eps_th: free thermal strain ``alpha*(T - T_ref)``, dimensionless.
        E: Young's modulus, MPa.
        nu: Poisson's ratio.
        C_k: Prager kinematic hardening modulus, MPa, or None / 0 for none (see
            :mod:`.kinematic`).
        gamma_k: Armstrong-Frederick recovery of that back stress (dimensionless,
            ``dX = (2/3) C_k deps_p - gamma_k X dp``), or None / 0 for none (Prager).
    """

    T: Any
    dt: Any
    eps_th: Any
    E: Any
    nu: Any
    C_k: Any = None
    gamma_k: Any = None


def initial_state(shape: tuple[int, ...], s0: torch.Tensor, *, kinematic: bool = False,
                  recovery: bool = False, **tkw) -> PointState:
    """Virgin state: zero strains, ``s = s0`` broadcast to ``shape``; with ``kinematic`` also a
    zero back stress ``X`` ``(*shape, 4)`` (else ``X = None``, which the update reads as zero),
    with ``recovery`` a zero lagged rate ``p_rate`` ``shape`` (else None, read as zero)."""
    return PointState(torch.zeros(*shape, 4, **tkw), torch.broadcast_to(s0, shape).clone(),
                      torch.zeros(shape, **tkw),
                      torch.zeros(*shape, 4, **tkw) if kinematic else None,
                      torch.zeros(shape, **tkw) if recovery else None)


class _Trial:
    """Elastic trial quantities for given total strain (Mandel).

    ``xi_tr = s_tr - X_n`` is the trial effective stress (``s_tr`` itself without back stress);
    ``nrm``, ``log_qtr`` are its norm and the log of its von Mises equivalent.
    """

    def __init__(self, eps, eps_p_n, eps_th, K, G, X_n=None):
        m = torch.tensor([1.0, 1.0, 1.0, 0.0], dtype=eps.dtype, device=eps.device)
        ee = eps - eps_p_n - eps_th[..., None] * m
        tr = ee[..., :3].sum(-1)
        self.m = m
        self.p = K * tr
        self.s_tr = 2.0 * G[..., None] * (ee - tr[..., None] * m / 3.0)
        self.xi_tr = self.s_tr if X_n is None else self.s_tr - X_n
        ss = (self.xi_tr * self.xi_tr).sum(-1) + torch.finfo(eps.dtype).tiny * 1e6
        self.nrm = torch.sqrt(ss)
        self.log_qtr = 0.5 * torch.log(1.5 * ss)


def _solve_s(L, c, s_n, s_guess, p, iters=60):
    """Solve the hardening residual for ``s`` given ``L = log(dep)`` (bracketed Newton)."""
    logZ = L - c
    _, _, _, _, _, h0, s_hat, n, _ = unpack(p)
    s_star = s_hat * torch.exp(n * logZ)
    lo, hi = torch.minimum(s_n, s_star), torch.maximum(s_n, s_star)
    s = torch.minimum(torch.maximum(s_guess, lo), hi)
    for _ in range(iters):
        H, dH_ds, dH_dL, _ = hardening_residual(s, s_n, L, logZ, p)
        done = H.abs() <= 1e-13 * s_n.abs() + 1e-300
        if bool(done.all()):
            break
        lo = torch.where(H < 0, s, lo)
        hi = torch.where(H > 0, s, hi)
        s_new = s - H / dH_ds
        bad = ~((s_new > lo) & (s_new < hi)) | ~torch.isfinite(s_new)
        s_new = torch.where(bad, 0.5 * (lo + hi), s_new)
        s = torch.where(done, s, s_new)
    H, dH_ds, dH_dL, _ = hardening_residual(s, s_n, L, logZ, p)
    return s, dH_ds, dH_dL


def _return_map(tr: _Trial, s_n, p, c, G, zeta0, iters=100):
    """Bracketed Newton on ``zeta`` with ``s(zeta)`` solved exactly inside. No autograd."""
    _, _, _, xi, m, *_ = unpack(p)
    base = tr.log_qtr - torch.log(3.0 * G)
    lo = torch.full_like(base, -ZETA_MAX)
    hi = torch.full_like(base, ZETA_MAX)
    zeta = zeta0.clamp(-ZETA_MAX + 1, ZETA_MAX - 1)
    s = s_n
    for _ in range(iters):
        L = base + _logsigmoid(-zeta)
        s, dH_ds, dH_dL = _solve_s(L, c, s_n, s, p)
        ly = torch.log(xi) + tr.log_qtr + _logsigmoid(zeta) - torch.log(s)
        R = L - c - _log_sinh_of_log(ly) / m
        done = (R.abs() < 1e-11) | (hi - lo < 1e-13)
        if bool(done.all()):
            break
        lo = torch.where(R > 0, zeta, lo)
        hi = torch.where(R < 0, zeta, hi)
        yc = _y_coth(ly)
        sg, sgm = torch.sigmoid(zeta), torch.sigmoid(-zeta)
        ds_dz = dH_dL * sg / dH_ds
        dR = -sg - yc * sgm / m + yc / (m * s) * ds_dz
        z_new = zeta - R / dR
        bad = ~((z_new > lo) & (z_new < hi)) | ~torch.isfinite(z_new)
        zeta = torch.where(done, zeta, torch.where(bad, 0.5 * (lo + hi), z_new))
    return zeta, s


def _partials_raw(base, lxq, zeta, s, s_n, p, c, m):
    """Flow and hardening residuals ``(R, H)``, the entries of their 2x2 Jacobian in
    ``(zeta, s)`` and the ingredients of the consistent tangent ``(yc, dH_ds, dH_dL)``.

    ``base = log(q_tr) - log(3G)`` and ``lxq = log(xi) + log(q_tr)`` are the constant parts of
    ``log(dep)`` and of ``log(xi*q/s)``; ``m`` the rate sensitivity.
    """
    t = torch.log1p(torch.exp(-zeta.abs()))  # shared by logsigmoid(zeta) and logsigmoid(-zeta)
    L = base + (torch.minimum(-zeta, torch.zeros_like(zeta)) - t)
    H, dH_ds, dH_dL, _ = hardening_residual(s, s_n, L, L - c, p)
    ly = lxq + (torch.minimum(zeta, torch.zeros_like(zeta)) - t) - torch.log(s)
    R = L - c - _log_sinh_of_log(ly) / m
    yc = _y_coth(ly)
    sg, sgm = torch.sigmoid(zeta), torch.sigmoid(-zeta)
    return R, H, (-sg - yc * sgm / m, yc / (m * s), -dH_dL * sg, dH_ds), yc, dH_ds, dH_dL


def _consts(log_qtr, p, G):
    """``(base, lxq, m)`` of :func:`_partials_raw`."""
    _, _, _, xi, m, *_ = unpack(p)
    return log_qtr - torch.log(3.0 * G), torch.log(xi) + log_qtr, m


def _partials(tr: _Trial, zeta, s, s_n, p, c, G):
    """Residuals ``(R, H)`` of (flow, hardening) and their 2x2 Jacobian in ``(zeta, s)``."""
    base, lxq, m = _consts(tr.log_qtr, p, G)
    R, H, (j00, j01, j10, j11), yc, dH_ds, dH_dL = _partials_raw(base, lxq, zeta, s, s_n, p,
                                                                 c, m)
    J = torch.stack([torch.stack([j00, j01], -1), torch.stack([j10, j11], -1)], -2)
    return R, H, J, yc, dH_ds, dH_dL


class TangentAux(NamedTuple):
    """What the consistent tangent needs from the converged local solve, each ``(...)``:
    ``yc = y coth(y)`` of the flow residual and the hardening residual's ``dH/ds`` (1) and
    ``dH/dlog(dep)`` (MPa) (see :func:`_partials_raw`)."""

    yc: torch.Tensor
    dH_ds: torch.Tensor
    dH_dL: torch.Tensor


#: Below this many points the joint Newton iterates on the full arrays; above it, it drops the
#: converged points from its working set (index gathers cost less than the elementwise work).
COMPACT_MIN = 4096


def _return_map_joint(tr: _Trial, s_n, p, c, G, zeta, s, iters=12):
    """Joint Newton on ``(zeta, s)`` from a warm start.

    Returns ``(zeta, s, done, aux)``: ``done`` masks the converged points and ``aux`` =
    ``(yc, dH_ds, dH_dL)`` at the returned point (valid where ``done``) for the tangent. A
    converged point is frozen; on large arrays the iteration continues on the unconverged points
    only, which gives the same values as iterating on all of them.
    """
    shape = zeta.shape
    base, lxq, m = _consts(tr.log_qtr, p, G)
    sn, cc = s_n, c
    pp = torch.broadcast_to(p, (*shape, p.shape[-1]))
    w = None  # flat indices of the working set once compacted, else None (all points)
    full: list[torch.Tensor] = []
    for it in range(iters + 1):
        R, H, (j00, j01, j10, j11), yc, dH_ds, dH_dL = _partials_raw(base, lxq, zeta, s, sn, pp,
                                                                     cc, m)
        done = (R.abs() < 1e-11) & (H.abs() <= 1e-13 * sn)
        if it == iters:
            done = done & torch.isfinite(zeta)
            break
        if bool(done.all()):
            break
        n_w = done.numel()
        if n_w >= COMPACT_MIN:
            n_done = int(done.sum())
            if 3 * n_done >= 2 * n_w:  # drop the converged points (>= 2/3) from the working set
                if w is None:
                    w = torch.arange(n_w, device=zeta.device)
                    full = [torch.empty(n_w, dtype=zeta.dtype, device=zeta.device)
                            for _ in range(5)]
                for buf, val in zip(full, (zeta, s, yc, dH_ds, dH_dL), strict=True):
                    buf[w] = val.reshape(-1)
                keep = ~done
                w = w[keep.reshape(-1)]
                base, lxq, m, sn, cc, zeta, s, R, H, j00, j01, j10, j11 = (
                    torch.broadcast_to(t, shape)[keep] if t.shape != keep.shape else t[keep]
                    for t in (base, lxq, m, sn, cc, zeta, s, R, H, j00, j01, j10, j11))
                pp = pp[keep]
                shape = zeta.shape
                done = torch.zeros_like(zeta, dtype=torch.bool)
        det = j00 * j11 - j01 * j10
        dz = -(j11 * R - j01 * H) / det
        ds = -(j00 * H - j10 * R) / det
        zeta = torch.where(done, zeta, zeta + dz.clamp(-10.0, 10.0))
        s = torch.where(done, s, (s + ds).clamp_min(1e-3 * sn))
    aux = TangentAux(yc, dH_ds, dH_dL)
    if w is not None:
        for buf, val in zip(full, (zeta, s, *aux), strict=True):
            buf[w] = val
        d = torch.ones(full[0].shape, dtype=torch.bool, device=done.device)
        d[w] = done
        zeta, s, done, yc, dH_ds, dH_dL = (t.reshape(s_n.shape)
                                           for t in (*full[:2], d, *full[2:]))
        aux = TangentAux(yc, dH_ds, dH_dL)
    return zeta, s, done, aux


@dataclass
class Tangent3D:
    """Consistent 3-D tangent in factored form (Mandel), leading shape ``(...)``:

        C = K m m^T + g2 (I - m m^T / 3) + coef nb nb^T,

    ``m = (1, 1, 1, 0)``, ``nb`` the unit trial deviator. :meth:`full` forms ``(..., 4, 4)``;
    :meth:`col_zz` and :meth:`row_zz` give ``C[..., :, ZZ]`` and ``C[..., ZZ, :]`` (the same
    floating-point values) without forming the rest, which is all plane stress needs per
    iteration.
    """

    K: torch.Tensor
    g2: torch.Tensor
    coef: torch.Tensor
    nb: torch.Tensor

    def _consts(self):
        m = torch.tensor([1.0, 1.0, 1.0, 0.0], dtype=self.nb.dtype, device=self.nb.device)
        mm = m[:, None] * m[None, :]
        return mm, torch.eye(4, dtype=m.dtype, device=m.device) - mm / 3.0

    def full(self) -> torch.Tensor:
        """The tangent ``C`` ``(..., 4, 4)``, MPa (Mandel)."""
        mm, dev = self._consts()
        return (self.K[..., None, None] * mm + self.g2[..., None, None] * dev
                + self.coef[..., None, None] * self.nb[..., :, None] * self.nb[..., None, :])

    def col_zz(self) -> torch.Tensor:
        """Its column ``C[..., :, ZZ]`` ``(..., 4)``, MPa."""
        mm, dev = self._consts()
        return (self.K[..., None] * mm[:, ZZ] + self.g2[..., None] * dev[:, ZZ]
                + self.coef[..., None] * self.nb * self.nb[..., ZZ, None])

    def row_zz(self) -> torch.Tensor:
        """Its row ``C[..., ZZ, :]`` ``(..., 4)``, MPa."""
        mm, dev = self._consts()
        return (self.K[..., None] * mm[ZZ] + self.g2[..., None] * dev[ZZ]
                + (self.coef * self.nb[..., ZZ])[..., None] * self.nb)

    def index(self, idx) -> Tangent3D:
        """The tangent at the points ``idx`` (any torch index of the leading dimensions)."""
        return Tangent3D(self.K[idx], self.g2[idx], self.coef[idx], self.nb[idx])


def _tangent3d(tr: _Trial, zeta, s, m, K, G, aux: TangentAux, C_k=None) -> Tangent3D:
    """Consistent 3-D tangent at the converged point ``(zeta, s)`` (``m`` the rate
    sensitivity, ``K``, ``G`` the bulk and shear moduli, MPa), from the tangent ingredients
    ``aux`` of :func:`_partials_raw` there; ``C_k`` ``(...)`` or None the kinematic modulus
    (see :mod:`.kinematic` for the two extra factors)."""
    yc, dH_ds, dH_dL = aux
    w = yc * torch.exp((-zeta).clamp(max=700.0)) / m
    Fs_dHdL = yc / (m * s) * dH_dL
    bracket = torch.sigmoid(-zeta) - w * dH_ds / ((1.0 + w) * dH_ds - Fs_dHdL)
    nb = tr.xi_tr / tr.nrm[..., None]
    if C_k is None:
        g2, coef = 2.0 * G * torch.sigmoid(zeta), 2.0 * G * bracket
    else:
        Gk = _return_modulus(G, C_k)
        g2 = 2.0 * G * (torch.sigmoid(zeta) + torch.sigmoid(-zeta) * (C_k / 3.0) / Gk)
        coef = 2.0 * G * (G / Gk) * bracket
    return Tangent3D(torch.broadcast_to(K, zeta.shape), g2, coef, nb)


def _return_modulus(G, C_k):
    """``Gk = G + C_k/3`` (so that ``3*Gk = 3G + C_k``), the shear modulus the return map sees;
    ``G`` itself when ``C_k`` is None. ``G + 0/3 == G`` exactly, hence C_k = 0 is bit-exact."""
    return G if C_k is None else G + C_k / 3.0


def _initial_zeta(tr: _Trial, s_n, p, c, G):
    """Predictor: flow at the trial stress, ``zeta`` = logit of the unrelaxed fraction."""
    _, _, _, xi, m, *_ = unpack(p)
    ly = torch.log(xi) + tr.log_qtr - torch.log(s_n)
    d = (c + _log_sinh_of_log(ly) / m - tr.log_qtr + torch.log(3.0 * G)).clamp(max=-1e-3)
    return -d + torch.log(-torch.expm1(d))


def _moduli(shape, tkw, inputs: PointInputs, p):
    """``(T, eps_th, K, G, p)`` broadcast to the points ``shape`` (K and G in MPa)."""
    T = torch.broadcast_to(torch.as_tensor(inputs.T, **tkw), shape)
    eps_th = torch.broadcast_to(torch.as_tensor(inputs.eps_th, **tkw), shape)
    E = torch.broadcast_to(torch.as_tensor(inputs.E, **tkw), shape)
    nu = torch.broadcast_to(torch.as_tensor(inputs.nu, **tkw), shape)
    p = torch.broadcast_to(p, (*shape, 9))
    return T, eps_th, E / (3.0 * (1.0 - 2.0 * nu)), E / (2.0 * (1.0 + nu)), p


def return_map_3d(eps, state: PointState, p, inputs: PointInputs, guess=None, tangent=True):
    """Backward-Euler Anand update for a given full 3-D strain (plane components + eps_zz).

    Args:
        eps: end-of-step total strain, Mandel ``(..., 4)`` = (xx, yy, zz, sqrt2*xy).
        state: start-of-step :class:`PointState` with leading shape ``(...)``.
        p: Anand constants ``(..., 9)`` (broadcastable), ANAND_NAMES order.
        inputs: the step's :class:`PointInputs` (temperature K, step s, free thermal strain,
            E MPa, nu, Prager modulus ``C_k`` MPa or None, Armstrong-Frederick recovery
            ``gamma_k`` or None), broadcastable to ``(...)`` (e.g. ``(b, 1, 1)`` per batch
            member in the FE). With ``C_k`` the back stress is ``state.X`` (None = zero); the
            new state carries ``X`` whenever ``C_k`` or ``state.X`` is given, and the step's
            equivalent inelastic strain rate ``p_rate = dep/dt`` whenever ``gamma_k`` or
            ``state.p_rate`` is given (:func:`lagged_prager`). See :mod:`.kinematic`.
        guess: optional ``(..., 2)`` warm start ``(zeta, s)`` from a nearby solve.
        tangent: whether to compute the 3-D consistent tangent; ``"factored"`` returns it as a
            :class:`Tangent3D` instead of a ``(..., 4, 4)`` tensor.
    Returns:
        ``(sigma (..., 4), new_state, C (..., 4, 4) or None, dep (...), x (..., 2))``; ``x`` is
        the detached solution ``(zeta, s)`` for warm starts. With autograd on, outputs carry
        exact first derivatives with respect to every input, ``C_k``, ``gamma_k``,
        ``state.X`` and ``state.p_rate`` included (one Newton step with the graph).
    """
    state, inputs, carry = lagged_prager(state, inputs)
    if (_native.usable(eps, state.eps_p, state.s, state.X, p, *inputs, guess)
            and torch.broadcast_shapes(eps.shape[:-1], state.s.shape) == eps.shape[:-1]):
        return _return_map_native(eps, state, p, inputs, guess, tangent, carry)
    shape = eps.shape[:-1]
    tkw = dict(dtype=eps.dtype, device=eps.device)
    T, eps_th, K, G, p = _moduli(shape, tkw, inputs, p)
    Ck = _kinematic_modulus(inputs.C_k, shape, tkw)
    Gk, Xn = _return_modulus(G, Ck), state.X
    _, QR, A, *_ = unpack(p)
    c = torch.log(inputs.dt * A) - QR / T
    with torch.no_grad():
        a = [t.detach() for t in (eps, state.eps_p, state.s, p, c, eps_th, K, G, Gk)]
        xd = None if Xn is None else Xn.detach()
        tr = _Trial(a[0], a[1], a[5], a[6], a[7], xd)
        if guess is None:
            zeta, s = _initial_zeta(tr, a[2], a[3], a[4], a[8]), a[2]
        else:
            zeta, s = guess[..., 0], guess[..., 1]
        zeta, s, done, aux = _return_map_joint(tr, a[2], a[3], a[4], a[8], zeta, s)
        if not bool(done.all()):  # robust nested, bracketed solve where the joint one failed
            i = ~done
            sub = _Trial(a[0][i], a[1][i], a[5][i], a[6][i], a[7][i], None if xd is None
                         else torch.broadcast_to(xd, a[1].shape)[i])
            z0 = _initial_zeta(sub, a[2][i], a[3][i], a[4][i], a[8][i])
            zi, si = _return_map(sub, a[2][i], a[3][i], a[4][i], a[8][i], z0)
            zeta, s = zeta.clone(), s.clone()
            zeta[i], s[i] = zi, si
            aux = None
        x = torch.stack([zeta, s], -1)
        C: torch.Tensor | Tangent3D | None = None
        if tangent:
            if aux is None:
                aux = TangentAux(*_partials(tr, zeta, s, a[2], a[3], a[4], a[8])[3:])
            Cf = _tangent3d(tr, zeta, s, a[3][..., 4], a[6], a[7], aux,
                            C_k=None if Ck is None else Ck.detach())
            C = Cf if tangent == "factored" else Cf.full()
    needs_grad = torch.is_grad_enabled() and any(
        t is not None and t.requires_grad
        for t in (eps, state.eps_p, state.s, p, c, eps_th, K, G, Gk, Xn))
    if needs_grad:
        tr = _Trial(eps, state.eps_p, eps_th, K, G, Xn)
        R, H, J, *_ = _partials(tr, x[..., 0], x[..., 1], state.s, p, c, Gk)
        zeta, s = (x - torch.linalg.solve(J.detach(), torch.stack([R, H], -1))).unbind(-1)
    sg = torch.sigmoid(zeta)
    deps_p = (torch.sigmoid(-zeta) / (2.0 * Gk))[..., None] * tr.xi_tr  # (..., 4)
    X = _back_stress(Xn, Ck, deps_p)
    sigma = tr.p[..., None] * tr.m + sg[..., None] * tr.xi_tr  # + X below: dev(sigma) = xi + X
    if X is not None:
        sigma = sigma + X
    dep = torch.exp(tr.log_qtr - torch.log(3.0 * Gk) + _logsigmoid(-zeta))
    return sigma, PointState(state.eps_p + deps_p, s, eps[..., ZZ], X,
                             dep / inputs.dt if carry else None), C, dep, x


def lagged_prager(state: PointState,
                  inputs: PointInputs) -> tuple[PointState, PointInputs, bool]:
    """The Prager step that a step with Armstrong-Frederick recovery is (:mod:`.kinematic`).

    With the recovery factor ``a = 1/(1 + gamma_k*p_rate*dt)`` ``(...)`` of the start-of-step
    lagged rate ``state.p_rate`` (1/s) and the step ``inputs.dt`` (s), the backward-Euler
    Armstrong-Frederick update is the Prager update of ``X_n -> a X_n`` (MPa, ``(..., 4)``) and
    ``C_k -> a C_k`` (MPa).

    Args:
        state: start-of-step :class:`PointState` (``X``, ``p_rate`` optional).
        inputs: the step's :class:`PointInputs` (``C_k``, ``gamma_k`` optional).
    Returns:
        ``(state', inputs', carry)``: the Prager step's start state and inputs (``gamma_k``
        None), and whether the new state is to carry ``p_rate`` (``gamma_k`` given, or
        ``state.p_rate`` given). Without recovery to apply (``gamma_k`` or ``C_k`` None or a
        plain 0, or ``p_rate`` None: the virgin state) ``X`` and ``C_k`` are passed on
        untouched; a zero tensor ``gamma_k`` gives ``a = 1`` exactly, so the Prager numbers to
        the last bit either way.
    """
    g, Ck = inputs.gamma_k, inputs.C_k
    given = g is not None and (isinstance(g, torch.Tensor) or g != 0)
    carry = given or state.p_rate is not None
    inputs = inputs._replace(gamma_k=None)
    if (not given or state.p_rate is None or Ck is None
            or (not isinstance(Ck, torch.Tensor) and Ck == 0)):
        return state, inputs, carry
    a = 1.0 / (1.0 + g * state.p_rate * inputs.dt)
    X = None if state.X is None else a[..., None] * state.X
    return dataclasses.replace(state, X=X), inputs._replace(C_k=a * Ck), carry


def _return_map_native(eps, state: PointState, p, inputs: PointInputs, guess, tangent, carry):
    """:func:`return_map_3d` without autograd through the fused C kernel
    (:func:`solderpyro._native.anand_update`): the same algorithm point by point, the same
    outputs to rounding. ``state`` and ``inputs`` are those of :func:`lagged_prager`
    (``carry``: the new state carries ``p_rate = dep/dt``)."""
    C_k = inputs.C_k
    if C_k is not None and not isinstance(C_k, torch.Tensor) and C_k == 0:
        inputs = inputs._replace(C_k=None)  # as _kinematic_modulus: a plain 0 is none
    sigma, eps_p, s, X, dep, x, tan = _native.anand_update(eps, state, p, inputs, guess,
                                                           bool(tangent))
    C: torch.Tensor | Tangent3D | None = None
    if tan is not None:
        C = Tangent3D(*tan)
        if tangent != "factored":
            C = C.full()
    st1 = PointState(eps_p, s, eps[..., ZZ], X, dep / inputs.dt if carry else None)
    return sigma, st1, C, dep, x


def _kinematic_modulus(C_k, shape, tkw):
    """``C_k`` as a ``shape`` tensor, or None when absent (None or a plain number 0)."""
    if C_k is None or (not isinstance(C_k, torch.Tensor) and C_k == 0):
        return None
    return torch.broadcast_to(torch.as_tensor(C_k, **tkw), shape)


def _back_stress(X_n, C_k, deps_p):
    """Prager update ``X = X_n + (2/3) C_k deps_p`` (Mandel ``(..., 4)``), None-aware."""
    if C_k is None:
        return X_n
    dX = (2.0 / 3.0) * C_k[..., None] * deps_p
    return dX if X_n is None else X_n + dX


def full_strain(eps_ip: torch.Tensor, ezz: torch.Tensor) -> torch.Tensor:
    """The 3D Mandel strain ``(..., 4)`` ``[xx, yy, zz, sqrt2 xy]`` (dimensionless) from the
    in-plane Mandel strain ``eps_ip (..., 3)`` ``[xx, yy, sqrt2 xy]`` and the out-of-plane
    strain ``ezz (...)``."""
    return torch.stack([eps_ip[..., 0], eps_ip[..., 1], ezz, eps_ip[..., 2]], -1)


def ezz_predictor(eps_ip, state: PointState, eps_th, E, nu):
    """Out-of-plane strain that keeps sigma_zz = 0 if no new inelastic flow occurs, ``(...)``.

    Valid with kinematic hardening too: without new flow ``sigma = C_el (eps - eps_p - eps_th)``
    and the back stress does not enter the stress.
    """
    ep = state.eps_p  # two adds, not sum(-1): a reduction over a strided pair is slow on CPU
    ee = (eps_ip[..., 0] + eps_ip[..., 1]) - (ep[..., 0] + ep[..., 1]) - 2 * eps_th
    return state.eps_p[..., ZZ] + eps_th - nu / (1.0 - nu) * ee


def anand_update(eps_ip, state: PointState, p, inputs: PointInputs, plane="stress",
                 tangent=True, guess=None, iters=30):
    """Anand update for an in-plane strain, plane stress (local eps_zz iteration) or strain.

    Args:
        eps_ip: end-of-step in-plane total strain, Mandel ``(..., 3)`` = (xx, yy, sqrt2*xy).
        state, p, inputs, guess: as in :func:`return_map_3d`.
        plane: ``"stress"`` (sigma_zz = 0, eps_zz iterated by Newton) or ``"strain"``.
        iters: at most this many Newton iterations on eps_zz (plane stress).
    Returns:
        ``(sigma (..., 4), new_state, C_ip (..., 3, 3) or None, dep, x)`` with the in-plane
        consistent tangent (plane-stress condensed). Differentiable like :func:`return_map_3d`.
    """
    if plane == "strain":
        out = return_map_3d(full_strain(eps_ip, torch.zeros_like(eps_ip[..., 0])), state, p,
                            inputs, guess, tangent)
        C = condense_zz(out[2], plane) if tangent else None
        return out[0], out[1], C, out[3], out[4]
    if plane != "stress":
        raise ValueError(f"plane must be 'stress' or 'strain', got {plane!r}")
    with torch.no_grad():
        ezz = ezz_predictor(eps_ip.detach(), state.detach(), torch.as_tensor(inputs.eps_th),
                            inputs.E, inputs.nu)
        fixed = inputs._replace(**{k: v.detach() for k, v in (("C_k", inputs.C_k),
                                                              ("gamma_k", inputs.gamma_k))
                                   if isinstance(v, torch.Tensor)})
        for _ in range(iters):
            sig, _, C, _, guess = return_map_3d(full_strain(eps_ip.detach(), ezz),
                                                state.detach(), p.detach(), fixed, guess)
            if bool((sig[..., ZZ].abs() <= 1e-12 * (1.0 + sig.abs().amax(-1))).all()):
                break
            ezz = ezz - sig[..., ZZ] / C[..., ZZ, ZZ]
    if torch.is_grad_enabled():  # one Newton step on eps_zz with the graph attached
        assert C is not None
        sig, *_ = return_map_3d(full_strain(eps_ip, ezz), state, p, inputs, guess,
                                tangent=False)
        ezz = ezz - sig[..., ZZ] / C[..., ZZ, ZZ]
    sig, st, C, dep, x = return_map_3d(full_strain(eps_ip, ezz), state, p, inputs, guess,
                                       tangent)
    return sig, st, condense_zz(C, plane) if tangent else None, dep, x
