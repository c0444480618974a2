"""Kinematic hardening of the solder: a back stress in the Anand flow, linear (Prager) or with
Armstrong-Frederick dynamic recovery.

The solder's flow is driven by the effective stress ``xi = dev(sigma) - X`` instead of
``dev(sigma)``, with the back stress ``X`` (deviatoric, MPa) growing with the inelastic strain,

    dX = (2/3) * C_k * deps_p - gamma_k * X * dp,    dp = sqrt(2/3) |deps_p|,

``C_k >= 0`` MPa the size (off: 0, the isotropic Anand model) and ``gamma_k >= 0``
(dimensionless) the form, a nuisance parameter: ``gamma_k = 0`` (the default) is the linear
Prager law, under proportional loading at constant rate a flow stress raised by ``C_k * eps_p``
on top of Anand's isotropic hardening; ``gamma_k > 0`` recovers the back stress dynamically, so
that it saturates, ``X_eq = (C_k/gamma_k)(1 - exp(-gamma_k eps_p))``, at ``C_k/gamma_k`` after
an inelastic strain of a few ``1/gamma_k``. On load reversal the solder flows earlier
(Bauschinger effect): during the cooling of the cycle the solder's shear reverses. Cyclic
tests of Sn-Pb solders give Prager/Armstrong-Frederick moduli from a few GPa to ~20 GPa; real
back stresses saturate, and whether they do within a cycle's few per cent of inelastic shear is
rarely known, so the form is left to the data: the default box's top ``gamma_k = 200``
saturates within ~1.5 % (three e-foldings of 0.5 %), at ``C_k/200``. The Gauss-point law, its
lagged-recovery integration, consistent tangent and the closed forms are in
:mod:`solderpyro.materials.kinematic`; the solver carries ``X`` (and, for the recovery, the
last step's inelastic rate) in the Gauss-point state when this effect is on. At ``C_k = 0`` the
update is the isotropic one to the last bit (``3G + 0``, ``X = 0 + 0``, whatever
``gamma_k``), and at ``gamma_k = 0`` the Prager one (recovery factor ``1/(1 + 0) = 1``).
Seam: the solder's material law.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from solderpyro.effects.base import Effect
from solderpyro.params import Box


@dataclass(frozen=True)
class KinematicHardening(Effect):
    """Back stress in the solder: size ``C_k`` (MPa), Armstrong-Frederick form ``gamma_k`` (-)."""

    name = "kinematic_hardening"
    seam = "material law (solder)"
    transfers = True
    nuisance = ("gamma_k",)

    def default_box(self) -> Box:
        return Box(("C_k", "gamma_k"), (0.0, 0.0), (2000.0, 200.0), units=("MPa", "-"))

    @property
    def off(self) -> tuple[float, ...]:
        return (0.0, 0.0)

    def check(self, q: torch.Tensor) -> None:
        if bool((q[:, 0] < 0).any()):
            raise ValueError(f"kinematic_hardening: C_k must be >= 0 MPa, got "
                             f"{q[:, 0].min().item():g}")
        if bool((q[:, 1] < 0).any()):
            raise ValueError(f"kinematic_hardening: gamma_k (the Armstrong-Frederick recovery; "
                             f"0: Prager) must be >= 0, got {q[:, 1].min().item():g}")

    def back_stress_modulus(self, C_k: torch.Tensor | None,
                            q: torch.Tensor) -> torch.Tensor | None:
        """``C_k`` ``(b,)`` MPa (the baseline has none)."""
        return q[:, 0] if C_k is None else C_k + q[:, 0]

    def back_stress_recovery(self, gamma_k: torch.Tensor | None,
                             q: torch.Tensor) -> torch.Tensor | None:
        """``gamma_k`` ``(b,)`` (dimensionless; the baseline has none)."""
        return q[:, 1] if gamma_k is None else gamma_k + q[:, 1]


EFFECT = KinematicHardening()
