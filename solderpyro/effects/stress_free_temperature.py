"""Residual stress from assembly: the specimen is stress free at T_sf >= 25 degC, not at 25 degC.

After reflow the joint solidifies and is stress free at some T_sf (at most the Sn37Pb eutectic,
183 degC), then cools to room temperature before the test. The effect simulates that
pre-history: from t = -D (``cooldown_s``) the temperature falls linearly from each member's
T_sf to the program's start temperature at t = 0; the solder creeps meanwhile. The Moire
reference image is taken at the start of the cycle, so V is reported relative to the state at
t = 0 (the FE reports ``V(t) - V(0)``).

The pre-history's time grid is fixed (shared by the batch; its steps respect ``dT_max`` for the
box's largest T_sf), so members with different T_sf share it. Off: T_sf = 25 degC (the
reference case's stress-free temperature; the pre-history is then a rest at 25 degC, which
changes nothing). With an elastic solder a T_sf shift changes nothing in V(t) - V(0) either
(superposition); with creep, the residual stress relaxes during the cycle and V changes.
Seam: the initial state.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from solderpyro.effects.base import Effect
from solderpyro.params import Box


@dataclass(frozen=True)
class StressFreeTemperature(Effect):
    """Stress-free temperature ``T_sf`` (degC) and a cool-down pre-history before t = 0.

    Attributes:
        cooldown_s: duration D of the cool-down from T_sf to the program's start, s (a cooling
            rate of ~5 K/min from the eutectic, as the cycle's ramps).
    """

    name = "stress_free_temperature"
    seam = "initial state"
    cooldown_s: float = 1800.0

    def __post_init__(self) -> None:
        if not self.cooldown_s > 0:
            raise ValueError(f"stress_free_temperature: cooldown_s must be > 0, "
                             f"got {self.cooldown_s}")

    def default_box(self) -> Box:
        return Box(("T_sf",), (25.0,), (183.0,), units=("degC",))

    @property
    def off(self) -> tuple[float, ...]:
        return (25.0,)

    def stress_free(self, T_ref: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """``T_sf`` ``(b,)`` degC (replaces the configured stress-free temperature)."""
        return q[:, 0]

    def pre_history(self) -> tuple[float, float] | None:
        b = self.default_box()  # not an override: the grid must not depend on the prior
        return self.cooldown_s, max(abs(b.upper[0] - self.off[0]), abs(b.lower[0] - self.off[0]))


EFFECT = StressFreeTemperature()
