"""Temperature histories and the deterministic time grid of the FE solve.

Times in s, temperatures in degC at this surface (the solver converts to K). A history is a
:class:`ThermalCycle`: knots given directly, or a measured profile read from a CSV file
(:func:`read_profile_csv`), simplified to fewer knots within a temperature tolerance
(:func:`simplify_profile`) and repeated for several cycles (:func:`repeat_cycle`).
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike


@dataclass(frozen=True)
class ThermalCycle:
    """Piecewise-linear temperature program through ``(times[i], temps_C[i])``.

    Uniform over the specimen in the baseline model. Effects that change the history (e.g.
    thermal lag) replace this object by another with the same ``__call__`` and ``breakpoints``.

    Attributes:
        times: ``(n_knot,)`` s, strictly increasing.
        temps_C: ``(n_knot,)`` degC.
        cycle_ends: s, the end of each repetition of a repeated profile (:func:`repeat_cycle`),
            each one a knot, the last one ``times[-1]``; per-cycle quantities are read at these
            marks. Default: ``(times[-1],)`` (one cycle).
    """

    times: tuple[float, ...]
    temps_C: tuple[float, ...]
    #: left out of the run store's hash while it is one cycle, so the hash of a one-cycle
    #: program is the same as before cycles could repeat (stored runs stay reusable)
    cycle_ends: tuple[float, ...] = field(default=(), metadata={
        "omit_in_hash": lambda c: tuple(c.cycle_ends) == (c.times[-1],)})

    def __post_init__(self) -> None:
        if len(self.times) != len(self.temps_C) or len(self.times) < 2:
            raise ValueError("cycle: times and temps_C must have the same length (>= 2)")
        if any(b <= a for a, b in zip(self.times[:-1], self.times[1:], strict=False)):
            raise ValueError(f"cycle: times must increase strictly, got {self.times}")
        if not self.cycle_ends:
            object.__setattr__(self, "cycle_ends", (self.times[-1],))
        ends = self.cycle_ends
        if (ends[-1] != self.times[-1] or any(t not in self.times for t in ends)
                or any(b <= a for a, b in zip(ends[:-1], ends[1:], strict=False))):
            raise ValueError(f"cycle: cycle_ends must be increasing knots ending at the last "
                             f"one ({self.times[-1]} s), got {ends}")

    def __call__(self, t: float) -> float:
        """Temperature in degC at time ``t`` (s)."""
        return float(np.interp(t, self.times, self.temps_C))

    @property
    def breakpoints(self) -> tuple[float, ...]:
        """The knots, s: every one is a point of the time grid (:func:`time_grid`)."""
        return self.times

    @property
    def end(self) -> float:
        """The end of the history, s."""
        return self.times[-1]

    @property
    def n_cycles(self) -> int:
        """Number of repetitions (``len(cycle_ends)``)."""
        return len(self.cycle_ends)


#: The reference case's cycle (docs/configuration.md): 25 -> 75 -> 100 -> 125 -> 25 degC,
#: 5 degC/min ramps, 30 min dwells.
REFERENCE_CYCLE = ThermalCycle(
    (0.0, 600.0, 2400.0, 2700.0, 4500.0, 4800.0, 6600.0, 7800.0),
    (25.0, 75.0, 75.0, 100.0, 100.0, 125.0, 125.0, 25.0),
)
SEED_TIMES = (600.0, 2700.0, 4800.0, 7800.0)
EXTENDED_TIMES = (600.0, 2400.0, 2700.0, 4500.0, 4800.0, 6600.0, 7800.0)


@dataclass(frozen=True)
class TimeStepping:
    """Time-grid controls.

    Attributes:
        dT_max: largest temperature change per step on ramps, K.
        dwell_dt0: first step after a change of the temperature rate, s (steps then grow).
        growth: ratio of consecutive steps within a segment.
        dt_max: largest step, s.
        dep_max: largest equivalent inelastic strain increment per step at any Gauss point;
            a member exceeding it sub-steps (per member, so batching never changes a result).
        max_depth: how many times a step may be halved for one member before it is reported failed.
        scheme: ``"sdirk2"`` (default: two-stage, L-stable, stiffly accurate, second order;
            each stage is a backward-Euler solve from a shifted start state) or ``"euler"``
            (backward Euler, first order).
        max_iter: Newton iterations per stage before the step counts as failed (it is halved).
        rtol: Newton tolerance on the residual, relative to the external + internal forces.
    """

    dT_max: float = 4.0
    dwell_dt0: float = 10.0
    growth: float = 1.5
    dt_max: float = 300.0
    dep_max: float = 1e-2
    max_depth: int = 10
    scheme: str = "sdirk2"
    max_iter: int = 30
    rtol: float = 1e-10

    def __post_init__(self) -> None:
        if self.scheme not in ("sdirk2", "euler"):
            raise ValueError(f"stepping.scheme must be 'sdirk2' or 'euler', got {self.scheme!r}")
        for k in ("dT_max", "dwell_dt0", "dt_max", "dep_max"):
            if not getattr(self, k) > 0:
                raise ValueError(f"stepping.{k} must be > 0, got {getattr(self, k)}")
        if not self.growth >= 1.0:
            raise ValueError(f"stepping.growth must be >= 1, got {self.growth}")


def time_grid(cycle: ThermalCycle, out_times: tuple[float, ...], ts: TimeStepping) -> np.ndarray:
    """Step end times ``(n_step + 1,)`` from 0, hitting every breakpoint and output time.

    Within each segment between consecutive knots the steps start at ``dwell_dt0`` and grow by
    ``growth`` up to ``min(dt_max, dT_max/|rate|)``; the grid depends on the cycle only, never on
    the parameters, so every batch member shares it.
    """
    for t in out_times:
        if not 0.0 < t <= cycle.end:
            raise ValueError(f"output time {t} s is outside the cycle (0, {cycle.end}] s")
    knots = np.unique(np.concatenate([cycle.breakpoints, out_times, [0.0]]))
    knots = knots[(knots >= 0) & (knots <= cycle.end)]
    out = [0.0]
    for a, b in zip(knots[:-1], knots[1:], strict=False):
        rate = abs(cycle(0.5 * (a + b)) - cycle(a)) / (0.5 * (b - a))
        cap = ts.dt_max if rate == 0 else min(ts.dt_max, ts.dT_max / rate)
        steps: list[float] = []
        h = min(ts.dwell_dt0, cap)
        while sum(steps) + h < (b - a) * (1 - 1e-9):
            steps.append(h)
            h = min(h * ts.growth, cap)
        w = np.array(steps + [h])  # sum >= b - a: scaling to fit only shrinks steps
        out += list(a + (b - a) * np.cumsum(w) / w.sum())
    return np.array(out)


#: the columns of a temperature-profile CSV file (:func:`read_profile_csv`)
PROFILE_COLUMNS = ("time_s", "temp_C")


def read_profile_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a measured temperature profile: a CSV file with a header naming the columns
    ``time_s`` (s) and ``temp_C`` (degC), in any order among others (ignored); blank lines and
    lines starting with ``#`` are skipped.

    Args:
        path: the file.
    Returns:
        ``(times (n,), temps_C (n,))``, times shifted so that the first row is at t = 0.
    Raises:
        FileNotFoundError: naming the file.
        ValueError: naming the line and column of a bad value (not a finite number, a time not
            after the previous row's), a missing column, or fewer than two rows.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"temperature profile not found: {path}")
    with path.open(newline="") as f:
        lines = [(n, ln) for n, ln in enumerate(f, 1) if ln.strip() and not ln.startswith("#")]
    if not lines:
        raise ValueError(f"{path}: empty (expected a header {','.join(PROFILE_COLUMNS)})")
    rows = list(csv.reader(ln for _, ln in lines))
    head = [c.strip() for c in rows[0]]
    missing = [c for c in PROFILE_COLUMNS if c not in head]
    if missing:
        raise ValueError(f"{path}: line {lines[0][0]}: the header {head} has no column "
                         f"{', '.join(missing)} (expected {','.join(PROFILE_COLUMNS)})")
    cols = [head.index(c) for c in PROFILE_COLUMNS]
    vals = np.empty((len(rows) - 1, 2))
    for k, (row, (n, _)) in enumerate(zip(rows[1:], lines[1:], strict=True)):
        for c, (name, i) in enumerate(zip(PROFILE_COLUMNS, cols, strict=True)):
            cell = row[i].strip() if i < len(row) else ""
            try:
                vals[k, c] = float(cell)
            except ValueError:
                vals[k, c] = math.nan
            if not math.isfinite(vals[k, c]):
                raise ValueError(f"{path}: line {n}, column {name}: {cell!r} is not a number")
        if k and vals[k, 0] <= vals[k - 1, 0]:
            raise ValueError(f"{path}: line {n}, column time_s: {vals[k, 0]:g} s is not after "
                             f"the previous row's {vals[k - 1, 0]:g} s")
    if len(vals) < 2:
        raise ValueError(f"{path}: {len(vals)} data row(s); a profile needs at least 2")
    return vals[:, 0] - vals[0, 0], vals[:, 1]


def simplify_profile(times: ArrayLike, temps_C: ArrayLike, tol_C: float) -> np.ndarray:
    """Knots of a piecewise-linear profile within ``tol_C`` of every sample
    (Ramer-Douglas-Peucker, with the temperature difference at a sample's time as the
    distance): a sample is kept only where the chord between the kept neighbours misses it by
    more than ``tol_C``. The first and last samples are always kept.

    Args:
        times: ``(n,)`` s, strictly increasing; temps_C: ``(n,)`` degC.
        tol_C: the largest temperature error, K (0 keeps every corner, drops only samples on
            straight lines).
    Returns:
        ``(n_knot,)`` sorted indices of the kept samples.
    """
    if tol_C < 0:
        raise ValueError(f"profile tolerance must be >= 0 K, got {tol_C}")
    t, T = np.asarray(times, float), np.asarray(temps_C, float)
    keep = np.zeros(len(t), bool)
    keep[[0, -1]] = True
    stack = [(0, len(t) - 1)]
    while stack:
        a, b = stack.pop()
        if b - a < 2:
            continue
        chord = T[a] + (T[b] - T[a]) * (t[a + 1:b] - t[a]) / (t[b] - t[a])
        err = np.abs(T[a + 1:b] - chord)
        k = int(np.argmax(err))
        if err[k] > tol_C * (1 + 1e-12) + 1e-12:
            m = a + 1 + k
            keep[m] = True
            stack += [(a, m), (m, b)]
    return np.nonzero(keep)[0]


def repeat_cycle(times: ArrayLike, temps_C: ArrayLike, n: int) -> ThermalCycle:
    """``n`` repetitions of one cycle ``(times, temps_C)`` (first and last temperature equal),
    back to back from ``times[0]``; the end of each is a knot (:attr:`ThermalCycle.cycle_ends`).

    Args:
        times: ``(n_knot,)`` s, strictly increasing; temps_C: ``(n_knot,)`` degC with
            ``temps_C[-1] == temps_C[0]``.
        n: number of cycles, >= 1.
    Returns:
        the :class:`ThermalCycle` of ``n * (n_knot - 1) + 1`` knots.
    Raises:
        ValueError: ``n < 1``, or the cycle does not end at its start temperature.
    """
    t, T = np.asarray(times, float), np.asarray(temps_C, float)
    if n < 1:
        raise ValueError(f"cycles must be >= 1, got {n}")
    if n > 1 and T[-1] != T[0]:
        raise ValueError(f"a repeated cycle must end at its start temperature, got "
                         f"{T[0]:g} -> {T[-1]:g} degC")
    period = t[-1] - t[0]
    tt = np.concatenate([t[:1]] + [t[1:] + k * period for k in range(n)])
    TT = np.concatenate([T[:1]] + [T[1:]] * n)
    ends = tuple(float(t[-1] + k * period) for k in range(n))
    return ThermalCycle(tuple(float(x) for x in tt), tuple(float(x) for x in TT), ends)
