"""Temperature histories and the deterministic time grid of the FE solve.

Times in s, temperatures in degC at this surface (the solver converts to K).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ThermalCycle:
    """Piecewise-linear temperature program through ``(times[i], temps_C[i])``.

    Uniform over the specimen in the baseline model. Effects that change the history (e.g.
    thermal lag) replace this object by another with the same ``__call__`` and ``breakpoints``.
    """

    times: tuple[float, ...]
    temps_C: tuple[float, ...]

    def __post_init__(self) -> None:
        if len(self.times) != len(self.temps_C) or len(self.times) < 2:
            raise ValueError("cycle: times and temps_C must have the same length (>= 2)")
        if any(b <= a for a, b in zip(self.times[:-1], self.times[1:], strict=False)):
            raise ValueError(f"cycle: times must increase strictly, got {self.times}")

    def __call__(self, t: float) -> float:
        """Temperature in degC at time ``t`` (s)."""
        return float(np.interp(t, self.times, self.temps_C))

    @property
    def breakpoints(self) -> tuple[float, ...]:
        return self.times

    @property
    def end(self) -> float:
        return self.times[-1]


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
