"""Temperature-dependent solder modulus: a softening law whose form the data may inform.

    E(T) = E25 * (1 - n_E * k_E * (T - 25 degC)) ** (1 / n_E),   floored at R_MIN * E25

``E25`` is the configured solder modulus (32 GPa for Sn37Pb, seed Table III), ``k_E >= 0`` in
1/K sizes the softening (off: 0) and ``n_E`` in [0, 1] is its form: ``n_E = 0`` is the
exponential law ``E25 exp(-k_E (T - 25))`` (the limit of the power, the default), ``n_E = 1``
the linear law ``E25 (1 - k_E (T - 25))`` (Darveaux's E = 32.0 - 0.088 T GPa is linear; a
fitted exponential is as common). Whether a solder softens linearly or exponentially is rarely
known, and at a large softening the two differ by more than the data's noise (at k_E = 0.006 /K
the linear law's E(125 degC) is 0.40 E25 against the exponential's 0.55), so the form is a
nuisance parameter the data inform rather than a fixed choice the Anand constants would absorb.
Every member of the family has the same slope ``-k_E E25`` at 25 degC, so the score test at
"off" (k_E = 0, where n_E changes nothing) is the same for all of them.

Sn37Pb loses roughly a third of its modulus between 25 and 125 degC (``k_E ~ 3.6e-3 /K``). The
box reaches k_E = ln(10)/100 /K (exponential: E(125 degC) = E25 / 10): beyond what Sn37Pb does,
but it lets a large softening be tested (docs/effects.md). The linear form would reach zero
inside the cycle there, so the modulus is floored at ``R_MIN`` = 1 % of E25 (the exponential at
the box's top stays above 2.6 % at 183 degC, the pre-history's highest temperature, so the
floor never touches it). The modulus enters the solder's elasticity in the return map (bulk and
shear moduli) and the plane-stress eps_zz predictor; Poisson's ratio and the bars' moduli stay
constant (the bars' moduli change by < 5 % over the cycle, and they are condensed once for the
whole batch).
Seam: the solder's material law.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from solderpyro.effects.base import Effect
from solderpyro.params import Box

#: top of the default box of k_E: exponential E(125 degC) = E25 / 10
K_MAX = math.log(10.0) / 100.0
#: the modulus never falls below this fraction of E25 (the linear form would reach zero)
R_MIN = 0.01
#: below this n_E the power is evaluated by its series about the exponential (the dropped term
#: of the exponent is n_E^2 u^3 / 3, u = k_E (T - 25) <= 3.64 in the box: < 1.7e-11 relative)
_N_SERIES = 1e-6


def softening(u: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """``E(T) / E25`` ``(b,)`` for ``u = k_E (T - 25)`` ``(b,)`` and the form ``n = n_E`` ``(b,)``.

    ``(1 - n u) ** (1 / n)`` computed as ``exp(log1p(-n u) / n)`` (log1p keeps the digits of a
    small ``n u``), floored at :data:`R_MIN`;
    for ``n`` below 1e-6 its series ``exp(-u - n u^2 / 2)``, so the exponential law ``n = 0``
    is exact and the derivative in ``n`` is smooth through 0 (``-u^2 / 2`` times the ratio).
    """
    small = n < _N_SERIES
    ns = torch.where(small, torch.ones_like(n), n)
    w = torch.maximum(-ns * u, torch.expm1(ns * math.log(R_MIN)))  # 1 + w floored at R_MIN^n
    log_r = torch.where(small, -u - n * u * u / 2.0, torch.log1p(w) / ns)
    return torch.exp(torch.clamp(log_r, min=math.log(R_MIN)))


@dataclass(frozen=True)
class ModulusTemperature(Effect):
    """Softening of the solder modulus with temperature: size ``k_E`` (1/K), form ``n_E`` (-).

    Attributes:
        T0_C: temperature at which the configured modulus holds, degC.
    """

    name = "modulus_temperature"
    seam = "material law (solder)"
    transfers = True
    nuisance = ("n_E",)
    T0_C: float = 25.0

    def default_box(self) -> Box:
        return Box(("k_E", "n_E"), (0.0, 0.0), (K_MAX, 1.0), units=("1/K", "-"))

    @property
    def off(self) -> tuple[float, ...]:
        return (0.0, 0.0)

    def check(self, q: torch.Tensor) -> None:
        n = q[:, 1]
        if bool(((n < 0) | (n > 1)).any()):
            raise ValueError(f"modulus_temperature: n_E (the law's form: 0 exponential, 1 "
                             f"linear) must be within [0, 1], got {n.min().item():g} to "
                             f"{n.max().item():g}")

    def modulus(self, E: torch.Tensor, T: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """``E * softening(k_E (T - T0), n_E)`` ``(b,)`` MPa."""
        return E * softening(q[:, 0] * (T - self.T0_C), q[:, 1])


EFFECT = ModulusTemperature()
