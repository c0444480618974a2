"""The reported 95 % credible interval of a parameter: the central one, or one that starts at a
face of the prior box when the posterior piles against that face.

The equal-tailed interval ``[q2.5, q97.5]`` (the seed paper's Table V layout) of a posterior that
is densest at a face of the box never holds the face itself: its lower end is the 2.5 % point,
above the face for any continuous posterior. A truth at the face (a copper that yields at the
lowest stress the band model allows, say) then lies outside every central interval, however much
data there is, and the report says the data exclude a value that they favour.

So solderpyro reports, per parameter, the *shortest* of three intervals that each hold the
share ``level`` of the posterior, measured on the box's own scale (logarithmic for a log-scale
parameter, as the prior is uniform there):

- central: ``[q_(1-level)/2, q_(1+level)/2]``;
- at the lower face: ``[lower, q_level]``;
- at the upper face: ``[q_(1-level), upper]``.

For a marginal whose density falls from a face this is the highest-density interval, snapped to
the face (ArviZ's ``hdi`` over draws starts at the smallest draw, never at the face itself); for
a marginal away from the faces it is the central interval, as before. Every candidate holds the
share ``level`` of the posterior, so whichever is chosen the reported interval is a ``level``
credible set and truths drawn from the prior lie inside it at the rate ``level`` (tests/unit/
test_intervals.py checks both, and the agreement with ArviZ's HDI at a face).

Units: each parameter's own (the box's).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from solderpyro.params import Box

#: the reported intervals' posterior probability
LEVEL = 0.95
#: the summary columns of the reported interval (``interval`` says which kind)
INTERVAL_COLUMNS = ("lo95", "hi95", "interval")
CENTRAL, LOWER_FACE, UPPER_FACE = "central", "lower face", "upper face"


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


def _quantiles(x: np.ndarray, probs: Sequence[float], weights: np.ndarray | None
               ) -> np.ndarray:
    if weights is None:
        return np.quantile(x, probs)
    from solderpyro.exact import weighted_quantiles

    return np.asarray(weighted_quantiles(x, weights, tuple(probs)), float)


def credible_interval(x: np.ndarray, lower: float | None = None, upper: float | None = None,
                      log_scale: bool = False, level: float = LEVEL,
                      weights: np.ndarray | None = None) -> Interval:
    """The shortest of the central and the two face-anchored ``level`` intervals of ``x``.

    Args:
        x: ``(n,)`` posterior draws of one parameter, its units (all inside
            ``[lower, upper]``).
        lower, upper: the prior box's bounds (None: no face on that side, e.g. a noise sd).
        log_scale: widths compared on ``log x`` (the box's own scale for a log-scale
            parameter; needs ``lower > 0``).
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
    q_lo, q_hi, q_a, q_b = _quantiles(x, (a, 1.0 - a, level, 1.0 - level), weights)
    f = np.log if log_scale else (lambda v: v)
    cands = [(float(f(q_hi) - f(q_lo)), Interval(float(q_lo), float(q_hi), CENTRAL))]
    if lower is not None:
        cands.append((float(f(q_a) - f(lower)), Interval(float(lower), float(q_a), LOWER_FACE)))
    if upper is not None:
        cands.append((float(f(upper) - f(q_b)), Interval(float(q_b), float(upper), UPPER_FACE)))
    # ties (a flat marginal) keep the central interval: it comes first
    return min(cands, key=lambda c: c[0])[1]


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


def reported_interval(row: dict) -> tuple[float, float]:
    """A summary row's reported 95 % interval: ``(lo95, hi95)`` where the row has them (runs
    since the face-anchored intervals), else the central ``(q2.5, q97.5)``."""
    if row.get("lo95") not in (None, ""):
        return float(row["lo95"]), float(row["hi95"])
    return float(row["q2.5"]), float(row["q97.5"])
