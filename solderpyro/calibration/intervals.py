"""The reported 95 % credible interval of a parameter: the central one, or one that starts at a
face of the prior box when the posterior piles against that face.

The equal-tailed interval ``[q2.5, q97.5]`` (the seed paper's Table V layout) of a posterior that
is densest at a face of the box never holds the face itself: its lower end is the 2.5 % point,
above the face for any continuous posterior. A truth at the face (a copper that yields at the
lowest stress the band model allows, say) then lies outside every central interval, however much
data there is, and the report says the data exclude a value that they favour.

So solderpyro reports, per parameter, the central interval ``[q2.5, q97.5]`` unless the
posterior piles against a face of the box: unless its densest half (the narrowest interval that
holds half of the draws, on the box's own scale: logarithmic for a log-scale parameter, where
the prior is uniform) reaches the face (within ``TIE`` of the narrowest width: a marginal flat
at the face ties its first windows), and is clearly narrower (by ``MARGIN``) than its central
half ``[q25, q75]``. Then the density is largest at the face, and the reported interval starts
there and holds the same share ``level``: ``[lower, q95]`` or ``[q5, upper]``, the highest-density
interval of a marginal that falls from the face (ArviZ's ``hdi`` of the draws is the same
interval but stops at the smallest draw, never the face itself).

Why not the shortest 95 % interval everywhere (the HDI): where a ridge only runs toward a face
(Q/R toward 13,000 K in the copper recalibration, its mode at 11,700), the HDI moves the lower
end up by the whole 2.5-5 % tail (10,368 -> 10,553 K there, truth 10,586) though the face is not
where the posterior is densest; the central interval stays the seed's Table V layout wherever
no face is the mode.

Every candidate holds the share ``level`` of the posterior, so whichever is chosen the reported
interval is a ``level`` credible set and truths drawn from the prior lie inside it at the rate
``level`` (tests/unit/calibration/test_intervals.py checks that, and the agreement with ArviZ's
HDI at a face).

Units: each parameter's own (the box's).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from solderpyro.params import Box

#: the reported intervals' posterior probability
LEVEL = 0.95
#: the share of the posterior whose narrowest interval must reach a face for the interval to
#: start there (the densest half)
DENSE = 0.5
#: ... and by how much that narrowest interval must be narrower than the central one of the
#: same share (a flat marginal, all of whose windows are alike, keeps the central interval)
MARGIN = 0.05
#: probability grid of the windows searched for the densest one
_GRID = 101
#: a window at a face counts as the densest when it is within this share of the narrowest: a
#: marginal flat at the face ties its first windows, and which of them Monte Carlo noise makes
#: the narrowest is chance (the copper field case: 15.00-15.66 MPa, the window at 0.5 %
#: narrower than the face's by 0.07 %, so without the tie the central interval missed the
#: true 15 MPa by 0.008, where another set of draws of the same posterior started at the face)
TIE = 0.02
#: the summary columns of the reported interval (``interval`` says which kind)
INTERVAL_COLUMNS = ("lo95", "hi95", "interval")
CENTRAL, LOWER_FACE, UPPER_FACE = "central", "lower face", "upper face"
#: the kind of an interval widened for model-form error where a misfit remains
#: (:mod:`solderpyro.pipeline.model_form`)
MODEL_FORM = "model form"
#: the kind of an interval widened to the draws the likelihood does not reject
#: (:func:`likelihood_hull`)
LIKELIHOOD = "likelihood"
#: a draw is not rejected while its log-likelihood is within this of the best draw's (half the
#: 95 % point of chi-square on 1 dof: the profile-likelihood interval's bound)
LIKELIHOOD_DROP = 0.5 * 3.841458820694124
#: an interval is widened to the likelihood's range only where that adds at least this share
#: of its width (in a posterior close to normal the unrejected draws stay inside the central
#: interval: a draw at 1.96 sd in one parameter is already 1.92 below the best)
LIKELIHOOD_GAIN = 0.05
#: the kind of an interval widened to the FE's profile-likelihood interval where neither
#: posterior is reliable (:func:`profile_hull`)
PROFILE = "profile"
#: what each widened kind says after an interval in the report and the run index
WIDENED = {MODEL_FORM: "widened for model-form error",
           LIKELIHOOD: "widened to the likelihood's range",
           PROFILE: "widened to the FE's profile-likelihood interval"}


@dataclass(frozen=True)
class Interval:
    """One parameter's reported credible interval.

    Attributes:
        lo, hi: its ends, the parameter's units.
        kind: ``"central"``, ``"lower face"`` (``lo`` is the box's lower bound) or
            ``"upper face"`` (``hi`` is the box's upper bound).
    """

    lo: float
    hi: float
    kind: str

    def holds(self, value: float) -> bool:
        """Whether ``value`` (the parameter's units) lies in ``[lo, hi]``."""
        return self.lo <= value <= self.hi


def weighted_quantiles(x: np.ndarray, w: np.ndarray, probs: tuple[float, ...]) -> list[float]:
    """Quantiles of ``x (n,)`` under weights ``w (n,)`` (normalized inside; midpoint rule with
    linear interpolation, so equal weights give the sample quantiles' usual values).

    Returns one value per entry of ``probs`` (each in [0, 1]), in ``x``'s units.
    """
    x, w = np.asarray(x, float), np.asarray(w, float)
    o = np.argsort(x)
    cw = np.cumsum(w[o])
    cw = (cw - 0.5 * w[o]) / cw[-1]
    return [float(np.interp(p, cw, x[o])) for p in probs]


def _quantiles(x: np.ndarray, probs: Sequence[float], weights: np.ndarray | None
               ) -> np.ndarray:
    if weights is None:
        return np.quantile(x, probs)
    return np.asarray(weighted_quantiles(x, weights, tuple(probs)), float)


def credible_interval(x: np.ndarray, lower: float | None = None, upper: float | None = None,
                      log_scale: bool = False, level: float = LEVEL,
                      weights: np.ndarray | None = None) -> Interval:
    """The reported ``level`` interval of ``x``: central, or from a face the posterior piles
    against (the module docstring says when).

    Args:
        x: ``(n,)`` posterior draws of one parameter, its units (all inside
            ``[lower, upper]``).
        lower, upper: the prior box's bounds (None: no face on that side, e.g. a noise sd).
        log_scale: the densest window is sought on ``log x`` (the box's own scale for a
            log-scale parameter; needs ``lower > 0``).
        level: the intervals' posterior probability, in (0, 1).
        weights: ``(n,)`` normalized importance weights of ``x`` (None: equal).
    Returns:
        :class:`Interval`.
    Raises:
        ValueError: for an empty ``x``, a ``level`` outside (0, 1), draws outside the bounds,
            or ``log_scale`` with a non-positive lower bound.
    """
    x = np.asarray(x, float).reshape(-1)
    if x.size == 0:
        raise ValueError("credible_interval: no draws")
    if not 0.0 < level < 1.0:
        raise ValueError(f"credible_interval: level must be in (0, 1), got {level}")
    if log_scale and lower is not None and lower <= 0:
        raise ValueError(f"credible_interval: log_scale needs lower > 0, got {lower}")
    tol = 1e-9 * max(1.0, float(np.abs(x).max()))
    if (lower is not None and x.min() < lower - tol) or (upper is not None
                                                        and x.max() > upper + tol):
        raise ValueError(f"credible_interval: draws span [{x.min():g}, {x.max():g}], outside "
                         f"the box [{lower}, {upper}]")
    a = (1.0 - level) / 2.0
    f = np.log if log_scale else (lambda v: v)
    p = np.linspace(0.0, 1.0 - DENSE, _GRID)
    # one pass over the sorted draws: the windows' ends, then the candidate intervals' ends
    qs = _quantiles(x, (*p, *(p + DENSE), a, 1.0 - a, level, 1.0 - level), weights)
    q = f(qs[:2 * _GRID])
    width = q[_GRID:] - q[:_GRID]  # (grid,) widths of the windows holding DENSE
    q_lo, q_hi, q_a, q_b = qs[2 * _GRID:]
    best = float(width.min())
    dense = best < (1.0 - MARGIN) * width[_GRID // 2]  # denser than the central window
    at_lo = dense and lower is not None and width[0] <= (1.0 + TIE) * best
    at_hi = dense and upper is not None and width[-1] <= (1.0 + TIE) * best
    if at_lo and lower is not None and (not at_hi or width[0] <= width[-1]):
        return Interval(float(lower), float(q_a), LOWER_FACE)
    if at_hi and upper is not None:
        return Interval(float(q_b), float(upper), UPPER_FACE)
    return Interval(float(q_lo), float(q_hi), CENTRAL)


def with_intervals(rows: Sequence[dict], theta: np.ndarray, box: Box,
                   weights: np.ndarray | None = None, level: float = LEVEL) -> list[dict]:
    """Summary rows with the reported interval added (``lo95``, ``hi95``, ``interval``).

    Args:
        rows: summary rows (``parameter``, ``q2.5``, ``q97.5``, ...); a parameter not in the
            box (the noise sd) gets its central interval ``[q2.5, q97.5]``.
        theta: ``(n, dim)`` posterior draws in the box's column order, physical units.
        box: :class:`solderpyro.params.Box` (names, lower, upper, log_scale).
        weights: ``(n,)`` normalized weights of ``theta`` (None: equal).
    Returns:
        new rows (the input rows are not changed).
    """
    names = list(box.names)
    theta = np.asarray(theta, float)
    if theta.ndim != 2 or theta.shape[1] != len(names):
        raise ValueError(f"with_intervals: theta has shape {theta.shape}, the box "
                         f"{len(names)} parameters {names}")
    out = []
    for r in rows:
        nm = r["parameter"]
        if nm in names:
            k = names.index(nm)
            iv = credible_interval(theta[:, k], box.lower[k], box.upper[k],
                                   bool(box.log_scale[k]), level, weights)
        else:
            iv = Interval(float(r["q2.5"]), float(r["q97.5"]), CENTRAL)
        out.append({**r, "lo95": iv.lo, "hi95": iv.hi, "interval": iv.kind})
    return out


def with_monte_carlo_error(rows: Sequence[dict], theta: np.ndarray, weights: np.ndarray,
                           box: Box, level: float = LEVEL) -> list[dict]:
    """Summary rows whose interval ends, read off importance-weighted draws, are moved outward
    by their Monte Carlo standard error.

    An importance sampler's interval end rests on the few effective samples in its tail: at a
    Kish ESS of 50, about one effective sample lies beyond a 2.5 % point. The end's Monte Carlo
    standard error is estimated as ArviZ's ``mcse(method="quantile")`` does (Vehtari et al.
    2021, the end's probability ``p`` moved by the binomial error ``d = sqrt(p (1 - p) / ESS)``
    of the empirical CDF there): half the spread between the weighted quantiles at ``p - d``
    and ``p + d``. Each end the draws estimate (not a face of the box) is moved out by that
    much, within the box; the reported interval then holds the exact ``level`` interval's end
    with probability about 84 % per side rather than 50 %. A normal marginal's interval widens
    by 28 % at an ESS of 50, 15 % at 100 and 4 % at 1,000. Why: the forms benchmark's moderate
    residual stress (FE-exact posterior, ESS 52) reported Q/R, xi and m 0.6-1.3 % inside of
    their true values.

    Args:
        rows: summary rows with ``lo95``, ``hi95``, ``interval`` (:func:`with_intervals`
            with the same ``weights``).
        theta: ``(n, dim)`` the weighted draws in the box's column order, physical units.
        weights: ``(n,)`` their normalized importance weights (their Kish ESS is used).
        box: the draws' box (names, lower, upper).
        level: the intervals' posterior probability.
    Returns:
        new rows (the input rows are not changed); parameters not in the box, and intervals
        of another kind than central or at a face, as they were.
    """
    theta, w = np.asarray(theta, float), np.asarray(weights, float).reshape(-1)
    names = list(box.names)
    if theta.ndim != 2 or theta.shape != (w.size, len(names)):
        raise ValueError(f"with_monte_carlo_error: theta has shape {theta.shape}, weights "
                         f"{w.shape}; expected (n, {len(names)}) for {names} and (n,)")
    if not (np.all(w >= 0) and w.sum() > 0):
        raise ValueError("with_monte_carlo_error: weights must be non-negative, not all zero")
    w = w / w.sum()
    ess = 1.0 / float(w @ w)
    a = (1.0 - level) / 2.0
    # the probabilities of each kind's ends: (lower end, upper end), None at a face
    ends = {CENTRAL: (a, 1.0 - a), LOWER_FACE: (None, level), UPPER_FACE: (1.0 - level, None)}
    out = []
    for r in rows:
        nm, kind = r["parameter"], r.get("interval")
        if nm not in names or kind not in ends:
            out.append(dict(r))
            continue
        k = names.index(nm)
        lo, hi = float(r["lo95"]), float(r["hi95"])
        moved = []
        for p, end, sign in zip(ends[kind], (lo, hi), (-1.0, 1.0), strict=True):
            if p is None:
                moved.append(end)
                continue
            d = np.sqrt(p * (1.0 - p) / ess)
            q_lo, q_hi = weighted_quantiles(theta[:, k], w, (max(p - d, 0.0), min(p + d, 1.0)))
            moved.append(end + sign * 0.5 * (q_hi - q_lo))
        out.append({**r, "lo95": max(moved[0], float(box.lower[k])),
                    "hi95": min(moved[1], float(box.upper[k]))})
    return out


def likelihood_hull(rows: Sequence[dict], theta: np.ndarray, loglik: np.ndarray, box: Box
                    ) -> list[dict]:
    """Summary rows whose reported interval also holds every draw the likelihood does not
    reject: the hull of the credible interval and the range of the draws whose
    log-likelihood is within :data:`LIKELIHOOD_DROP` of the best draw's, where that widens it
    by at least :data:`LIKELIHOOD_GAIN` of its width (kind :data:`LIKELIHOOD`).

    Why: along a ridge the data leave open (s0, Q/R and xi trade off), the prior box's volume
    decides where a credible interval ends, not the data. The draws' range is an inner bound of
    the profile-likelihood interval (a draw's log-likelihood is at most the profile's at its
    value), so the hull is at most as wide as the credible interval and that profile interval
    together, and in a posterior close to normal it is the credible interval. Measured on the
    clean interior-constants field data of the forms benchmark (surrogate posterior, 1,000
    draws): xi 1.138-2.369 widens to 1.069-2.369; s0 stays 10.30-16.77 MPa against a true 10,
    where the surrogate's own profile (the other constants and sigma optimized) is 2.16 below
    its best, outside the profile interval too.

    Args:
        rows: summary rows with ``lo95``, ``hi95``, ``interval`` (:func:`with_intervals`).
        theta: ``(k, dim)`` posterior draws in the box's column order, physical units.
        loglik: ``(k,)`` the data's joint log-likelihood at each draw, nats.
        box: the draws' box (names).
    Returns:
        new rows (the input rows are not changed); parameters not in the box as they were.
    """
    theta, loglik = np.asarray(theta, float), np.asarray(loglik, float).reshape(-1)
    names = list(box.names)
    if theta.ndim != 2 or theta.shape != (loglik.size, len(names)):
        raise ValueError(f"likelihood_hull: theta has shape {theta.shape}, loglik "
                         f"{loglik.shape}; expected (k, {len(names)}) for {names} and (k,)")
    ok = np.isfinite(loglik)
    if not ok.any():
        raise ValueError("likelihood_hull: no finite log-likelihood")
    keep = theta[ok][loglik[ok] >= loglik[ok].max() - LIKELIHOOD_DROP]
    out = []
    for r in rows:
        nm = r["parameter"]
        if nm not in names:
            out.append(dict(r))
            continue
        k = names.index(nm)
        out.append(_hull(r, float(keep[:, k].min()), float(keep[:, k].max()), LIKELIHOOD))
    return out


def _hull(row: dict, lo: float, hi: float, kind: str) -> dict:
    """A copy of summary row ``row`` whose reported interval is widened to hold ``[lo, hi]``
    (the parameter's units) as kind ``kind``, where that adds at least
    :data:`LIKELIHOOD_GAIN` of its width; else a plain copy."""
    r_lo, r_hi = float(row["lo95"]), float(row["hi95"])
    a, b = min(r_lo, lo), max(r_hi, hi)
    if (r_lo - a) + (b - r_hi) >= LIKELIHOOD_GAIN * (r_hi - r_lo):
        return {**row, "lo95": a, "hi95": b, "interval": kind}
    return dict(row)


def profile_hull(rows: Sequence[dict], profiles: Mapping[str, tuple[float, float]]
                 ) -> list[dict]:
    """Summary rows whose reported interval also holds the FE's profile-likelihood interval
    of the same parameter: the hull of the two where the profile widens it by at least
    :data:`LIKELIHOOD_GAIN` of its width (kind :data:`PROFILE`).

    Why: where the FE-exact posterior's weights are not reliable, the reported intervals are
    the surrogate's, and the profile intervals are the only ones the FE computed itself. On
    the forms benchmark's linear modulus at the seed's constants (budget spent, ESS below 50)
    the surrogate's s0 13.6-24.3 MPa and k_E 0.00834-0.01070 /K missed the true 12.92 and
    0.00806, and the FE's profiles (11.2-25, 0.00802-0.01054) held both. The hull, not the
    profile alone, because an interval widened for model-form error or to the likelihood's
    range already admits what the profile's fixed noise sd does not.

    Args:
        rows: summary rows with ``lo95``, ``hi95``, ``interval`` (:func:`with_intervals`).
        profiles: ``{parameter: (lower, upper)}`` the profile intervals, physical units.
    Returns:
        new rows (the input rows are not changed); parameters without a profile as they were.
    """
    out = []
    for r in rows:
        pr = profiles.get(r["parameter"])
        if pr is None or not all(np.isfinite(pr)):
            out.append(dict(r))
        else:
            out.append(_hull(r, float(pr[0]), float(pr[1]), PROFILE))
    return out


def reported_interval(row: dict) -> tuple[float, float]:
    """A summary row's reported 95 % interval: ``(lo95, hi95)`` where the row has them (runs
    since the face-anchored intervals), else the central ``(q2.5, q97.5)``."""
    if row.get("lo95") not in (None, ""):
        return float(row["lo95"]), float(row["hi95"])
    return float(row["q2.5"]), float(row["q97.5"])
