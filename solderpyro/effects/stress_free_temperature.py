"""Residual stress from assembly: the specimen is stress free at T_sf >= 25 degC, not at 25 degC.

After reflow the joint solidifies and is stress free at some T_sf (at most the Sn37Pb eutectic,
183 degC), then cools to room temperature before the test. The effect simulates that
pre-history: each member cools linearly from its T_sf to the program's start temperature over
its own cool-down ``D`` (s), ending at t = 0; the solder creeps meanwhile. The Moire reference
image is taken at the start of the cycle, so V is reported relative to the state at t = 0 (the
FE reports ``V(t) - V(0)``).

How fast the assembly cooled is rarely known, and the data partly see it (a slower cool-down
lets more of the residual stress relax before the test: at the true constants a 1 K/min
cool-down from 150 degC and the 1,800 s one differ by 11 % of the effect). So the cool-down is a
parameter of the effect, a nuisance the data inform, on a log-scale box of 900-9,000 s (about
10 K/min to 1 K/min from 150 degC), rather than a fixed form the constants would absorb. Nor is
its course known: a controlled oven ramps at a constant rate, a joint left to cool in still air
cools fastest at first and slows as it nears the room (Newton's law). The shape
``cooldown_shape`` = p, a second nuisance on [1, 3] (off: 1), runs the member ``s ** p`` of
the way from the room to T_sf at the share ``s`` of its cool-down still to run: p = 1 the
constant rate, p = 3 three times the mean rate at first and none at the end (a Newton cool-down
over three time constants has 3.16 times its mean rate at first and 0.16 at the end).

The pre-history's time grid is shared by the batch (:class:`~solderpyro.effects.base.PreHistory`:
it spans the box's longest cool-down and resolves its fastest ramp for the box's largest T_sf
and shape: 393 steps at the default stepping, against 132 for constant rates only);
a member with a shorter cool-down rests at its T_sf first, which changes nothing. Off: T_sf =
25 degC (the reference case's stress-free temperature; the pre-history is then a rest at
25 degC, whatever the cool-down). With an elastic solder a T_sf shift changes nothing in
V(t) - V(0) either (superposition); with creep, the residual stress relaxes during the cycle
and V changes. Seam: the initial state.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from solderpyro.effects.base import Effect, PreHistory
from solderpyro.params import Box

#: the cool-down's box, s: about 10 K/min to 1 K/min from 150 degC to 25 degC
COOLDOWN_BOX = (900.0, 9000.0)
#: the cool-down where the effect is "off" (any value gives the baseline there): 5 K/min
#: from 175 degC, as the cycle's ramps
COOLDOWN_OFF = 1800.0
#: the cool-down shape's box: 1 a constant rate (off), 3 three times the mean rate at first
SHAPE_BOX = (1.0, 3.0)


@dataclass(frozen=True)
class StressFreeTemperature(Effect):
    """Stress-free temperature ``T_sf`` (degC), the cool-down ``cooldown`` (s) before t = 0 and
    its shape ``cooldown_shape`` (-)."""

    name = "stress_free_temperature"
    seam = "initial state"
    nuisance = ("cooldown", "cooldown_shape")

    def default_box(self) -> Box:
        return Box(("T_sf", "cooldown", "cooldown_shape"),
                   (25.0, COOLDOWN_BOX[0], SHAPE_BOX[0]), (183.0, COOLDOWN_BOX[1], SHAPE_BOX[1]),
                   log_scale=(False, True, False), units=("degC", "s", "-"))

    @property
    def off(self) -> tuple[float, ...]:
        return (25.0, COOLDOWN_OFF, SHAPE_BOX[0])

    def check(self, q: torch.Tensor) -> None:
        lo, hi = COOLDOWN_BOX
        c = q[:, 1]
        if bool(((c < lo * (1 - 1e-9)) | (c > hi * (1 + 1e-9))).any()):
            raise ValueError(f"stress_free_temperature: cooldown must be within [{lo:g}, "
                             f"{hi:g}] s (the pre-history's grid), got {c.min().item():g} to "
                             f"{c.max().item():g}")
        p = q[:, 2]
        if bool(((p < SHAPE_BOX[0]) | (p > SHAPE_BOX[1])).any()):
            raise ValueError(f"stress_free_temperature: cooldown_shape (1 a constant rate, 3 "
                             f"three times the mean rate at first) must be within "
                             f"[{SHAPE_BOX[0]:g}, {SHAPE_BOX[1]:g}] (the pre-history's grid), "
                             f"got {p.min().item():g} to {p.max().item():g}")

    def stress_free(self, T_ref: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """``T_sf`` ``(b,)`` degC (replaces the configured stress-free temperature)."""
        return q[:, 0]

    def cooldown(self, q: torch.Tensor) -> torch.Tensor:
        """``(b,)`` s."""
        return q[:, 1]

    def cooldown_shape(self, q: torch.Tensor) -> torch.Tensor | None:
        """``(b,)`` (-)."""
        return q[:, 2]

    def pre_history(self) -> PreHistory:
        b = self.default_box()  # not an override: the grid must not depend on the prior
        dT = max(abs(b.upper[0] - self.off[0]), abs(b.lower[0] - self.off[0]))
        return PreHistory(COOLDOWN_BOX[1], dT, COOLDOWN_BOX[0], SHAPE_BOX[1])


EFFECT = StressFreeTemperature()
