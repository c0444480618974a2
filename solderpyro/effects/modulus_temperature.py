"""Temperature-dependent solder modulus: E(T) = E25 * (1 - k_E * (T - 25 degC)).

``E25`` is the configured solder modulus (32 GPa for Sn37Pb, seed Table III), ``k_E >= 0`` in
1/K (off: 0). Sn37Pb loses roughly a third of its modulus between 25 and 125 degC, i.e.
``k_E ~ 3e-3 /K`` (e.g. Darveaux's E = 32.0 - 0.088 T GPa gives 2.9e-3 /K). The modulus
enters the solder's elasticity in the return map (bulk and shear moduli) and the plane-stress
eps_zz predictor; Poisson's ratio and the bars' moduli stay constant (the bars' moduli change
by < 5 % over the cycle, and they are condensed once for the whole batch).
Seam: the solder's material law.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..params import Box
from .base import Effect


@dataclass(frozen=True)
class ModulusTemperature(Effect):
    """Linear softening of the solder modulus with temperature; parameter ``k_E`` (1/K).

    Attributes:
        T0_C: temperature at which the configured modulus holds, degC.
    """

    name = "modulus_temperature"
    seam = "material law (solder)"
    T0_C: float = 25.0

    def default_box(self) -> Box:
        return Box(("k_E",), (0.0,), (5e-3,), units=("1/K",))

    @property
    def off(self) -> tuple[float, ...]:
        return (0.0,)

    def modulus(self, E: torch.Tensor, T: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """``E * (1 - k_E (T - T0))`` ``(b,)`` MPa."""
        return E * (1.0 - q[:, 0] * (T - self.T0_C))


EFFECT = ModulusTemperature()
