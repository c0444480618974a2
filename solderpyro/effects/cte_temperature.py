"""Temperature-dependent CTE of all three materials: alpha(T) = alpha25 * (1 + c_alpha (T - 25)).

One relative coefficient ``c_alpha`` (1/K, off: 0) for steel, solder and copper alike;
``alpha25`` is each material's configured CTE. Their CTEs rise by a few (steel, copper) to
~10-20 % (Sn37Pb) per 100 K; the box's upper value 3e-3 /K (+30 % per 100 K) is generous. The
free thermal strain is the integral from the stress-free temperature T_ref,

    eps_th = int_{T_ref}^{T} alpha = alpha25 * [(T - T_ref) + c_alpha/2 ((T-25)^2 - (T_ref-25)^2)],

added to the baseline ``alpha25 (T - T_ref)`` as the second term. It enters the solder update
and the condensed thermal loads and observation offsets of the bars.
Seam: the material laws (thermal strain).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from solderpyro.effects.base import Effect
from solderpyro.params import Box


@dataclass(frozen=True)
class CteTemperature(Effect):
    """Linear rise of every material's CTE with temperature; parameter ``c_alpha`` (1/K).

    Attributes:
        T0_C: temperature at which the configured CTEs hold, degC.
    """

    name = "cte_temperature"
    seam = "material laws (thermal strain)"
    transfers = True
    T0_C: float = 25.0

    def default_box(self) -> Box:
        return Box(("c_alpha",), (0.0,), (3e-3,), units=("1/K",))

    @property
    def off(self) -> tuple[float, ...]:
        return (0.0,)

    def thermal_strain(self, eps: torch.Tensor, alpha: float, T: torch.Tensor,
                       T_ref: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """``eps + alpha c/2 ((T-T0)^2 - (T_ref-T0)^2)`` ``(b,)``."""
        a, b = T - self.T0_C, T_ref - self.T0_C
        return eps + alpha * 0.5 * q[:, 0] * (a * a - b * b)


EFFECT = CteTemperature()
