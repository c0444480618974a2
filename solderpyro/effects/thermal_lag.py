"""Thermal lag: the specimen temperature follows the chamber program with a first-order lag.

    dT/dt = (T_prog(t) - T) / tau,   T(0) = T_prog(0)     (tau >= 0 s, off: tau = 0)

Uniform over the specimen (a lumped heat capacity: copper and steel bars conduct fast compared
with the chamber's convection). On a linear segment of the program with rate ``r`` the lag
``e = T_prog - T`` solves ``de/dt = r - e/tau`` in closed form,

    e(t) = r*tau + (e_a - r*tau) * exp(-(t - t_a)/tau),

so ramps end ``~ r*tau`` below their target and dwells approach it exponentially. At
``tau = 0`` the exponential is replaced by its limit 0 (also in the derivative), so the
program is recovered exactly and ``de/dtau = r`` there (the one-sided derivative).
Seam: the temperature history (per batch member).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from solderpyro.effects.base import Effect
from solderpyro.fem.loading import ThermalCycle
from solderpyro.params import Box


def lag(cycle: ThermalCycle, t: float, tau: torch.Tensor) -> torch.Tensor:
    """Lag ``T_prog(t) - T(t)`` ``(b,)`` K of a first-order system behind the program.

    Args:
        cycle: the piecewise-linear program (degC, s); the system starts on it at ``times[0]``.
        t: time, s (clamped to the program's span).
        tau: ``(b,)`` time constants, s (>= 0; 0 means no lag).
    """
    e = torch.zeros_like(tau)
    pos = tau > 0
    safe = torch.where(pos, tau, torch.ones_like(tau))
    kn, Tk = cycle.times, cycle.temps_C
    for i in range(len(kn) - 1):
        ta, tb = kn[i], kn[i + 1]
        if t <= ta:
            break
        r = (Tk[i + 1] - Tk[i]) / (tb - ta)
        decay = torch.where(pos, torch.exp(-(min(t, tb) - ta) / safe), torch.zeros_like(tau))
        e = r * tau + (e - r * tau) * decay
    return e


@dataclass(frozen=True)
class ThermalLag(Effect):
    """First-order thermal lag of the specimen behind the program; parameter ``tau`` (s)."""

    name = "thermal_lag"
    seam = "temperature history"

    def default_box(self) -> Box:
        # a 9 mm thick steel/copper stack in a forced-convection chamber: tens of seconds to
        # a few minutes; 300 s leaves the 75 degC dwell start ~22 K short of its target
        return Box(("tau",), (0.0,), (300.0,), units=("s",))

    @property
    def off(self) -> tuple[float, ...]:
        return (0.0,)

    def check(self, q: torch.Tensor) -> None:
        if bool((q[:, 0] < 0).any()):
            raise ValueError(f"thermal_lag: tau must be >= 0 s, got {q[:, 0].min().item():g}")

    def temperature(self, T: torch.Tensor, t: float, cycle: ThermalCycle,
                    q: torch.Tensor) -> torch.Tensor:
        """``T - lag`` ``(b,)`` degC (``T`` is the program's value at ``t``)."""
        return T - lag(cycle, t, q[:, 0])


EFFECT = ThermalLag()
