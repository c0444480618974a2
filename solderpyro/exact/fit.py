"""Least-squares fits through the FE: a batched, bounded Levenberg-Marquardt.

Used where the exact model (not the surrogate) must say where the data are fitted best: the
FE anchor of a calibration's refinement (:func:`solderpyro.pipeline.calibrate_specimen`) and the
profile refits of the diagnosis (:func:`solderpyro.diagnose.refits.fit_models`). Several starts
(or models with different free parameters) advance together, so every FE call is one batch.

Units: parameters in their physical units, predictions and data in um, sigma in um.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np


@dataclass
class LMFit:
    """One start's result.

    Attributes:
        x: ``(p,)`` parameters at the end (physical units).
        chi2: ``sum((y - f(x))^2) / sigma^2`` there.
        free: indices of the parameters that were fitted.
        J: ``(n, len(free))`` forward-difference Jacobian of f with respect to the free
            parameters scaled to the unit box (``df / du``, um), at the last point where it was
            evaluated (the last accepted step's start; None if never).
        iters: accepted steps; history: chi-square at each evaluation.
        converged: the stopping rule of :attr:`LMOptions.tol` was met (always False
            without ``tol``).
    """

    x: np.ndarray
    chi2: float
    free: np.ndarray
    J: np.ndarray | None = None
    iters: int = 0
    history: list[float] = field(default_factory=list)
    converged: bool = False

    def jacobian_unit(self, lo: Sequence[float] | np.ndarray, hi: Sequence[float] | np.ndarray,
                      log_scale: Sequence[bool]) -> np.ndarray | None:
        """:attr:`J` on a box's unit scale, logarithmic where ``log_scale`` says so (the scale
        of :meth:`solderpyro.params.Box.to_unit`): ``(n, len(free))`` um, None if no J.

        ``d(linear unit)/d(log unit) = x log(hi/lo) / (hi - lo)`` for a log-scale parameter.
        """
        if self.J is None:
            return None
        lo_a, hi_a = np.asarray(lo, float)[self.free], np.asarray(hi, float)[self.free]
        logm = np.asarray(log_scale, bool)[self.free]
        x = np.asarray(self.x, float)[self.free]
        ratio = np.where(logm, hi_a / np.where(logm, lo_a, 1.0), np.e)  # lo > 0 where log
        dudv = np.where(logm, x * np.log(ratio) / (hi_a - lo_a), 1.0)
        return self.J * dudv[None]

    def laplace_sd(self, lo: np.ndarray, hi: np.ndarray, sigma: float) -> np.ndarray:
        """Marginal sd ``(len(free),)`` of the free parameters (physical units) under the
        Laplace approximation ``(J' J / sigma^2)^-1`` (pseudo-inverse: a direction the data do
        not constrain gets the box width)."""
        w = (np.asarray(hi) - np.asarray(lo))[self.free]
        if self.J is None:
            return w.copy()
        A = self.J.T @ self.J / sigma**2
        cov = np.linalg.pinv(A, rcond=1e-10)
        sd = np.sqrt(np.clip(np.diag(cov), 0.0, None)) * w
        return np.minimum(np.where(np.isfinite(sd), sd, w), w)


#: damping factors of the trial steps of each iteration (one batched call for all of them)
TRIALS = np.array([0.01, 0.1, 1.0, 10.0, 100.0])


def _step(A: np.ndarray, g: np.ndarray, lam: float, x: np.ndarray, lo: np.ndarray,
          hi: np.ndarray) -> np.ndarray:
    """The damped Gauss-Newton step ``(k,)`` (unit-box scale) with the binding parameters held:
    those on a bound whose descent direction ``g`` (``J' W r``) points out of the box (the
    binding set of a projected Newton method, Bertsekas 1982). Without it, a step clipped
    afterwards turns, and a fit whose optimum lies beyond a bound crept along it."""
    tiny = 1e-12 * (hi - lo)
    act = ~(((x <= lo + tiny) & (g < 0)) | ((x >= hi - tiny) & (g > 0)))
    du = np.zeros(len(g))
    if act.any():
        Aa = A[np.ix_(act, act)]
        du[act] = np.linalg.solve(Aa + lam * np.diag(np.diag(Aa) + 1e-12), g[act])
    return du


def _truncate(x: np.ndarray, step: np.ndarray, lo: np.ndarray, hi: np.ndarray
              ) -> np.ndarray:
    """``x + alpha step`` with the largest ``alpha <= 1`` that stays in the box, after holding
    the components on a bound that would step out: the step keeps its direction up to the
    first bound it meets, where clipping each component turns it. Measured once by hand on
    the hidden-modulus field data, from the posterior median: the same optimum (chi2 17,239,
    on three bounds) in 5 iterations instead of 10."""
    tiny = 1e-12 * (hi - lo)
    step = np.where(((x <= lo + tiny) & (step < 0)) | ((x >= hi - tiny) & (step > 0)),
                    0.0, step)
    with np.errstate(divide="ignore", invalid="ignore"):
        room = np.where(step > 0, (hi - x) / step, np.where(step < 0, (lo - x) / step, np.inf))
    alpha = float(min(1.0, np.min(room))) if len(room) else 1.0
    return np.clip(x + max(alpha, 0.0) * step, lo, hi)


@dataclass(frozen=True)
class LMOptions:
    """The tuning of :func:`lm_fit`.

    Attributes:
        iters: iterations (the most, with ``tol``).
        rel: difference step as a share of the box width.
        lam0: the first iteration's damping.
        tol: stop a start once an iteration lowers its chi-square by less than ``tol``
            (absolute; the chi-square's own sampling sd is ``sqrt(2 n)``, so 0.1 is far below
            anything a test could see), or once two iterations in a row accept no step (the
            second one's trials damped 1e3 x more: a bound or a kink holds it); stopped starts
            cost no more FE rows. None: run all ``iters``.
    """

    iters: int = 5
    rel: float = 1e-3
    lam0: float = 1e-2
    tol: float | None = None


def lm_fit(fun: Callable[[np.ndarray], np.ndarray], x0: np.ndarray,
           lo: Sequence[float] | np.ndarray, hi: Sequence[float] | np.ndarray, y: np.ndarray,
           sigma: float, free: Sequence[np.ndarray] | None = None,
           options: LMOptions = LMOptions()) -> list[LMFit]:
    """Bounded Levenberg-Marquardt from ``S`` starts at once, forward differences.

    Each iteration makes two calls of ``fun``: the points and their difference steps (``S``
    starts x ``(1 + n_free)`` rows), then five trial steps per start (damping lam x 0.01, 0.1,
    1, 10, 100); the best trial is taken if it lowers chi-square, and the next iteration's
    damping is a tenth of the one taken. A step that would leave the box is shortened along
    its direction to the first bound it meets, and parameters held on a bound by the descent
    direction stay there (:func:`_step`, :func:`_truncate`).

    Trials below the current damping let a start that was damped hard (after a rejected step)
    take full Gauss-Newton steps again at once: with only lam, 10 lam and 100 lam, a fit
    along the Anand constants' curved ridge crept at 0.3 % of chi-square per iteration for 10
    iterations after one rejection (seen in ``solderpyro diagnose``'s base fit).

    Args:
        fun: ``rows (N, p) -> (N, n)`` predictions (um; NaN rows where the model failed).
        x0: ``(S, p)`` starts, physical units, inside ``[lo, hi]``.
        lo, hi: ``(p,)`` box.
        y: ``(n,)`` data, um; sigma: noise sd, um.
        free: per start, the indices it fits (default: all ``p``).
        options: iterations, difference step, first damping and stopping rule
            (:class:`LMOptions`).
    Returns:
        ``S`` :class:`LMFit`, in the order of ``x0``.
    """
    x0 = np.atleast_2d(np.asarray(x0, float))
    lo_a, hi_a = np.asarray(lo, float), np.asarray(hi, float)
    if x0.shape[1] != lo_a.shape[0] or hi_a.shape != lo_a.shape:
        raise ValueError(f"lm_fit: x0 has {x0.shape[1]} columns, lo/hi {lo_a.shape}/"
                         f"{hi_a.shape}")
    if not sigma > 0:
        raise ValueError(f"lm_fit: sigma must be > 0, got {sigma}")
    iters, rel, lam0, tol = options.iters, options.rel, options.lam0, options.tol
    y = np.asarray(y, float)
    S = x0.shape[0]
    frees = [np.arange(x0.shape[1])] * S if free is None else [np.asarray(f, int) for f in free]
    fits = [LMFit(x0[s].copy(), np.inf, frees[s]) for s in range(S)]
    lam = np.full(S, lam0)
    rejected = np.zeros(S, int)
    h_all = rel * (hi_a - lo_a)
    width = hi_a - lo_a
    for _ in range(iters):
        rows: list[np.ndarray] = []
        where: dict[int, int] = {}
        for s, ft in enumerate(fits):
            if ft.converged:
                continue
            where[s] = len(rows)
            rows.append(ft.x)
            rows += _step_rows(ft.x, ft.free, h_all, hi_a)
        if not rows:
            break
        V = fun(np.array(rows))
        trials: list[np.ndarray] = []
        tw: dict[int, int] = {}
        for s, i0 in where.items():
            ft = fits[s]
            fr = ft.free
            r = y - V[i0]
            ft.chi2 = float(((r / sigma) ** 2).sum())
            ft.history.append(ft.chi2)
            J = _difference_jacobian(V[i0], V[i0 + 1:i0 + 1 + len(fr)], ft.x,
                                     rows[i0 + 1:i0 + 1 + len(fr)], fr, width)
            if not (np.all(np.isfinite(J)) and np.isfinite(ft.chi2)):
                continue
            ft.J = J
            A, g = J.T @ J / sigma**2, J.T @ r / sigma**2
            tw[s] = len(trials)
            for lm in lam[s] * TRIALS:
                xt = ft.x.copy()
                xt[fr] = _truncate(ft.x[fr], _step(A, g, lm, ft.x[fr], lo_a[fr], hi_a[fr])
                                   * width[fr], lo_a[fr], hi_a[fr])
                trials.append(xt)
        if not trials:
            break
        Vt = fun(np.array(trials))
        for s, i0 in tw.items():
            ft = fits[s]
            c2 = np.array([((y - v) ** 2).sum() / sigma**2
                           for v in Vt[i0:i0 + len(TRIALS)]])
            c2 = np.where(np.isfinite(c2), c2, np.inf)
            k = int(np.argmin(c2))
            if c2[k] < ft.chi2:
                gain = ft.chi2 - float(c2[k])
                ft.x, ft.chi2 = trials[i0 + k], float(c2[k])
                lam[s] = max(lam[s] * TRIALS[k] * 0.1, 1e-9)
                ft.iters += 1
                rejected[s] = 0
                ft.converged = tol is not None and gain < tol
            else:
                lam[s] *= 1e3
                rejected[s] += 1
                ft.converged = tol is not None and rejected[s] >= 2
    for ft in fits:
        if not ft.history or ft.chi2 < ft.history[-1]:
            ft.history.append(ft.chi2)
    return fits


def difference_jacobian(fun: Callable[[np.ndarray], np.ndarray], x: np.ndarray,
                        lo: Sequence[float] | np.ndarray, hi: Sequence[float] | np.ndarray,
                        rel: float = 1e-3) -> LMFit:
    """The forward-difference Jacobian at one point, as :func:`lm_fit` takes it, in one call
    of ``fun`` (``1 + p`` rows) and without the trial steps of an iteration.

    Args:
        fun: ``rows (N, p) -> (N, n)`` predictions (um); x: ``(p,)`` the point, physical units,
            inside ``[lo, hi]``; lo, hi: ``(p,)`` box; rel: the step as a share of its width
            (backward where a forward step would leave the box).
    Returns:
        an :class:`LMFit` at ``x`` with every parameter free, ``J (n, p)`` on the unit-box
        scale (None where a row failed) and ``chi2`` NaN (no data).
    """
    x = np.asarray(x, float).reshape(-1)
    lo_a, hi_a = np.asarray(lo, float), np.asarray(hi, float)
    width = hi_a - lo_a
    free = np.arange(len(x))
    steps = _step_rows(x, free, rel * width, hi_a)
    V = fun(np.array([x, *steps]))
    J = _difference_jacobian(V[0], V[1:], x, steps, free, width)
    return LMFit(x.copy(), float("nan"), free, J if np.all(np.isfinite(J)) else None)


def _step_rows(x: np.ndarray, free: np.ndarray, h: np.ndarray, hi: np.ndarray
               ) -> list[np.ndarray]:
    """The difference steps of ``x (p,)``: one row per index of ``free``, that parameter
    moved by ``h`` (forward, or backward where forward would pass ``hi``)."""
    out = []
    for j in free:
        xj = x.copy()
        xj[j] += h[j] if x[j] + h[j] <= hi[j] else -h[j]
        out.append(xj)
    return out


def _difference_jacobian(v0: np.ndarray, v_steps: np.ndarray, x: np.ndarray,
                         steps: Sequence[np.ndarray], free: np.ndarray, width: np.ndarray
                         ) -> np.ndarray:
    """``(n, len(free))`` forward differences on the unit-box scale from the predictions at
    ``x`` (``v0 (n,)``) and at its :func:`_step_rows` (``v_steps (len(free), n)``)."""
    dx = np.array([steps[k][j] - x[j] for k, j in enumerate(free)])
    return (v_steps - v0).T / dx * width[free]
