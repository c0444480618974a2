"""A volume-preserving map that straightens a curved posterior ridge for NUTS.

The specimen's posterior is a thin *curved* ridge (the Anand constants trade off along a
curve): on the modulus-temperature recalibration, regressing one coordinate on the others
leaves 0.8 % of its variance linearly but 0.01 % quadratically. A mass matrix, dense or not,
is linear: NUTS then needs a step as small as the ridge is thin and ~50 leapfrog steps per
iteration to follow it (step 0.08, 54 gradients per iteration with a dense metric).

:class:`RidgeMap` is a lower-triangular map with unit diagonal, learned from draws of a
previous posterior of the same model (the design's last round; the final posterior samples
the same surrogate):

    z = (q - mean) / sd,   z_0 = w_0,   z_k = w_k + f_k(z_0 .. z_{k-1})   (k = 1 .. d - 1)

with ``f_k`` quadratic in the earlier coordinates, each passed through ``h``: the identity
within the range ``|z| <= a`` the draws span, beyond it ``sign(z) (a + tanh(|z| - a))`` (at
most one sd more: the fitted quadratic is not extrapolated far outside the draws, where it
would bend the tails; ``h`` is continuous with its first derivative).
Each ``f_k`` is the least-squares regression of ``z_k`` on those features over the draws, so
``w`` is what is left of each coordinate once the ridge's curve is taken out. Because the map
only shifts each coordinate by a function of the earlier ones, its Jacobian ``dz/dw`` is unit
lower-triangular: ``log|det| = 0`` (plus the constant ``sum log sd``), so the density of
``w`` is the density of ``q`` at ``T(w)``, and NUTS on ``w`` samples exactly the same
posterior, whatever the fit's quality. A poor fit costs only speed.

Measured paired on two field posteriors (``benchmarks/ridge_coords.py``, BENCHMARKS.md,
"Per-gradient and per-round costs of the calibration"): gradients per iteration 35-49 -> 9-21, min
bulk ESS per second 1.07-2.0x, the same quantiles to Monte Carlo error, and 2-16 divergent
transitions in 6,000 where the sampler's own coordinates had none (the quadratic does not straighten
the tails).

Written here rather than taken from a library: the normalizing-flow packages (e.g. Pyro's
``AffineAutoregressive``, ``flowMC``) train neural flows by stochastic optimization, seconds
to minutes per fit; this is a closed-form least-squares fit in milliseconds, refitted every
design round.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from itertools import combinations_with_replacement
from typing import Any

import numpy as np

#: ridge regularization of the least squares (times the number of draws), standardized units
RIDGE = 1e-6
#: fewest draws a map is fitted to (per feature of the last coordinate: ~10)
MIN_DRAWS = 200
#: a coordinate's quadratic terms are kept only where they leave at most 1 / QUAD_GAIN of the
#: residual variance the linear ones leave. Why: on a posterior pressed into a box corner
#: (the loop's base run, a model that misfits) the quadratic explained <= 8 % more than the
#: linear shear, and in its coordinates one chain adapted to step 0.025 and 100 gradients per
#: iteration (7 without the map); on the CTE-slope posterior the one coordinate where it
#: gains 25 % (m: 0.0176 -> 0.0131) is the ridge's bend
QUAD_GAIN = 1.25

LogpGrad = Callable[[np.ndarray], tuple[float, np.ndarray]]


class RidgeMap:
    """``q = T(w)`` (module docstring), fitted to draws ``Q (N, d)`` of ``q``.

    Attributes:
        mean, sd: ``(d,)`` the draws' standardization; span: ``(d,)`` their largest
        ``|z|``. curved: per coordinate, whether its quadratic terms are kept
        (:data:`QUAD_GAIN`; else only the linear ones). coef: per coordinate ``k >= 1`` the
            regression coefficients on ``[1, h(z_<k), h(z_i) h(z_j) (i <= j < k)]``.
    """

    def __init__(self, Q: np.ndarray) -> None:
        Q = np.asarray(Q, dtype=float)
        if Q.ndim != 2 or Q.shape[1] < 2 or len(Q) < MIN_DRAWS:
            raise ValueError(f"RidgeMap needs draws (N >= {MIN_DRAWS}, d >= 2), got shape "
                             f"{Q.shape}")
        if not np.all(np.isfinite(Q)):
            raise ValueError("RidgeMap: the draws have non-finite values")
        self.d = Q.shape[1]
        self.mean = Q.mean(0)
        self.sd = np.maximum(Q.std(0), 1e-12)
        Z = (Q - self.mean) / self.sd
        self.span = np.abs(Z).max(0)  # a: h is the identity within the draws
        H = self._h(Z)
        self._pairs = [list(combinations_with_replacement(range(k), 2)) for k in range(self.d)]
        self.coef: list[np.ndarray] = [np.zeros(0)]
        self.curved = [False]
        for k in range(1, self.d):
            F = self._features(H[:, :k], k)
            A = F.T @ F + RIDGE * len(Z) * np.eye(F.shape[1])
            c = np.linalg.solve(A, F.T @ Z[:, k])
            lin = 1 + k  # the constant and linear columns: what a dense metric already does
            cl = np.linalg.solve(A[:lin, :lin], F[:, :lin].T @ Z[:, k])
            r_quad = float(np.var(Z[:, k] - F @ c))
            r_lin = float(np.var(Z[:, k] - F[:, :lin] @ cl))
            curved = r_lin >= QUAD_GAIN * r_quad
            if not curved:  # a straight ridge: no bend to take out, keep the shear linear
                c = np.concatenate([cl, np.zeros(len(c) - lin)])
            self.curved.append(curved)
            self.coef.append(c)
        self._quadratic_forms()

    def _h(self, z: np.ndarray) -> np.ndarray:
        a = self.span[:z.shape[-1]]
        over = np.maximum(np.abs(z) - a, 0.0)
        return np.where(over > 0.0, np.sign(z) * (a + np.tanh(over)), z)

    def _dh(self, z: np.ndarray) -> np.ndarray:
        over = np.maximum(np.abs(z) - self.span[:z.shape[-1]], 0.0)
        return 1.0 - np.tanh(over) ** 2

    def _features(self, h: np.ndarray, k: int) -> np.ndarray:
        """``(N, 1 + k + k (k + 1) / 2)`` regressors of coordinate ``k`` from ``h (N, k)``
        (the fit's design matrix)."""
        quad = [h[..., i] * h[..., j] for i, j in self._pairs[k]]
        return np.concatenate([np.ones((*h.shape[:-1], 1)), h, *(
            [np.stack(quad, -1)] if quad else [])], -1)

    def _quadratic_forms(self) -> None:
        """``f_k(h) = c0_k + b_k . h + h . A_k h`` and ``S_k = A_k + A_k^T`` from the fitted
        ``coef``: what :meth:`_shift` and :meth:`vjp` evaluate (a few small dot products per
        point: the map runs at every gradient)."""
        self._c0, self._b, self._A, self._S = [0.0], [np.zeros(0)], [np.zeros((0, 0))], [
            np.zeros((0, 0))]
        for k in range(1, self.d):
            c = self.coef[k]
            A = np.zeros((k, k))
            for (i, j), v in zip(self._pairs[k], c[1 + k:], strict=True):
                A[i, j] += v
            self._c0.append(float(c[0]))
            self._b.append(c[1:1 + k].copy())
            self._A.append(A)
            self._S.append(A + A.T)

    def _h1(self, k: int, z: float) -> float:
        a = float(self.span[k])
        over = abs(z) - a
        return z if over <= 0.0 else math.copysign(a + math.tanh(over), z)

    def _shift(self, k: int, h: np.ndarray) -> np.ndarray | float:
        """``f_k`` at ``h (..., k)`` = h(z_<k): ``c0 + b . h + h . A h`` (one formula for one
        point and for a batch)."""
        return self._c0[k] + h @ self._b[k] + ((h @ self._A[k]) * h).sum(-1)

    def forward(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``w (..., d) -> (q (..., d), z (..., d))`` (``z`` standardized, for :meth:`vjp`)."""
        w = np.asarray(w, dtype=float)
        z = np.empty_like(w)
        if w.ndim == 1:  # one point, the sampler's path: h by scalar math (measured faster)
            h = np.empty(self.d)
            z[0] = w[0]
            h[0] = self._h1(0, float(z[0]))
            for k in range(1, self.d):
                z[k] = w[k] + self._shift(k, h[:k])
                h[k] = self._h1(k, float(z[k]))
            return self.mean + self.sd * z, z
        z[..., 0] = w[..., 0]
        for k in range(1, self.d):
            z[..., k] = w[..., k] + self._shift(k, self._h(z[..., :k]))
        return self.mean + self.sd * z, z

    def inverse(self, q: np.ndarray) -> np.ndarray:
        """``q (..., d) -> w (..., d)``, exactly inverting :meth:`forward`."""
        z = (np.asarray(q, dtype=float) - self.mean) / self.sd
        w = z.copy()
        for k in range(1, self.d):
            w[..., k] = z[..., k] - self._shift(k, self._h(z[..., :k]))
        return w

    def vjp(self, z: np.ndarray, g_q: np.ndarray) -> np.ndarray:
        """``(dq/dw)^T g_q`` at the point whose standardized coordinates are ``z (d,)``:
        the gradient in ``w`` of a function whose gradient in ``q`` is ``g_q (d,)``."""
        a = np.asarray(g_q, dtype=float) * self.sd  # d/dz
        h = self._h(z)
        dh = self._dh(z)
        for k in range(self.d - 1, 0, -1):  # reverse sweep: z_k = w_k + f_k(h(z_<k))
            hk = h[:k]
            a[:k] += a[k] * (self._b[k] + self._S[k] @ hk) * dh[:k]
        return a

    def native(self) -> Any:
        """The one-point :meth:`forward` and :meth:`vjp` in C
        (:class:`solderpyro._native.RidgeMapKernel`, the same formulas), or None where the
        native kernels are unavailable. Why: in NumPy the map cost 36 us of a 137 us gradient
        of the loop's final posterior (~60 calls on vectors of d values); in C ~3 us."""
        from solderpyro import _native

        if _native.library() is None or self.d > 64:
            return None
        d = self.d
        b, A, S = np.zeros((d, d)), np.zeros((d, d, d)), np.zeros((d, d, d))
        for k in range(1, d):
            b[k, :k] = self._b[k]
            A[k, :k, :k] = self._A[k]
            S[k, :k, :k] = self._S[k]
        return _native.RidgeMapKernel(self.mean, self.sd, self.span, np.asarray(self._c0), b,
                                      A, S)

    def wrap(self, logp_and_grad: LogpGrad) -> LogpGrad:
        """The log density and gradient in ``w`` of one in ``q`` (the same density: the
        Jacobian's determinant is the constant ``prod sd``); through :meth:`native` where
        available."""
        kern = self.native()
        fwd, vjp = (self.forward, self.vjp) if kern is None else (kern.forward, kern.vjp)

        def f(w: np.ndarray) -> tuple[float, np.ndarray]:
            q, z = fwd(w)
            lp, g = logp_and_grad(q)
            return lp, vjp(z, g)

        return f
