"""Stage 4, the FE check: does the FE itself fit where the surrogate posterior lies?"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

#: the FE check warns when even the best of the checked posterior draws misfits by more than
#: this many noise sd (the project's yardstick: a fit at the noise level is within 1.5 sd) ...
FE_CHECK_RMS = 1.5
#: ... and its chi-square exceeds this quantile of chi2(n) (guards small n against chance)
FE_CHECK_QUANTILE = 0.999
#: posterior draws the FE check runs (one batched FE solve)
FE_CHECK_DRAWS = 8


def misfits(chi2: float, n: int) -> bool:
    """The FE check's rule: a chi-square ``chi2`` (residuals over the noise sd) on ``n``
    values misfits when it is not finite, or when its RMS residual exceeds
    :data:`FE_CHECK_RMS` noise sd and it exceeds the :data:`FE_CHECK_QUANTILE` quantile of
    chi2(n)."""
    from scipy.stats import chi2 as chi2_dist

    if not np.isfinite(chi2):
        return True
    return bool(np.sqrt(chi2 / n) > FE_CHECK_RMS and chi2 > chi2_dist.ppf(FE_CHECK_QUANTILE, n))


#: a misfit remains at the FE's best fit when its chi-square exceeds this quantile of
#: chi2(n - p): the model then still misses part of the physics (within the FE check's bound)
REMAINS_QUANTILE = 0.99


def misfit_remains(chi2: float, n: int, p: int) -> tuple[bool, float]:
    """Whether a misfit remains at a best fit of ``p`` parameters to ``n`` values whose
    chi-square (residuals over the noise sd) is ``chi2``, and the quantile it is judged by:
    ``chi2 > `` the :data:`REMAINS_QUANTILE` point of chi2(n - p)."""
    from scipy.stats import chi2 as chi2_dist

    if n - p < 1:
        raise ValueError(f"misfit_remains: need more values than parameters, got n={n}, p={p}")
    q = float(chi2_dist.ppf(REMAINS_QUANTILE, n - p))
    return bool(np.isfinite(chi2) and chi2 > q), q


#: a posterior misses a best fit when its best draw fits worse by more than this quantile of
#: chi2(dim) (the excess of a posterior draw over the optimum of a Gaussian posterior follows
#: chi2(dim))
MISSES_QUANTILE = 0.999


def misses(c2_draw: float, c2_fit: float, dim: int) -> bool:
    """Does a posterior whose best draw has chi-square ``c2_draw`` miss a best fit at
    ``c2_fit`` (both residuals over the noise sd) in ``dim`` parameters: is the draw worse by
    more than the :data:`MISSES_QUANTILE` point of chi2(dim)? The draws of a posterior
    around that fit are not that far off it."""
    from scipy.stats import chi2 as chi2_dist

    return bool(c2_draw - c2_fit > chi2_dist.ppf(MISSES_QUANTILE, dim))


def ranked(V: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``(b,)`` indices of the FE outputs ``V (b, n_obs)`` from the best fit of ``y
    (n_obs,)`` (lowest sum of squared residuals) to the worst, rows with a NaN (not converged)
    last."""
    r = np.atleast_2d(np.asarray(V, float)) - np.asarray(y, float)
    return np.argsort(np.where(np.isfinite(r).all(1), (r**2).sum(1), np.inf), kind="stable")


def fe_check(V: np.ndarray, y_obs: torch.Tensor, sigma: float) -> dict[str, Any]:
    """Does the FE itself fit where the surrogate posterior lies?

    A surrogate posterior can sit where the GP, not the FE, fits the data (a GP error in a
    region of large code variance soaks up the misfit). The FE at a few posterior draws shows
    it: if even the best of them misfits, the posterior is the surrogate's. (The marginal
    medians are no test point: for a weakly identified, curved posterior they can lie off the
    ridge where the model fits.)

    Args:
        V: ``(b, n_obs)`` FE outputs at ``b`` posterior draws, um (NaN rows: not converged);
        y_obs: ``(n_obs,)`` um; sigma: noise sd, um.
    Returns:
        ``{"chi2", "n", "rms_um", "rms_over_sigma", "draws", "ok", "best"}`` of the
        best-fitting draw (``best``: its row of ``V``, :func:`ranked`'s first);
        ``ok`` is False when its RMS residual exceeds :data:`FE_CHECK_RMS` noise sd and its
        chi-square the :data:`FE_CHECK_QUANTILE` quantile of chi2(n) (or no draw converged).
    """
    y = y_obs.detach().cpu().numpy()
    V = np.atleast_2d(np.asarray(V, float))
    k = int(ranked(V, y)[0])
    r = V[k] - y
    c2 = float(((r / sigma) ** 2).sum()) if np.isfinite(r).all() else float("inf")
    n = int(y.size)
    rms = float(np.sqrt(c2 / n)) * sigma if np.isfinite(c2) else float("nan")
    bad = misfits(c2, n)
    return {"chi2": c2, "n": n, "rms_um": rms, "rms_over_sigma": rms / sigma,
            "draws": int(V.shape[0]), "ok": not bad, "best": k}


#: the discretization check refines every element count and time-step limit by this factor
REFINE_FACTOR = 1.5
#: ... and warns when one refinement moves the model's observed outputs by at least this much
#: chi-square (noise units): the data then resolve the FE's own discretization error
DISCRETIZATION_CHI2 = 1.0


def refined(problem: Any, factor: float = REFINE_FACTOR) -> Any:
    """``problem`` (:class:`~solderpyro.fem.problem.Problem`) one refinement finer: every
    layer's element rows and the elements along x times ``factor`` (rounded, at least one
    more), the time steps' limits (``dT_max``, ``dt_max``, ``dwell_dt0``) divided by it."""
    import dataclasses

    def more(n: int) -> int:
        return max(n + 1, int(round(n * factor)))

    st = problem.stepping
    return dataclasses.replace(
        problem,
        layers=tuple(dataclasses.replace(lay, ny=more(lay.ny)) for lay in problem.layers),
        mesh=dataclasses.replace(problem.mesh, nx=more(problem.mesh.nx)),
        stepping=dataclasses.replace(st, dT_max=st.dT_max / factor, dt_max=st.dt_max / factor,
                                     dwell_dt0=st.dwell_dt0 / factor))


def refined_model(cp: Any, factor: float = REFINE_FACTOR) -> Any:
    """``cp`` (:class:`~.problem.CalibrationProblem`) on the FE once refined
    (:func:`refined`), the same data, store and effects; its runs count in ``cp.tally`` when
    added there."""
    import dataclasses

    from solderpyro.pipeline.problem import CalibrationProblem

    fine_setup = dataclasses.replace(cp.setup, problem=refined(cp.setup.problem, factor))
    return CalibrationProblem.build(fine_setup, cp.meas, str(cp.store.root), cp.batch,
                                    False).with_data(cp.data)


def discretization_error(cp: Any, theta: np.ndarray, factor: float = REFINE_FACTOR,
                         V: np.ndarray | None = None) -> np.ndarray:
    """The FE's discretization error at the observed values, estimated by one refinement:
    ``FE_refined(theta) - FE(theta)`` (two FE runs through the run store; observation-side
    effects cancel, so only the FE parameters enter).

    Args:
        cp: the :class:`~.problem.CalibrationProblem`; theta: ``(n_fe,)`` FE parameters,
            physical units; V: ``(n_obs,)`` the calibration FE at ``theta`` where at hand.
    Returns:
        ``(n_obs,)`` um (NaN where either FE run failed).
    """
    th = torch.as_tensor(np.asarray(theta, float)[None, :cp.n_fe], dtype=torch.float64)
    if V is None:
        V = cp.fe(th)[0][0].numpy()
    fine = refined_model(cp, factor)
    Vf = fine.fe(th)[0][0].numpy()
    cp.tally.add(fine.tally)
    return Vf - np.asarray(V, float)


def discretization_check(cp: Any, x: np.ndarray, sigma: float,
                         factor: float = REFINE_FACTOR, V: np.ndarray | None = None,
                         delta: np.ndarray | None = None) -> dict[str, Any]:
    """How far the FE's own discretization error reaches into what the data resolve.

    The FE at ``x`` (a point that fits: ``fit_change`` at a poor one measures the point) on
    the calibration's mesh and time steps, and once refined
    (:func:`refined`; one FE run each, through the run store): ``shift_chi2 = |V_fine - V|^2 /
    sigma^2``, the chi-square by which one refinement moves the observed outputs. A posterior moves
    by one sd along a direction that changes chi-square by one, so ``shift_chi2 >= 1``
    (:data:`DISCRETIZATION_CHI2`) says the intervals can be shifted by the discretization error
    (measured on the clean hidden-effect field data from a mesh twice as fine: 4.27 at the base
    run's medians; without the discretization correction the calibration's Q/R and m sat at or
    beyond their interval ends; BENCHMARKS.md, "Hidden effects: diagnose, recalibrate, cover the
    truths"). ``fit_change``: chi-square of the refined FE minus that of the calibration's
    (negative: the finer FE fits the data better).

    Args:
        cp: the :class:`~.problem.CalibrationProblem`; x: ``(dim,)`` a full parameter row,
            physical (the FE's best fit, or the best checked posterior draw); sigma: noise
            sd, um; V: ``(n_obs,)`` the calibration FE's outputs at ``x`` where they are at
            hand (else one more call of ``cp.observed``). The refined run counts in
            ``cp.tally`` (an FE run of the calibration; the store keeps it under the refined
            problem's hash). delta: ``(n_obs,)`` the correction the calibration applied
            (:meth:`~.problem.ObservedData.corrected`, taken at another point): the check then
            measures what is left, ``|V_fine - V - delta|^2 / sigma^2`` (and ``cp.y`` holds the
            corrected data).
    Returns:
        ``{"factor", "shift_chi2", "fit_change", "warn", "message"}`` (and, with ``delta``,
        ``"uncorrected_chi2"``: the shift without the correction).
    """
    row = np.asarray(x, float)[None]
    V = cp.observed(row)[0] if V is None else np.asarray(V, float)
    off = cp.offsets(torch.as_tensor(row, dtype=torch.float64))
    d = discretization_error(cp, row[0], factor, V if off is None else V - off[0].numpy())
    Vf = V + d
    y = cp.y.detach().cpu().numpy()
    corr = np.zeros_like(V) if delta is None else np.asarray(delta, float)
    shift = float(np.sum((Vf - V - corr) ** 2) / sigma**2)
    change = float((np.sum((y + corr - Vf) ** 2) - np.sum((y - V) ** 2)) / sigma**2)
    warn = bool(np.isfinite(shift) and shift >= DISCRETIZATION_CHI2)
    refine = f"one refinement of the FE (elements and time steps x{factor:g})"
    if delta is None:
        msg = (f"discretization: {refine} moves the model by chi2 {shift:.3g} at the best fit "
               f"(its fit changes by {change:+.3g})" + (
                   ": the data resolve the FE's own discretization error, so the intervals "
                   "can be shifted by up to ~sqrt of that in sd (calibration.discretization="
                   "correct, the default, takes it off the data of a model that fits; or "
                   "calibrate on a finer mesh, mesh=fine)"
                   if warn else ": below what the data resolve"))
        return {"factor": factor, "shift_chi2": shift, "fit_change": change, "warn": warn,
                "message": msg}
    raw = float(np.sum((Vf - V) ** 2) / sigma**2)
    msg = (f"discretization: corrected (the FE's error estimated by {refine}, chi2 {raw:.3g} "
           f"here, taken off the data); at the best fit the corrected FE is within chi2 "
           f"{shift:.3g} of the refined one" + (
               ": the error changes across the posterior by more than the data resolve; "
               "calibrate on a finer mesh (mesh=fine)" if warn else
               ": what is left is below what the data resolve"))
    return {"factor": factor, "shift_chi2": shift, "fit_change": change, "warn": warn,
            "uncorrected_chi2": raw, "message": msg}
