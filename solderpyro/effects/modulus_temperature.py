"""Temperature-dependent solder modulus: E(T) = E25 * exp(-k_E * (T - 25 degC)).

``E25`` is the configured solder modulus (32 GPa for Sn37Pb, seed Table III), ``k_E >= 0`` in
1/K (off: 0). Sn37Pb loses roughly a third of its modulus between 25 and 125 degC, i.e.
``k_E ~ 3.6e-3 /K`` (Darveaux's linear E = 32.0 - 0.088 T GPa gives E(125)/E(25) = 0.70). The
exponential form equals the linear E25 (1 - k_E (T - 25)) to first order in k_E (so the score
test at "off" is the same) and stays positive at any temperature, including the 183 degC of
the stress-free pre-history. The box reaches k_E = ln(10)/100 /K (E(125 degC) = E25 / 10):
beyond what Sn37Pb does, but it lets a large softening be tested (docs/effects.md). The modulus
enters the solder's elasticity in the return map (bulk and shear moduli) and the plane-stress
eps_zz predictor; Poisson's ratio and the bars' moduli stay constant (the bars' moduli change
by < 5 % over the cycle, and they are condensed once for the whole batch).
Seam: the solder's material law.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from solderpyro.effects.base import Effect
from solderpyro.params import Box

#: top of the default box: E(125 degC) = E25 / 10
K_MAX = math.log(10.0) / 100.0


@dataclass(frozen=True)
class ModulusTemperature(Effect):
    """Exponential softening of the solder modulus with temperature; parameter ``k_E`` (1/K).

    Attributes:
        T0_C: temperature at which the configured modulus holds, degC.
    """

    name = "modulus_temperature"
    seam = "material law (solder)"
    T0_C: float = 25.0

    def default_box(self) -> Box:
        return Box(("k_E",), (0.0,), (K_MAX,), units=("1/K",))

    @property
    def off(self) -> tuple[float, ...]:
        return (0.0,)

    def modulus(self, E: torch.Tensor, T: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """``E * exp(-k_E (T - T0))`` ``(b,)`` MPa."""
        return E * torch.exp(-q[:, 0] * (T - self.T0_C))


EFFECT = ModulusTemperature()
