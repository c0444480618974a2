"""Stage (where a misfit remains): intervals that admit the model-form error.

A calibration whose FE best fit still misfits the data beyond the noise
(:func:`~solderpyro.pipeline.fe_check.misfit_remains`) has constants that absorb part of the
physics the model misses, and intervals that do not know it. This stage fits a Kennedy-O'Hagan
discrepancy over (time, x, y) to the residual there, takes the constants' Laplace posterior
under that likelihood (:mod:`solderpyro.exact.discrepancy`), and reports, per parameter, the
hull of the posterior's interval and that one (kind :data:`MODEL_FORM` in summary.csv), with
what was fitted in ``model_form.json``.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from solderpyro.calibration.intervals import MODEL_FORM
from solderpyro.exact.discrepancy import WidenedInterval, fit_discrepancy, widened_intervals
from solderpyro.exact.fit import difference_jacobian
from solderpyro.pipeline.problem import CalibrationProblem

log = logging.getLogger("solderpyro")


@dataclass(frozen=True)
class ModelForm:
    """What the model-form stage found.

    Attributes:
        intervals: one :class:`~solderpyro.exact.discrepancy.WidenedInterval` per parameter of
            the calibration's space.
        sd_um: the discrepancy's sd, um. noise_sd_um: the noise sd, um.
        lengthscales: ``{"time_s", "x_mm", "y_mm"}`` -> its correlation length (None: the data
            do not vary along it).
        at: ``name -> value`` where it was linearised.
    """

    intervals: list[WidenedInterval]
    sd_um: float
    noise_sd_um: float
    lengthscales: dict[str, float | None]
    at: dict[str, float]


def model_form_intervals(cp: CalibrationProblem, x_best: np.ndarray, seed: int = 0
                         ) -> ModelForm:
    """The discrepancy's intervals at the FE's best fit ``x_best`` ``(space.dim,)`` (physical
    units): its Jacobian on the box's unit scale (forward differences through the run store:
    one batched solve of ``1 + dim`` rows, :func:`~solderpyro.exact.fit.difference_jacobian`),
    the residual there, the
    discrepancy fitted over the measurements' (time s, x mm, y mm)."""
    space, meas = cp.space, cp.meas
    y = cp.y.numpy()
    x_best = np.asarray(x_best, float).reshape(-1)
    r = y - cp.observed(x_best[None])[0]
    if not np.isfinite(r).all():
        raise RuntimeError("the FE did not converge at the best fit")
    fit = difference_jacobian(cp.observed, x_best, space.lower, space.upper)
    J = fit.jacobian_unit(space.lower, space.upper, space.log_scale)
    if J is None:
        raise RuntimeError("the FE did not converge at the Jacobian's difference steps")
    X = np.c_[meas.time_s, meas.x_mm, meas.y_mm]
    d = fit_discrepancy(X, r, cp.priors.sigma_known, seed)
    return ModelForm(widened_intervals(space, x_best, J, r, d), d.sd_um, d.noise_sd_um,
                     {k: float(v) if np.isfinite(v) else None for k, v in
                      zip(("time_s", "x_mm", "y_mm"), d.lengthscales, strict=True)},
                     dict(zip(space.names, map(float, x_best), strict=True)))


def widen_rows(rows: list[dict], mf: ModelForm) -> list[dict]:
    """Summary rows whose reported 95 % interval (``lo95``, ``hi95``) is the hull of their own
    and the model-form one, kind :data:`MODEL_FORM` where that widened it; rows of parameters
    outside the space (the noise sd) unchanged."""
    by = {iv.parameter: iv for iv in mf.intervals}
    out = []
    for r in rows:
        iv = by.get(r["parameter"])
        if iv is None:
            out.append(r)
            continue
        lo, hi = min(float(r["lo95"]), iv.lo), max(float(r["hi95"]), iv.hi)
        wider = lo < float(r["lo95"]) or hi > float(r["hi95"])
        out.append({**r, "lo95": lo, "hi95": hi,
                    "interval": MODEL_FORM if wider else r["interval"]})
    return out


def model_form_text(mf: ModelForm) -> str:
    """The trust line's account of the widening."""
    widest = max(mf.intervals, key=lambda iv: iv.widening)
    ls = ", ".join(f"{v:.3g} {k.rsplit('_', 1)[1]}" for k, v in mf.lengthscales.items()
                   if v is not None)
    return (f"the 95 % intervals are widened for that model-form error: a Kennedy-O'Hagan "
            f"discrepancy fitted to the residual (sd {mf.sd_um:.3g} um, correlation lengths "
            f"{ls}) leaves the constants less certain, {widest.parameter}'s interval "
            f"{widest.widening:.1f} x as wide as with independent noise (model_form.json); "
            "the intervals are wide where the constants compensate the missing physics")


def model_form_stage(cp: CalibrationProblem, rows: list[dict], x_best: np.ndarray,
                     out: Path, seed: int = 0) -> tuple[list[dict], str]:
    """Widen ``rows`` for the model-form error at ``x_best`` and write model_form.json.

    Returns:
        ``(rows, text)``: the widened rows and the trust line's account, or the rows unchanged
        and a problem saying why the widening failed (the run's other results are kept).
    """
    log.info("model form: a misfit remains; fitting a discrepancy to the residual at the "
             "FE's best fit to widen the intervals")
    try:
        mf = model_form_intervals(cp, x_best, seed)
    except (RuntimeError, ValueError, np.linalg.LinAlgError) as err:
        log.warning("model form: intervals not widened: %s", err)
        return rows, f"the intervals could not be widened for the model-form error: {err}"
    ivs = [{**asdict(iv), "widening": iv.widening if np.isfinite(iv.widening) else None}
           for iv in mf.intervals]
    (out / "model_form.json").write_text(json.dumps({**asdict(mf), "intervals": ivs},
                                                    indent=1) + "\n")
    for iv in mf.intervals:
        log.info("model form: %s in [%.4g, %.4g] (%.1f x the independent-noise width)",
                 iv.parameter, iv.lo, iv.hi, iv.widening)
    return widen_rows(rows, mf), model_form_text(mf)
