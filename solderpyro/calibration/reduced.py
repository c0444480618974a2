"""The modular KOH likelihood of a PCA surrogate, reduced to the K basis directions.

For a PCA surrogate (:class:`~solderpyro.surrogate.GPSurrogate` with ``output="pca"``) the
observations ``y (n,)`` are, at a calibration point ``t``,

    y ~ N(mu0 + off(q) + B c(t), B V(t) B^T + D + sigma^2 I),

with ``B = diag(scale) Phi (n, K)`` the scaled basis, ``c(t), V(t) = diag(v(t))`` the K
component GPs' predictive means and variances, ``D = diag(d)`` the truncated components'
variance per output, ``off(q)`` additive observation-side effects (a Moire rigid motion) and
``sigma`` the noise. With ``D_s = D + sigma^2 I`` (diagonal; it depends on sigma alone),
``A = B^T D_s^-1 B (K, K)``, ``e = B^T D_s^-1 r (K,)`` for the residual ``r = y - mu0 - off -
B c`` and ``P = V^1/2 (I + V^1/2 A V^1/2)^-1 V^1/2``, the Woodbury identity gives

    log|C| = log|D_s| + log|I + V^1/2 A V^1/2|,    r^T C^-1 r = r^T D_s^-1 r - e^T P e.

This is the Higdon et al. (2008) / SEPIA reduction: the data enter through their projections
``b = B^T D_s^-1 (y - mu0)`` and the orthogonal remainder ``(y - mu0)^T D_s^-1 (y - mu0)``, which
do not depend on t; everything that does is K-dimensional. Per log-density evaluation the cost
is one weighted Gram matrix ``A`` (O(n K^2), sigma changes at every step) and O(K^3 + K n_sim^2)
for the GPs, instead of Pyro's ``LowRankMultivariateNormal`` over all n values and its autograd
tape. The gradient is analytic (``dll/dc = B^T C^-1 r``, ``dll/dv_j = 1/2 ((B^T C^-1 r)_j^2 -
(B^T C^-1 B)_jj)``, ``dll/dsigma = sigma (|C^-1 r|^2 - tr C^-1)``), chained through the GPs'
kernels and the input map in NumPy (:class:`GPInputMap`).

:func:`reduced_loglik_torch` is the same reduced likelihood in torch, for the check against
the full density (``tests/unit/calibration/test_reduced.py``: equal to 1e-8 relative).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from scipy.linalg.lapack import dtrtrs as _dtrtrs

from solderpyro.params import Box
from solderpyro.surrogate import GPSurrogate

_LOG_2PI = math.log(2.0 * math.pi)


class GPInputMap:
    """The map from the sampler's ``t_unit (p,)`` to a GP's inputs ``u (d',)``, with its
    Jacobian, in NumPy.

    ``t_unit`` (the calibration box's unit cube) -> physical ``x = box.from_unit(t_unit)`` ->
    the GP's inputs: ``gp.box.to_unit(x)``, or the GP's input map (``FlowStressInputs``)
    rescaled by its range. Only the first ``gp.box.dim`` coordinates of ``t`` enter.

    Args:
        gp: the fitted surrogate; theta_box: the calibration box (its first ``gp.box.dim``
            names must be the GP's inputs, in order).
    Raises:
        ValueError naming the mismatch.
    """

    def __init__(self, gp: GPSurrogate, theta_box: Box) -> None:
        n = gp.box.dim
        if tuple(theta_box.names[:n]) != tuple(gp.box.names):
            raise ValueError(f"the calibration box's first names {theta_box.names[:n]} are not "
                             f"the surrogate's inputs {gp.box.names}")
        self.n = n
        self.lo_t, self.w_t, self.log_t = _unit_map(theta_box, n)
        self.lo_g, self.w_g, self.log_g = _unit_map(gp.box, n)
        self.feats: Any = gp.inputs
        if self.feats is not None:
            if not hasattr(self.feats, "value_and_jacobian"):
                raise NotImplementedError(f"the GP input map {type(self.feats).__name__} has no "
                                          "value_and_jacobian")
            scaling = gp.input_scaling
            assert scaling is not None  # the surrogate has an input map
            self.in_lo = scaling[0].detach().cpu().numpy().astype(float)
            self.in_span = scaling[1].detach().cpu().numpy().astype(float)

    def __call__(self, t_unit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``t_unit (p,)`` -> GP inputs ``u (d',)`` and ``du/dt_unit (d', n)``."""
        z = self.lo_t + t_unit[:self.n] * self.w_t
        x = np.where(self.log_t, np.exp(np.where(self.log_t, z, 0.0)), z)
        dx = np.where(self.log_t, x, 1.0) * self.w_t  # dx/dt_unit (n,)
        if self.feats is None:
            zg = np.where(self.log_g, np.log(np.where(self.log_g, x, 1.0)), x)
            u = (zg - self.lo_g) / self.w_g
            return u, np.diag(np.where(self.log_g, 1.0 / x, 1.0) / self.w_g * dx)
        f, jf = self.feats.value_and_jacobian(x)  # (d',), (d', n)
        return (f - self.in_lo) / self.in_span, jf * dx[None, :] / self.in_span[:, None]


def _unit_map(box: Box, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(lo, width, log)`` of a box's first ``n`` coordinates on its (log where flagged)
    scale: ``z = lo + u * width``."""
    b = box.to_working(torch.tensor([box.lower, box.upper], dtype=torch.float64)).numpy()[:, :n]
    return b[0], b[1] - b[0], np.asarray(box.log_scale[:n], dtype=bool)


class ComponentGPs:
    """The K component GPs of a fitted PCA surrogate in NumPy: predictive means ``c (K,)`` and
    variances ``v (K,)`` at one input, and the vector-Jacobian product back to the input.

    Args:
        gp: a fitted :class:`~solderpyro.surrogate.GPSurrogate` (any output layout; the
            components share their training inputs).
    """

    def __init__(self, gp: GPSurrogate) -> None:
        fac = gp.factors()
        self.kernel = gp.kernel
        self.U = fac.u[0].detach().cpu().numpy().astype(float)  # (n_sim, d')
        self.os = fac.outputscale.detach().cpu().numpy().astype(float)  # (K,)
        ls = fac.lengthscale.detach().cpu().numpy().astype(float)  # (K, d'|1)
        self.inv_ls2 = np.broadcast_to(1.0 / ls**2, (ls.shape[0], self.U.shape[1])).copy()
        self.c0 = fac.mean_const.detach().cpu().numpy().astype(float)  # (K,)
        self.w = (None if fac.mean_weights is None
                  else fac.mean_weights.detach().cpu().numpy().astype(float))  # (K, d')
        self.alpha = fac.alpha.detach().cpu().numpy().astype(float)  # (K, n_sim)
        chol = fac.chol.detach().cpu().numpy().astype(float)  # (K, n_sim, n_sim)
        self.linv = np.stack([_trsv(c, np.eye(c.shape[0]), False) for c in chol])  # L^-1
        self.linv_t = np.ascontiguousarray(self.linv.transpose(0, 2, 1))

    def __call__(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, Any]:
        """``u (d',)`` -> means ``c (K,)``, variances ``v (K,)`` and a closure
        ``(gc (K,), gv (K,)) -> d/du (d',)`` of ``sum(gc c + gv v)``."""
        diff = u[None, :] - self.U  # (n_sim, d')
        r2 = (diff * diff) @ self.inv_ls2.T  # (n_sim, K)
        if self.kernel == "gaussian":
            rho = np.exp(-0.5 * r2)
            drho = -rho  # d rho / d(diff_l) = drho * diff_l / ls_l^2
        else:  # Matern 5/2 (solderpyro.surrogate.kernels.matern52)
            s5r = math.sqrt(5.0) * np.sqrt(np.maximum(r2, 1e-30))
            ex = np.exp(-s5r)
            rho = (1.0 + s5r + s5r * s5r / 3.0) * ex
            drho = -(5.0 / 3.0) * (1.0 + s5r) * ex
        kap = (rho * self.os).T  # (K, n_sim)
        c = self.c0 + (kap * self.alpha).sum(1)
        if self.w is not None:
            c = c + self.w @ u
        # v = os - |L^-1 kappa|^2 (through L^-1, not K^-1: half the condition number)
        half = (self.linv @ kap[:, :, None])[:, :, 0]  # L^-1 kappa (K, n_sim)
        beta = (self.linv_t @ half[:, :, None])[:, :, 0]  # K^-1 kappa
        v_raw = self.os - (half * half).sum(1)
        v = np.maximum(v_raw, 0.0)
        pos = v_raw > 0.0

        def vjp(gc: np.ndarray, gv: np.ndarray) -> np.ndarray:
            coef = gc[:, None] * self.alpha - 2.0 * np.where(pos, gv, 0.0)[:, None] * beta
            a = (coef * self.os[:, None]).T * drho  # (n_sim, K): d sum / d rho_k(i)
            g = ((a @ self.inv_ls2) * diff).sum(0)
            if self.w is not None:
                g = g + gc @ self.w
            return g

        return c, v, vjp


def _trsv(chol: np.ndarray, b: np.ndarray, trans: bool) -> np.ndarray:
    """``L^-1 b`` (or ``L^-T b`` with ``trans``) for a lower-triangular ``L``."""
    x, _ = _dtrtrs(chol, b, lower=1, trans=1 if trans else 0)
    return x


class PCAReduction:
    """The reduced likelihood's data side: the scaled basis, the centred data and the
    truncated components' variance, computed once; :meth:`sigma_terms` is the sigma-dependent
    part, :meth:`loglik` the whole (NumPy, analytic gradient).

    Args:
        gp: a fitted PCA surrogate of the observations; y_obs: ``(n,)`` um.
    """

    def __init__(self, gp: GPSurrogate, y_obs: torch.Tensor) -> None:
        if gp.output != "pca":
            raise ValueError(f"PCAReduction needs a PCA surrogate, got output={gp.output!r}")
        sc = gp.std.scale.detach().cpu().numpy().astype(float)
        self.B = (gp.basis.detach().cpu().numpy().astype(float) * sc[:, None])  # (n, K)
        self.mu0 = gp.std.mean.detach().cpu().numpy().astype(float)  # (n,)
        self.d = (gp.resid_var.detach().cpu().numpy().astype(float) * sc**2)  # (n,)
        self.y = y_obs.detach().cpu().numpy().astype(float)
        if self.y.shape != self.mu0.shape:
            raise ValueError(f"y_obs has shape {self.y.shape}, the surrogate predicts "
                             f"{self.mu0.shape}")
        self.n, self.K = self.B.shape
        # every sigma-dependent sum over the n outputs in one product: Q^T [w, w^2] with
        # Q = [b_i b_i^T (upper triangle), b_i y0_i, y0_i^2] (n, K(K+1)/2 + K + 1)
        self._iu = np.triu_indices(self.K)
        y0 = self.y - self.mu0
        outer = (self.B[:, :, None] * self.B[:, None, :])[:, self._iu[0], self._iu[1]]
        self._Qt = np.ascontiguousarray(np.concatenate(
            [outer, self.B * y0[:, None], (y0 * y0)[:, None]], 1).T)  # (m + K + 1, n)
        self._moments = _WeightMoments(self.d, self._Qt)

    def _sym(self, flat: np.ndarray) -> np.ndarray:
        out = np.empty((self.K, self.K))
        out[self._iu] = flat
        out.T[self._iu] = flat
        return out

    def loglik(self, c: np.ndarray, v: np.ndarray, sigma: float, off: np.ndarray | None
               ) -> tuple[float, np.ndarray, np.ndarray, float, np.ndarray | None]:
        """Log density of ``y`` and its gradients.

        Args:
            c, v: ``(K,)`` component means and variances (standardized PC units); sigma: um;
            off: ``(n,)`` additive observation offsets (um) or None.
        Returns:
            ll, ``d ll/dc (K,)``, ``d ll/dv (K,)``, ``d ll/dsigma``, ``d ll/doff (n,)`` (None
            when ``off`` is None).
        """
        if off is None:
            return self._loglik_projected(c, v, sigma)
        w = 1.0 / (self.d + sigma * sigma)  # D_s^-1 (n,)
        y0 = self.y - self.mu0 if off is None else self.y - self.mu0 - off
        Bw = self.B * w[:, None]  # (n, K)
        A = self.B.T @ Bw  # (K, K)
        r = y0 - self.B @ c  # (n,)
        e = Bw.T @ r  # (K,)
        logdet_m, P, Pe, gc, gv = _k_terms(A, e, v)
        quad = float(r @ (w * r)) - float(e @ Pe)
        ll = -0.5 * (self.n * _LOG_2PI - float(np.log(w).sum()) + logdet_m + quad)
        z = w * (r - self.B @ Pe)  # C^-1 r (n,)
        # tr C^-1 = sum w - tr(P B^T D_s^-2 B)
        A2 = Bw.T @ Bw
        tr = float(w.sum()) - float(np.vdot(P, A2))
        gs = sigma * (float(z @ z) - tr)
        return ll, gc, gv, gs, (z if off is not None else None)

    def _loglik_projected(self, c: np.ndarray, v: np.ndarray, sigma: float
                          ) -> tuple[float, np.ndarray, np.ndarray, float, None]:
        """:meth:`loglik` without offsets, from the projections: O(n K^2) in one product."""
        K, m = self.K, len(self._iu[0])
        sums = self._moments(sigma * sigma)
        if sums is None:  # sigma^2 too small against the spread of d: the sums over n
            w = 1.0 / (self.d + sigma * sigma)
            S1, S2 = self._Qt @ w, self._Qt @ (w * w)  # (one GEMM with two columns is 2.5x
            sum_w, sum_log_w = float(w.sum()), float(np.log(w).sum())  # slower)
        else:
            S1, S2, sum_w, sum_log_w = sums
        A, A2 = self._sym(S1[:m]), self._sym(S2[:m])
        bw, bw2 = S1[m:m + K], S2[m:m + K]  # B^T D^-1 y0, B^T D^-2 y0
        yw, yw2 = S1[-1], S2[-1]  # y0^T D^-1 y0, y0^T D^-2 y0
        Ac = A @ c
        e = bw - Ac  # B^T D^-1 r
        logdet_m, P, Pe, g, gv = _k_terms(A, e, v)
        rwr = yw - 2.0 * float(c @ bw) + float(c @ Ac)
        quad = rwr - float(e @ Pe)
        ll = -0.5 * (self.n * _LOG_2PI - sum_log_w + logdet_m + quad)
        h = c + Pe  # C^-1 r = D^-1 (y0 - B h)
        zz = yw2 - 2.0 * float(h @ bw2) + float(h @ A2 @ h)
        tr = sum_w - float(np.vdot(P, A2))
        return ll, g, gv, sigma * (zz - tr), None


def native_loglik(gps: ComponentGPs, red: PCAReduction) -> Any:
    """The fused native version of ``red.loglik(*gps(u)[:2], sigma, None)`` with the
    gradient chained back to ``u`` (:class:`solderpyro._native.ReducedLoglik`: ``(u (d',),
    sigma) -> (ll, d ll/du (d',), d ll/dsigma, c (K,), v (K,))``), or None where the native
    kernels are switched off or unavailable (then the NumPy path serves).

    Why: per gradient of the loop's final posterior (K 20, 91 runs, n 2,240) the NumPy component
    GPs, their vector-Jacobian product and the reduced likelihood took 128 of 239 us, almost all of
    it call overhead on arrays of 20-91 values (BENCHMARKS.md, "Per-gradient and per-round costs of
    the calibration"); the native call takes ~15 us.
    """
    from solderpyro import _native

    if _native.library() is None:
        return None
    mo = red._moments
    arrays = _native.GPArrays(gps.U, gps.os, gps.inv_ls2, gps.c0, gps.w, gps.alpha, gps.linv,
                              gps.kernel != "gaussian")
    series = _native.MomentSeries(mo.Mq, mo.mt, mo.mid, mo.half, mo.TOL)
    return _native.ReducedLoglik(arrays, series, red.d, red._Qt)


class _WeightMoments:
    """The sums ``Q^T w``, ``Q^T w^2``, ``sum w`` and ``sum log w`` over the n outputs, with
    ``w_i = 1 / (d_i + s)``, from moments of ``d`` computed once.

    With ``a = (min d + max d) / 2 + s``, ``h = (max d - min d) / 2``, ``t_i = (d_i - (min d +
    max d) / 2) / h`` in [-1, 1] and ``r = h / a < 1``,

        w_i = sum_k (-r t_i)^k / a,    w_i^2 = sum_k (k + 1) (-r t_i)^k / a^2,
        log w_i = -log a - sum_{k>=1} (-1)^(k+1) (r t_i)^k / k,

    so every sum is a short series in the moments ``Q^T t^k`` (a ``(rows, L + 1)`` matrix, one
    GEMM at construction). The series is cut where its tail bound ``(L + 2) r^(L+1) / (1 -
    r)^2`` falls below :data:`TOL` (relative to the terms' sizes); where that needs more than
    :data:`MAX_ORDER` terms (``s`` small against the spread of ``d``), :meth:`__call__` returns
    None and the caller sums over the n outputs.

    Why: the two ``(rows, n)`` products were a third of a gradient of the loop's final
    posterior (118 of 300 us; n 2,240, K 20, 231 rows); ``d`` (the truncated components'
    variance) spans ~2e-5 um^2 against sigma^2 ~2.4e-3, so r ~ 0.005 and six terms reach 1e-14.
    """

    TOL = 1e-15
    MAX_ORDER = 40

    def __init__(self, d: np.ndarray, Qt: np.ndarray) -> None:
        lo, hi = float(d.min()), float(d.max())
        self.mid, self.half, self.n = 0.5 * (lo + hi), 0.5 * (hi - lo), len(d)
        t = (d - self.mid) / self.half if self.half > 0 else np.zeros_like(d)
        P = t[:, None] ** np.arange(self.MAX_ORDER + 1)[None, :]  # (n, L + 1); t^0 = 1
        self.Mq = Qt @ P  # (rows, L + 1)
        self.mt = P.sum(0)  # (L + 1,)
        k = np.arange(self.MAX_ORDER + 1)
        self._sign = (-1.0) ** k
        self._k1 = k + 1.0
        self._inv_k = np.concatenate([[0.0], 1.0 / k[1:]])

    def order(self, r: float) -> int | None:
        """The number of terms after the first, L, for the ratio ``r``; None beyond the cap."""
        if r <= 0.0:
            return 0
        if r >= 0.5:
            return None
        for L in range(self.MAX_ORDER + 1):
            if (L + 2) * r ** (L + 1) / (1.0 - r) ** 2 <= self.TOL:
                return L
        return None

    def __call__(self, s: float) -> tuple[np.ndarray, np.ndarray, float, float] | None:
        """``(Q^T w (rows,), Q^T w^2 (rows,), sum w, sum log w)`` at ``s = sigma^2``, or None
        (see the class docstring)."""
        a = self.mid + s
        if not a > 0.0:
            return None
        r = self.half / a
        L = self.order(r)
        if L is None:
            return None
        pw = self._sign[:L + 1] * r ** np.arange(L + 1)  # (-r)^k
        c1 = pw / a
        c2 = self._k1[:L + 1] * pw / (a * a)
        M = self.Mq[:, :L + 1]
        mt = self.mt[:L + 1]
        log_sum = -self.n * math.log(a) + float((pw * self._inv_k[:L + 1]) @ mt)
        return M @ c1, M @ c2, float(c1 @ mt), log_sum


def _k_terms(A: np.ndarray, e: np.ndarray, v: np.ndarray
             ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The K-dimensional part shared by both paths of :meth:`PCAReduction.loglik`.

    Args:
        A: ``B^T D_s^-1 B (K, K)``; e: ``B^T D_s^-1 r (K,)``; v: component variances ``(K,)``.
    Returns:
        ``log|I + V^1/2 A V^1/2|``, ``P (K, K)``, ``P e``, ``d ll/dc = B^T C^-1 r`` and
        ``d ll/dv`` (both ``(K,)``).
    """
    sv = np.sqrt(v)
    M = np.eye(A.shape[0]) + sv[:, None] * A * sv[None, :]
    Lm = np.linalg.cholesky(M)
    P = sv[:, None] * np.linalg.inv(M) * sv[None, :]
    Pe = P @ e
    g = e - A @ Pe  # B^T C^-1 r
    gv = 0.5 * (g * g - (A.diagonal() - np.einsum("ij,ji->i", A @ P, A)))
    return 2.0 * float(np.log(Lm.diagonal()).sum()), P, Pe, g, gv


def reduced_loglik_torch(gp: GPSurrogate, y_obs: torch.Tensor, t: torch.Tensor,
                         sigma: torch.Tensor) -> torch.Tensor:
    """The reduced log density in torch (differentiable), for checks against the full one.

    Args:
        gp: fitted PCA surrogate; y_obs: ``(n,)``; t: ``(d,)`` physical input; sigma: scalar.
    Returns:
        scalar: ``log N(y_obs; mean, F F^T + diag(d + sigma^2))`` of ``gp.mean_lowrank(t)``.
    """
    mc, vc = gp.coefficients(t.reshape(1, -1), full_cov=False)  # (K, 1), (K, 1)
    c, v = mc[:, 0], vc[:, 0].clamp_min(0.0)
    B = gp.basis * gp.std.scale[:, None]
    w = 1.0 / (gp.resid_var * gp.std.scale.square() + sigma.square())
    r = y_obs - gp.std.mean - B @ c
    Bw = B * w[:, None]
    A = B.T @ Bw
    e = Bw.T @ r
    sv = v.sqrt()
    M = torch.eye(B.shape[1], dtype=B.dtype) + sv[:, None] * A * sv[None, :]
    Lm = torch.linalg.cholesky(M)
    Pe = sv * torch.cholesky_solve((sv * e)[:, None], Lm)[:, 0]
    quad = (r * w * r).sum() - (e * Pe).sum()
    logdet = -w.log().sum() + 2.0 * Lm.diagonal().log().sum()
    return -0.5 * (r.shape[0] * _LOG_2PI + logdet + quad)


def pca_flat(inp: Any, priors: Any = None, coords: str = "auto") -> Any:
    """:func:`~.koh.observation_model` with a PCA surrogate (a :class:`GPEmulator` of the
    observations, possibly inside an :class:`ObservedEmulator`) as a
    :class:`~.flat.FlatModel` on the reduced likelihood, with an analytic gradient.

    Flat vector: ``t_unit (p,)`` then ``sigma``; the same priors as the Pyro model. The transforms:
    with ``coords="auto"`` and a surrogate on flow-stress inputs whose box holds s0, QR, xi, m (A,
    s_hat, n fixed), those four are sampled in the soft-walled flow-stress coordinates of
    :class:`~.flowcoords.SoftFlowCoords` (the same posterior, a far rounder density; BENCHMARKS.md,
    "Per-gradient and per-round costs of the calibration"); every other coordinate, and all of them
    with ``coords="logit"``, on Pyro's transforms (the logit of the unit interval). Observation
    offsets (``ObservedEmulator``) enter through one torch backward pass through the offset function
    per gradient.

    Raises:
        NotImplementedError: another emulator, a discrepancy or custom priors (the generic
            path, :func:`~.potential.torch_flat`, covers those).
    """
    from solderpyro.calibration.emulators import GPEmulator, ObservedEmulator
    from solderpyro.calibration.flat import FlatModel, FlatSite, reject_unsupported, sigma_site
    from solderpyro.calibration.koh import SITE_T, Priors

    pr = priors or Priors()
    em = inp.emulator
    base = em.base if isinstance(em, ObservedEmulator) else em
    ok = (isinstance(base, GPEmulator) and base.x_obs is None and base.gp.output == "pca"
          and (not isinstance(em, ObservedEmulator) or isinstance(em.base, GPEmulator)))
    if coords not in ("auto", "logit"):
        raise ValueError(f"pca_flat coords must be 'auto' or 'logit', got {coords!r}")
    reject_unsupported(pr, {"emulators other than a PCA GPEmulator": not ok,
                      "discrepancy=True": inp.discrepancy})
    gp = base.gp
    red = PCAReduction(gp, inp.y_obs)
    gps = ComponentGPs(gp)
    umap = GPInputMap(gp, inp.theta_box)
    p = inp.theta_box.dim
    n_fe = gp.box.dim
    sig, mu, sd = sigma_site(pr, red.y, p)
    sites = [FlatSite(SITE_T, p, True, 0.0, 1.0, 0), sig]
    offset = em.offset if isinstance(em, ObservedEmulator) else None
    n_q = p - n_fe
    if offset is None and n_q:
        raise ValueError(f"the calibration box has {p} parameters, the surrogate {n_fe}")
    if offset is not None:
        obox = Box(tuple(inp.theta_box.names[n_fe:]), tuple(inp.theta_box.lower[n_fe:]),
                   tuple(inp.theta_box.upper[n_fe:]), tuple(inp.theta_box.log_scale[n_fe:]))

    fused = native_loglik(gps, red) if offset is None else None

    def loglik(x: np.ndarray) -> tuple[float, np.ndarray]:
        s = float(x[p])
        if not s * s > 0.0:  # sigma (or its square) underflowed to 0: zero density
            return -math.inf, np.zeros(p + 1)
        u, du = umap(x[:p])
        if fused is not None:
            try:
                ll, gu, gs, _, _ = fused(u, s)
            except FloatingPointError:  # non-finite inputs (the NumPy path gives NaN): the
                return -math.inf, np.zeros(p + 1)  # sampler counts a divergence either way
            g = np.zeros(p + 1)
            g[:n_fe] = gu @ du
            g[p] = gs
            return ll, g
        c, v, vjp = gps(u)
        off_np = None
        if offset is not None:
            with torch.enable_grad():
                qu = torch.tensor(x[n_fe:p], dtype=inp.y_obs.dtype, requires_grad=True)
                off_t = offset(obox.from_unit(qu))  # (n,)
            off_np = off_t.detach().cpu().numpy()
        ll, gc, gv, gs, goff = red.loglik(c, v, s, off_np)
        g = np.zeros(p + 1)
        g[:n_fe] = vjp(gc, gv) @ du
        g[p] = gs
        if offset is not None and n_q:
            assert goff is not None
            (gq,) = torch.autograd.grad(off_t, qu, torch.from_numpy(goff))
            g[n_fe:p] = gq.numpy()
        return ll, g

    reparam = _flow_reparam(gp, inp.theta_box) if coords == "auto" else None
    fm = FlatModel(sites, loglik, mu, sd, inp.y_obs.dtype, reparam)
    if fused is not None and reparam is not None and p <= 64:
        fm.native = _native_flow_flat(fused, umap, reparam[1], sig, mu, sd, p)
    return fm


def _native_flow_flat(fused: Any, umap: GPInputMap, flow: Any, sig: Any, mu: float, sd: float,
                      p: int) -> Any:
    """The flat model's whole ``logp_and_grad`` in one native call
    (:class:`solderpyro._native.FlowFlat`) for :func:`pca_flat` in flow coordinates without
    offsets: ``fused`` (:func:`native_loglik`), the input map ``umap`` (FlowStressInputs),
    the coordinates ``flow`` (:class:`~.flowcoords.SoftFlowCoords`), the sigma site ``sig``
    with its LogNormal ``(mu, sd)``. Why: with the reduced likelihood in C the Python around
    it (sites, flow coordinates, input map) was 55 of 94 us per gradient."""
    from solderpyro import _native

    feats = umap.feats
    box = feats.box
    lh = box.to_working(torch.tensor([box.lower, box.upper], dtype=torch.float64)).numpy()[:, :p]
    head = [mu, sd] if sig.positive else [sig.lo, sig.hi - sig.lo]
    head += [flow.T, flow.lr, flow.lsh, flow.n, flow.frac, flow.za, flow.zb, flow.ls0a,
             flow.ls0b, *flow.p0, *flow.pw, *(float(v) for v in flow.log)]
    par = np.concatenate([np.asarray(head, dtype=float), umap.lo_t, umap.w_t,
                          umap.log_t.astype(float), lh[0], lh[1] - lh[0],
                          np.asarray(box.log_scale[:p], dtype=float), umap.in_lo[:p],
                          umap.in_span[:p]])
    dims = (p, int(sig.positive), *(int(i) for i in flow.idx))
    return _native.FlowFlat(dims, par, fused)


def _flow_reparam(gp: GPSurrogate, theta_box: Box) -> tuple[np.ndarray, Any] | None:
    """``(idx, SoftFlowCoords)`` for a surrogate on flow-stress inputs whose calibration box
    the transform covers, else None (the logit)."""
    from solderpyro.calibration.flowcoords import SoftFlowCoords
    from solderpyro.surrogate.features import FlowStressInputs

    feats = gp.inputs
    if not isinstance(feats, FlowStressInputs) or SoftFlowCoords.applies(theta_box,
                                                                          feats.fixed):
        return None
    c = SoftFlowCoords(theta_box, feats.fixed, feats.T_ref_K - 273.15, feats.rate_ref)
    return c.idx.astype(np.int64), c
