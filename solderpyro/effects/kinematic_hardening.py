"""Kinematic hardening of the solder: a linear (Prager) back stress in the Anand flow.

The solder's flow is driven by the effective stress ``xi = dev(sigma) - X`` instead of
``dev(sigma)``, with the back stress ``X`` (deviatoric, MPa) growing with the inelastic strain,

    dX = (2/3) * C_k * deps_p,        C_k >= 0 MPa (off: 0, the isotropic Anand model),

so under proportional loading at constant rate the flow stress rises by ``C_k * eps_p`` on top
of Anand's isotropic hardening, and on load reversal the solder flows earlier (Bauschinger
effect): during the cooling of the cycle the solder's shear reverses. Cyclic tests of Sn-Pb
solders give Prager/Armstrong-Frederick moduli from a few GPa to ~20 GPa (the linear back stress
saturates in reality; over one cycle the inelastic shear strain stays at a few per cent, where
a linear law is a fair first approximation). The Gauss-point law, its consistent tangent and the
closed forms are in :mod:`solderpyro.materials.kinematic`; the solver carries ``X`` in the
Gauss-point state when this effect is on. At ``C_k = 0`` the update is the isotropic one to the
last bit (``3G + 0``, ``X = 0 + 0``).
Seam: the solder's material law.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from solderpyro.effects.base import Effect
from solderpyro.params import Box


@dataclass(frozen=True)
class KinematicHardening(Effect):
    """Linear Prager back stress in the solder; parameter ``C_k`` (MPa)."""

    name = "kinematic_hardening"
    seam = "material law (solder)"
    transfers = True

    def default_box(self) -> Box:
        return Box(("C_k",), (0.0,), (2000.0,), units=("MPa",))

    @property
    def off(self) -> tuple[float, ...]:
        return (0.0,)

    def check(self, q: torch.Tensor) -> None:
        if bool((q[:, 0] < 0).any()):
            raise ValueError(f"kinematic_hardening: C_k must be >= 0 MPa, got "
                             f"{q[:, 0].min().item():g}")

    def back_stress_modulus(self, C_k: torch.Tensor | None,
                            q: torch.Tensor) -> torch.Tensor | None:
        """``C_k`` ``(b,)`` MPa (the baseline has none)."""
        return q[:, 0] if C_k is None else C_k + q[:, 0]


EFFECT = KinematicHardening()
