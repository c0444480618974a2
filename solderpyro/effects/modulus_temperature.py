"""Temperature-dependent solder modulus: a softening law whose form the data may inform.

    E(T) = E25 * (r_E + (1 - r_E) * g(k_E (T - 25 degC) / (1 - r_E), n_E)),
    g(v, n) = (1 - n v) ** (1 / n)   (floored at 0)

``E25`` is the configured solder modulus (32 GPa for Sn37Pb, seed Table III), ``k_E >= 0`` in
1/K sizes the softening (off: 0), and two form parameters say how it proceeds:

- ``n_E`` in [0, 2], the law's curvature: ``n_E = 0`` is the exponential ``exp(-v)`` (the limit
  of the power, the default), ``n_E = 1`` the linear law ``1 - v`` (Darveaux's
  E = 32.0 - 0.088 T GPa is linear; a fitted exponential is as common), ``n_E = 2`` a softening
  that quickens as the temperature rises (``sqrt(1 - 2 v)``, as a solder's modulus does
  towards its melting point). The linear law lies inside the box, so data made with it are
  not fitted against a face.
- ``r_E`` in [0.01, 0.5], the plateau: the share of E25 the modulus levels off at where the
  law would take it lower (the exponential approaches it, the linear law and the quickening
  ones reach it at a finite temperature and stay there). Its default 0.01 only keeps the
  modulus positive; a large softening that levels off inside the cycle makes the data see it
  (a linear law floored at 5 % of E25 against one floored at 1 % changes the Moire field by
  20 noise sd RMS at k_E = 0.0115 /K).

Whether a solder softens linearly or exponentially, and where it stops, is rarely known, and
at a large softening the members differ by more than the data's noise (at k_E = 0.006 /K the
linear law's E(125 degC) is 0.40 E25 against the exponential's 0.55), so the form is a pair of
nuisance parameters the data inform rather than a fixed choice the Anand constants would
absorb. Every member has the same slope ``-k_E E25`` at 25 degC, so the score test at "off"
(k_E = 0, where the form changes nothing) is the same for all of them.

Sn37Pb loses roughly a third of its modulus between 25 and 125 degC (``k_E ~ 3.6e-3 /K``). The
box reaches k_E = ln(10)/100 /K (exponential at the default plateau: E(125 degC) close to
E25 / 10): beyond what Sn37Pb does, but it lets a large softening be tested
(docs/effects.md). The modulus enters the solder's elasticity in the return map (bulk and shear
moduli) and the plane-stress eps_zz predictor; Poisson's ratio and the bars' moduli stay
constant (the bars' moduli change by < 5 % over the cycle, and they are condensed once for the
whole batch).
Seam: the solder's material law.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from solderpyro.effects.base import Effect
from solderpyro.effects.power import log_power
from solderpyro.params import Box

#: top of the default box of k_E: exponential E(125 degC) = E25 / 10 (without a plateau)
K_MAX = math.log(10.0) / 100.0
#: the lowest plateau, a share of E25 (the default: the modulus stays positive)
R_MIN = 0.01
#: the highest plateau of the default box
R_MAX = 0.5
#: the curvature's box: 0 exponential, 1 linear, 2 quickening
N_MAX = 2.0


def softening(u: torch.Tensor, n: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """``E(T) / E25`` ``(b,)`` for ``u = k_E (T - 25)`` ``(b,)``, the curvature ``n = n_E``
    ``(b,)`` in [0, 2] and the plateau ``r = r_E`` ``(b,)`` in (0, 1).

    ``1 + (1 - r) (g - 1)`` with ``v = u / (1 - r)`` and ``g = (1 - n v) ** (1 / n)``, which is
    ``r + (1 - r) g`` written so that ``v = 0`` gives 1 exactly and the derivatives in ``n`` and
    ``r`` vanish there exactly; ``g - 1`` is ``expm1`` of the power family's logarithm
    (:func:`~solderpyro.effects.power.log_power` at ``z = -v``: the exponential ``n = 0``
    exact, the derivative in ``n`` smooth through 0), and ``g = 0`` (the plateau exactly) where
    ``n v >= 1``. The slope at 25 degC is ``-1`` per unit ``u`` for every ``n`` and ``r``.
    """
    v = u / (1.0 - r)
    reached = n * v >= 1.0  # the law has reached zero: the modulus is the plateau
    log_g = log_power(torch.where(reached, torch.zeros_like(v), -v), n)
    g_minus_1 = torch.where(reached, -torch.ones_like(v), torch.expm1(log_g))
    return 1.0 + (1.0 - r) * g_minus_1


@dataclass(frozen=True)
class ModulusTemperature(Effect):
    """Softening of the solder modulus with temperature: size ``k_E`` (1/K), forms ``n_E`` (-,
    curvature) and ``r_E`` (-, the plateau as a share of E25).

    Attributes:
        T0_C: temperature at which the configured modulus holds, degC.
    """

    name = "modulus_temperature"
    seam = "material law (solder)"
    transfers = True
    nuisance = ("n_E", "r_E")
    T0_C: float = 25.0

    def default_box(self) -> Box:
        return Box(("k_E", "n_E", "r_E"), (0.0, 0.0, R_MIN), (K_MAX, N_MAX, R_MAX),
                   units=("1/K", "-", "-"))

    @property
    def off(self) -> tuple[float, ...]:
        return (0.0, 0.0, R_MIN)

    def check(self, q: torch.Tensor) -> None:
        n, r = q[:, 1], q[:, 2]
        if bool(((n < 0) | (n > N_MAX)).any()):
            raise ValueError(f"modulus_temperature: n_E (the law's curvature: 0 exponential, 1 "
                             f"linear, 2 quickening) must be within [0, {N_MAX:g}], got "
                             f"{n.min().item():g} to {n.max().item():g}")
        if bool(((r <= 0) | (r >= 1)).any()):
            raise ValueError(f"modulus_temperature: r_E (the plateau, a share of E25) must be "
                             f"within (0, 1), got {r.min().item():g} to {r.max().item():g}")

    def modulus(self, E: torch.Tensor, T: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """``E * softening(k_E (T - T0), n_E, r_E)`` ``(b,)`` MPa."""
        return E * softening(q[:, 0] * (T - self.T0_C), q[:, 1], q[:, 2])


EFFECT = ModulusTemperature()
