"""Each candidate effect's fingerprint: what it would change in the data, to set beside the
residual.

With the FE refits of the diagnosis (:func:`~solderpyro.diagnose.refits.refit_candidates`: the FE
refitted to the data with each candidate on, and without any), the fingerprint of effect c is
exact: ``V(x_c) - V(x_0)``, the change of the prediction when c is added and every parameter
is refitted, and the residual after adding it is ``y - V(x_c)``; the residual shown is then
``y - V(x_0)``, so that residual = fingerprint + residual after. Without refits (no misfit
found), when the baseline's refit is worse than its linearised fit (the refit stopped short:
its residual is not the model's best), or for a candidate whose refit fits worse than the
baseline's (it stopped short, e.g. at the box's edge), it is the linearised one,
``P J_c delta_c`` of the score test (the effect's change at its least-squares magnitude once
the calibrated parameters took their share).

The shape correlation of a fingerprint with the residual (Pearson, over every value) is taken
against the denoised residual for full-field data (:mod:`.denoise`: the noise, 2-5 times the
pattern, would otherwise hide it) and against the residual itself for point data.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from solderpyro.diagnose.denoise import Smooth, denoise, shape_correlation


@dataclass
class Fingerprints:
    """Fingerprints of the candidates, row for row with the data (um).

    Attributes:
        residual: ``(n,)`` the residual they explain (see the module docstring).
        source: effect -> ``"refit"`` (exact, from the FE refits) or ``"linearised"``;
            the residual is ``y - V(x_0)`` when the baseline refit is given, else ``P r``.
        smooth: the denoised residual (full-field data), else None.
        signature: effect -> ``(n,)`` its fingerprint.
        after: effect -> ``(n,)`` the residual after adding it.
        correlation: effect -> shape correlation of the fingerprint with the denoised residual
            (field) or the residual (points).
        smooth_after: effect -> the denoised residual after adding it (field; its own
            smoother, fitted to it: what is left shows only if it is above the noise).
    """

    residual: np.ndarray
    source: dict[str, str]
    smooth: Smooth | None
    signature: dict[str, np.ndarray]
    after: dict[str, np.ndarray]
    correlation: dict[str, float]
    smooth_after: dict[str, Smooth] = field(default_factory=dict)


def fingerprints(meas: Any, residual: np.ndarray, scores: list[Any], sigma: float,
                 preds: dict[str, np.ndarray] | None = None, field_data: bool = True,
                 smooth_top: tuple[str, ...] = ()) -> Fingerprints:
    """The fingerprints of every scored candidate, and the denoised residual.

    Args:
        meas: the data (n rows; ``x_mm``, ``y_mm``, ``time_s``, ``value_um``).
        residual: ``(n,)`` the linearised refitted residual ``P r`` (used without refits).
        scores: the candidates' ``Score`` (their ``pattern`` is the linearised fingerprint).
        sigma: noise sd, um.
        preds: ``"baseline"`` and effect -> ``(n,)`` FE prediction at its refit, um (an
            effect left out gets its linearised fingerprint); None: all linearised.
        field_data: denoise (full-field data) or not (points).
        smooth_top: effects whose residual after is also denoised.
    Returns:
        :class:`Fingerprints`.
    """
    y = np.asarray(meas.value_um, float)
    sig: dict[str, np.ndarray] = {}
    after: dict[str, np.ndarray] = {}
    source: dict[str, str] = {}
    if preds is not None and "baseline" in preds:
        res = y - preds["baseline"]
        for s in scores:
            if s.effect in preds:
                sig[s.effect] = preds[s.effect] - preds["baseline"]
                after[s.effect] = y - preds[s.effect]
                source[s.effect] = "refit"
    else:
        res = np.asarray(residual, float)
    for s in scores:
        if s.effect not in sig:
            sig[s.effect] = np.asarray(s.pattern, float)
            after[s.effect] = res - sig[s.effect]
            source[s.effect] = "linearised"
    xy = np.c_[meas.x_mm, meas.y_mm]
    sm = denoise(xy, res, meas.time_s, sigma) if field_data else None
    ref = sm.mean if sm is not None else res
    corr = {e: shape_correlation(v, ref) for e, v in sig.items()}
    sm_after = {}
    if sm is not None:
        for e in smooth_top:
            if e in after:
                sm_after[e] = denoise(xy, after[e], meas.time_s, sigma)
    return Fingerprints(res, source, sm, sig, after, corr, sm_after)
