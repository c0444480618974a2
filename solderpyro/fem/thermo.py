"""The step's inputs of a batched solve: temperature-dependent fields at one instant.

:class:`StepThermo` holds the temperature, the solder's free thermal strain and modulus, the
linear materials' thermal strains and, with effects, the solder's Prager modulus and its
Armstrong-Frederick recovery and a band's
thermal strain and yield stress; :class:`ThermoFields` computes it at a time of the thermal
cycle, shared by the batch in the baseline model and per member through the bound effects
(:class:`~solderpyro.effects.EffectSet`). :class:`MemberStep` bundles it with the members'
parameter rows and the step length: what a step of the batch takes besides displacements and
state.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import torch

from solderpyro.effects import EffectSet
from solderpyro.params import ANAND_NAMES

N_ANAND = len(ANAND_NAMES)


@dataclass(frozen=True)
class StepThermo:
    """Temperature-dependent inputs at one instant of the solve.

    Attributes:
        T: temperature, degC; eps_th: the solder's free thermal strain; E: its Young's
            modulus, MPa. Floats in the baseline model; ``(b, 1, 1)`` per member with effects.
        eps_lin: free thermal strains of the linear materials, ``(n_mat,)`` or ``(b, n_mat)``.
        per_member: whether the fields are per batch member (then :meth:`index` selects rows).
        C_k: the solder's Prager modulus ``(b, 1, 1)`` MPa, or None (no back stress).
        gamma_k: the Armstrong-Frederick recovery of that back stress ``(b, 1, 1)``
            (dimensionless), or None (none: Prager).
        band: ``(eps_th, sigma_y)``, each ``(b, 1, 1)``, of an elasto-plastic band's material
            (free thermal strain, yield stress MPa), or None (no band).
    """

    T: Any
    eps_th: Any
    E: Any
    eps_lin: torch.Tensor
    per_member: bool = False
    C_k: Any = None
    band: Any = None
    gamma_k: Any = None

    def index(self, idx) -> StepThermo:
        """The inputs of the members ``idx`` (itself when shared by the batch)."""
        if not self.per_member:
            return self
        return StepThermo(self.T[idx], self.eps_th[idx], self.E[idx], self.eps_lin[idx], True,
                          None if self.C_k is None else self.C_k[idx],
                          None if self.band is None else tuple(a[idx] for a in self.band),
                          None if self.gamma_k is None else self.gamma_k[idx])

    def rows(self, idx) -> StepThermo:
        """:meth:`index` for sorted, unique member indices ``idx``; itself (no copy) when they
        are all of its members."""
        if not self.per_member or len(idx) == self.eps_lin.shape[0]:
            return self
        return self.index(idx)


class MemberStep(NamedTuple):
    """What a step of the batch takes besides displacements and state.

    Attributes:
        p: ``(b, 9 + n_eff)`` the members' Anand constants (ANAND_NAMES order) and effect
            parameters.
        th: the end-of-step inputs (:class:`StepThermo`).
        dt: step, s.
    """

    p: torch.Tensor
    th: StepThermo
    dt: float

    def rows(self, idx) -> MemberStep:
        """The step of the members ``idx`` (sorted, unique; itself when they are all)."""
        if len(idx) == self.p.shape[0]:
            return self
        return MemberStep(self.p[idx], self.th.rows(idx), self.dt)


class ThermoFields:
    """:class:`StepThermo` of a problem at a time or temperature.

    Args:
        problem: the :class:`~solderpyro.fem.problem.Problem` (cycle, materials, T_ref_C).
        solder: its solder law; lin_keys: the linear materials' keys, in the order of
            ``eps_lin``; band_material: the key of an elasto-plastic band's material, or None.
        tkw: torch dtype and device of the fields.
    """

    def __init__(self, problem, solder, lin_keys: list[str], band_material: str | None,
                 tkw: dict) -> None:
        self.problem, self.solder, self.lin_keys = problem, solder, lin_keys
        self.band_material, self.tkw = band_material, tkw

    def eps_th_lin(self, T_C) -> torch.Tensor:
        """Free thermal strains ``(n_mat,)`` of the linear materials at T (degC)."""
        mats, T0 = self.problem.materials, self.problem.T_ref_C
        return torch.tensor([float(mats[k].thermal_strain(T_C, T0)) for k in self.lin_keys],
                            **self.tkw)

    def at_temperature(self, T_C: float) -> StepThermo:
        """Baseline inputs at a uniform temperature ``T_C`` (degC), shared by the batch."""
        sol, T0 = self.solder, self.problem.T_ref_C
        return StepThermo(T_C, sol.thermal_strain(T_C, T0), sol.modulus(T_C),
                          self.eps_th_lin(T_C))

    def as_thermo(self, th) -> StepThermo:
        """``th`` itself if a :class:`StepThermo`, else the inputs at temperature ``th``
        (degC)."""
        return th if isinstance(th, StepThermo) else self.at_temperature(float(th))

    def at(self, t: float, p: torch.Tensor, fx: EffectSet | None) -> StepThermo:
        """Inputs at time ``t`` (s) for the members ``p`` ``(b, 9 + n_eff)``: the program's
        temperature in the baseline model (``fx`` None), else per member through the effects
        ``fx`` bound to the solve's times."""
        pr = self.problem
        if fx is None:
            return self.at_temperature(pr.cycle(t))
        q = p[:, N_ANAND:]
        T = fx.temperature(pr.cycle, t, pr.T_ref_C, q)  # (b,)
        T_ref = fx.stress_free(pr.T_ref_C, q)  # (b,)
        mats = pr.materials
        eps_lin = torch.stack([fx.thermal_strain(mats[k], T, T_ref, q)
                               for k in self.lin_keys], -1)  # (b, n_mat)
        eps_th = fx.thermal_strain(self.solder, T, T_ref, q)
        E = fx.modulus(self.solder, T, q)
        C_k = fx.back_stress_modulus(q)  # (b,) or None
        gamma_k = fx.back_stress_recovery(q)  # (b,) or None
        band = None
        if self.band_material is not None:
            eb = fx.thermal_strain(mats[self.band_material], T, T_ref, q)
            sy = fx.yield_stress(q)
            assert sy is not None
            band = (eb[:, None, None], sy[:, None, None])
        return StepThermo(T[:, None, None], eps_th[:, None, None], E[:, None, None], eps_lin,
                          True, None if C_k is None else C_k[:, None, None], band,
                          None if gamma_k is None else gamma_k[:, None, None])
