"""What the data cannot rule out: effects the fit does not need, yet would move the constants.

When the model fits (no candidate is selected), a candidate effect can still be present: its
signature may be one the calibrated constants mimic. Eight point displacements with copper
plasticity at 15 MPa fit as well as an elastic copper with a lower strain-rate exponent m (the
hidden copper case on point data: chi2 3.3 on 4 dof, m 0.051-0.073 against the true 0.1). The
fit is then no evidence that the effect is absent, and the reported intervals hold only if it
is.

For each one-parameter candidate the diagnosis already has the FE with the effect switched on
at its ladder of magnitudes (:func:`~solderpyro.diagnose.screen.fe_jacobians`), the calibrated
constants at the FE's best fit: the effect's signature ``s = V(magnitude) - V(off)``. Per
magnitude the constants are refitted to the data less the signature, linearised with their
Jacobian J and held by the prior (the box's uniform prior as a Gaussian of the same variance,
``P = diag(12 / (hi - lo)^2)``); what they absorb of the signature is ``delta = (J^T W J +
P)^-1 J^T W s`` (W = 1 / sigma^2).
Without P, four constants refitted to eight values go to the box's corners along the
directions the data leave to the prior. Then

- the data reject the magnitude when the chi-square after the refit rises by at least
  :data:`REJECT` (95 % of chi-square on 1 dof, a profile likelihood) over the refit without
  the effect;
- the constants would be at ``mean - delta`` (the posterior mean of the run's draws moved by
  what the constants absorbed of the signature).

The farthest magnitude the data do not reject is reported with the constants it moves outside
their reported 95 % intervals, and :func:`admitting` widens those intervals to hold what each
such effect would make of them. The ladder's rungs are coarse (15, 40 and 100 % of the way to
the box's far edge): where even the first is rejected, the magnitude at the boundary is
found between "off" and it, with the signature taken linear in the magnitude there (the
refit's chi-square rise is then a quadratic in it, solved for :data:`REJECT`). Why: an
Armstrong-Frederick back stress of C_k = 200 MPa (gamma_k 50) fitted at 1.01 noise sd with m
pulled from 0.100 to 0.075-0.088, while the first rung, a Prager C_k of 300 MPa, was rejected,
so nothing was said. Linearised: a shift is a direction and a size, clipped to the box (the
report says so). Only one-parameter candidates have a ladder; the others are not assessed
here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import stats

#: chi-square rise at which the data reject a magnitude (95 % point of chi-square on 1 dof)
REJECT = float(stats.chi2.ppf(0.95, 1))


@dataclass(frozen=True)
class Constants:
    """The calibrated constants as the calibration reported them.

    Attributes:
        names: ``(p,)`` their names; lower, upper: ``(p,)`` their prior box (physical units).
        draws: ``(N, p)`` posterior draws; intervals: name -> the reported 95 % interval
            (names missing are not judged).
    """

    names: list[str]
    lower: np.ndarray
    upper: np.ndarray
    draws: np.ndarray
    intervals: dict[str, tuple[float, float]]


def boundary_rung(r0: np.ndarray, s1: np.ndarray, refit: Any) -> float | None:
    """The share ``t`` in (0, 1) of the first rung's signature ``s1`` ``(n,)`` (um) at which
    the refit's chi-square rise reaches :data:`REJECT` (0.999 of it: kept as unrejected), the
    signature taken linear in the magnitude: with ``refit`` (residual -> (shift, chi2)) linear,
    ``rise(t) = chi2(r0 - t s1) - chi2(r0) = b t^2 - 2 a t``. None where the first rung is not
    rejected (``t`` would be >= 1)."""
    _, c0 = refit(r0)
    _, c1 = refit(r0 - s1)
    _, cm = refit(r0 + s1)
    b = 0.5 * (c1 + cm) - c0  # the quadratic's coefficients from three exact evaluations
    a = 0.25 * (cm - c1)
    if b <= 0.0:
        return None
    t = (a + np.sqrt(a * a + b * 0.999 * REJECT)) / b
    return float(t) if 0.0 < t < 1.0 else None


def cannot_rule_out(y: np.ndarray, v0: np.ndarray, j_theta: np.ndarray, sigma: float,
                    ladder: dict[str, tuple[np.ndarray, np.ndarray]], consts: Constants,
                    offs: dict[str, float] | None = None) -> list[dict]:
    """The one-parameter candidates whose unrejected magnitudes move a constant outside its
    reported interval.

    Args:
        y: ``(n,)`` data, um; v0: ``(n,)`` FE at the best fit, every candidate off, um;
        j_theta: ``(n, p)`` Jacobian of the outputs w.r.t. the calibrated constants there (um
            per unit); sigma: noise sd, um.
        ladder: effect -> ``(values (L,), V (L, n))``: its magnitudes (its own units,
            ascending from "off") and the FE there (um), the constants as for ``v0``.
        consts: the constants' names, box, posterior draws and reported intervals.
        offs: effect -> its "off" magnitude (its own units); where given and the first rung
            is rejected, a rung at the boundary between "off" and it
            (:func:`boundary_rung`).

    Returns:
        one dict per such effect, the largest shift (in interval widths) first: ``effect``,
        ``value`` (the farthest unrejected magnitude), ``chi2_rise`` there, ``moves`` (name ->
        ``[posterior mean, moved, clipped to the box]``, every constant), ``outside`` (the
        names moved outside their interval) and ``shift_widths`` (the largest move of those,
        in interval widths).
    """
    names, lower, upper = consts.names, consts.lower, consts.upper
    draws, intervals = consts.draws, consts.intervals
    w = 1.0 / sigma**2
    prec = j_theta.T @ j_theta * w + np.diag(12.0 / (upper - lower) ** 2)

    def refit(r: np.ndarray) -> tuple[np.ndarray, float]:
        d = np.linalg.solve(prec, j_theta.T @ r * w)
        res = r - j_theta @ d
        return d, float(res @ res) * w

    d0, chi0 = refit(y - v0)
    mu = draws.mean(0)
    out: list[dict[str, Any]] = []
    for eff, (vals, vl) in ladder.items():
        if offs is not None and eff in offs and len(vals):
            t = boundary_rung(y - v0, vl[0] - v0, refit)
            if t is not None:
                vals = np.concatenate([[offs[eff] + t * (vals[0] - offs[eff])], vals])
                vl = np.concatenate([(v0 + t * (vl[0] - v0))[None], vl])
        best = None
        for v, row in zip(vals, vl, strict=True):
            d, chi = refit(y - row)
            if chi - chi0 < REJECT:
                best = (float(v), chi - chi0, d0 - d)  # the farthest unrejected magnitude
        if best is None:
            continue
        v, rise, absorbed = best
        raw = mu - absorbed
        moved = np.clip(raw, lower, upper)
        outside = [nm for k, nm in enumerate(names) if nm in intervals
                   and not intervals[nm][0] <= moved[k] <= intervals[nm][1]]
        if not outside:
            continue
        size = max(abs(moved[names.index(nm)] - mu[names.index(nm)])
                   / max(intervals[nm][1] - intervals[nm][0], 1e-300) for nm in outside)
        out.append({"effect": eff, "value": v, "chi2_rise": round(rise, 3),
                    "moves": {nm: [float(mu[k]), float(moved[k]), bool(moved[k] != raw[k])]
                              for k, nm in enumerate(names)},
                    "outside": outside, "shift_widths": round(float(size), 3)})
    return sorted(out, key=lambda r: -r["shift_widths"])


def admitting(consts: Constants, found: list[dict]) -> dict[str, tuple[float, float]]:
    """The reported intervals widened to admit every effect the data cannot rule out.

    An effect at a magnitude the data do not reject moves the constants' posterior by what
    they absorb of its signature (``moves`` of a :func:`cannot_rule_out` entry, linear in the
    magnitude), so the interval it would leave is the reported one shifted by that move. The
    hull over "absent" and every magnitude up to the farthest unrejected one is the reported
    interval stretched by the move on its side: ``[min(lo, lo + d), max(hi, hi + d)]`` with
    ``d = moved - mean``, per effect, within the box. It is the interval a user can hold
    whether or not the effects are present: the data cannot tell, so it is as wide as their
    possible presence makes it (a union of credible sets, conservative against a posterior
    averaged over the models). Why: the Armstrong-Frederick back stress of the forms
    benchmark near the faces (C_k fitted as well at 2,000 MPa) left m at 0.051-0.066
    against a true 0.07, the shift to 0.070 named but not in any interval.

    Args:
        consts: the reported constants (:class:`Constants`); found: :func:`cannot_rule_out`'s
            entries (those without ``moves`` are skipped).
    Returns:
        name -> ``(lo, hi)`` for every constant with a reported interval, physical units
        (those no effect moves as reported); empty where ``found`` moves nothing.
    """
    moving = [r for r in found if "moves" in r]
    if not moving:
        return {}
    out = {}
    for k, nm in enumerate(consts.names):
        if nm not in consts.intervals:
            continue
        lo, hi = consts.intervals[nm]
        for r in moving:
            mean, moved, _ = r["moves"][nm]
            d = moved - mean
            lo, hi = min(lo, consts.intervals[nm][0] + d), max(hi, consts.intervals[nm][1] + d)
        out[nm] = (max(lo, float(consts.lower[k])), min(hi, float(consts.upper[k])))
    return out


def describe(r: dict, param: str, unit: str) -> str:
    """One sentence for a :func:`cannot_rule_out` entry; ``param``, ``unit``: the effect's
    parameter name and unit."""
    moves = "; ".join(
        f"{nm} {r['moves'][nm][0]:.4g} -> {r['moves'][nm][1]:.4g}"
        + (" (the box's edge)" if r["moves"][nm][2] else "")
        for nm in r["outside"])
    return (f"{r['effect']} at {param} = {r['value']:.4g}{(' ' + unit) if unit else ''} fits "
            f"the data as well (chi2 {r['chi2_rise']:+.1f} with the constants refitted; the "
            f"data reject from +{REJECT:.2f}) and would move {moves} (posterior mean, "
            f"linearised), outside {'their' if len(r['outside']) > 1 else 'its'} reported "
            f"95 % interval{'s' if len(r['outside']) > 1 else ''}: the intervals hold only if "
            f"{r['effect']} is absent")
