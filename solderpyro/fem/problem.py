"""Typed description of the FE problem: geometry, materials per region, loading, outputs.

The library takes these objects; only the CLI and experiment scripts read config files.
Units: mm, MPa, s, degC (at this surface), displacements reported in um.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from solderpyro.fem.loading import REFERENCE_CYCLE, ThermalCycle, TimeStepping
from solderpyro.fem.mesh import Layer, MeshSpec


@dataclass(frozen=True)
class Elastic:
    """Linear isotropic thermo-elastic material: E (MPa), nu, alpha (1/K).

    A material law is the seam through which physical effects enter a region: subclass and
    override :meth:`thermal_strain` (e.g. a temperature-dependent CTE). Linear laws are
    condensed once, so their stiffness must not depend on the batch member.
    """

    E: float
    nu: float
    alpha: float
    nonlinear: bool = False

    def __post_init__(self) -> None:
        if not self.E > 0:
            raise ValueError(f"E must be > 0 MPa, got {self.E}")
        if not -1.0 < self.nu < 0.5:
            raise ValueError(f"nu must lie in (-1, 0.5), got {self.nu}")

    def thermal_strain(self, T_C, T_ref_C):
        """Free (isotropic) thermal strain from ``T_ref_C`` to ``T_C`` (degC); scalar or tensor."""
        return self.alpha * (T_C - T_ref_C)


class SolderStep(NamedTuple):
    """The step's conditions of a solder law's Gauss-point update (:meth:`AnandSolder.update`).

    Attributes:
        T_C: end-of-step temperature, degC: a float or per member ``(b, 1, 1)``.
        T_ref_C: stress-free temperature, degC.
        dt: step, s.
        eps_th, E: free thermal strain and Young's modulus (MPa), float or ``(b, 1, 1)``,
            replacing the law's :meth:`~Elastic.thermal_strain` and :meth:`~AnandSolder.modulus`
            (physical effects computed per batch member, see :mod:`solderpyro.effects`); None:
            the law's own.
        C_k: Prager modulus of a back stress (MPa), float or ``(b, 1, 1)``, or None (none);
            the state then carries the back stress ``X``
            (:mod:`solderpyro.materials.kinematic`).
        gamma_k: Armstrong-Frederick recovery of that back stress (dimensionless), float or
            ``(b, 1, 1)``, or None (none: Prager); the state then carries the lagged rate
            ``p_rate``.
    """

    T_C: Any
    T_ref_C: float
    dt: float
    eps_th: Any = None
    E: Any = None
    C_k: Any = None
    gamma_k: Any = None


@dataclass(frozen=True)
class AnandSolder(Elastic):
    """Thermo-elastic-viscoplastic solder (Anand); the nine constants come per batch member.

    :meth:`update` is what the solver calls at the Gauss points; a subclass can make the
    modulus depend on temperature or add a back stress without touching the solver.
    """

    nonlinear: bool = True

    def modulus(self, T_C):
        """Young's modulus (MPa) at temperature ``T_C`` (constant in the baseline model)."""
        return self.E

    def update(self, eps, state, p, step: SolderStep, guess=None, tangent=True):
        """Gauss-point update; see :func:`solderpyro.materials.integrate.return_map_3d`.

        Args:
            eps: ``(b, n_e, n_qp, 4)`` total strain (Mandel); state: start-of-step state;
            p: ``(b, 1, 1, 9)`` Anand constants; step: the step's :class:`SolderStep`
                (temperatures degC, dt s, optional per-member thermal strain, modulus, Prager
                modulus and recovery); guess, tangent: as in ``return_map_3d``.
        """
        from solderpyro.materials.integrate import PointInputs, return_map_3d

        eps_th = step.eps_th
        if eps_th is None:
            eps_th = self.thermal_strain(step.T_C, step.T_ref_C)
        E = step.E
        if E is None:
            E = self.modulus(step.T_C)
        inputs = PointInputs(step.T_C + 273.15, step.dt, eps_th, E, self.nu, step.C_k,
                             step.gamma_k)
        return return_map_3d(eps, state, p, inputs, guess=guess, tangent=tangent)


#: Material laws by config name (``materials.<key>.law``); effects register theirs here.
LAWS: dict[str, type] = {"elastic": Elastic, "anand": AnandSolder}

#: seed Table III
SUS630 = Elastic(E=200e3, nu=0.29, alpha=10.8e-6)
SN37PB = AnandSolder(E=32e3, nu=0.35, alpha=23.5e-6)
COPPER = Elastic(E=130e3, nu=0.34, alpha=16.3e-6)

REFERENCE_LAYERS = (
    Layer("copper", "copper", -4.0, 0.0, 8, 0.25, "top"),
    Layer("solder", "solder", 0.0, 0.5, 4),
    Layer("steel", "steel", 0.5, 4.5, 8, 0.25, "bottom"),
)


def reference_grid() -> tuple[list[str], np.ndarray]:
    """The full-field grid of the reference case (1 mm, 31 x 18; docs/configuration.md): labels
    ``g_ii_jj`` and ``(558, 2)`` points, mm."""
    xs = np.arange(-15.0, 15.0 + 1e-9, 1.0)
    ys = np.arange(-4.0, 4.5 + 1e-9, 0.5)
    labels, pts = [], []
    for j, y in enumerate(ys):
        for i, x in enumerate(xs):
            labels.append(f"g_{i:02d}_{j:02d}")
            pts.append((x, y))
    return labels, np.array(pts)


@dataclass(frozen=True)
class Problem:
    """Everything the FE solver needs except the Anand constants.

    Attributes:
        layers: bottom-to-top layers; ``materials`` maps their ``material`` keys to laws.
        half_length: L/2 of the bars, mm.
        mesh: x resolution (``half=True`` uses the x = 0 symmetry line).
        plane: ``"stress"`` (default; the Moire free face) or ``"strain"``.
        T_ref_C: stress-free temperature, degC.
        cycle: temperature program (uniform temperature).
        stepping: time-grid controls.
        points: named observation points ``{name: (x, y)}`` in mm; V is reported relative to O.
        origin: the point O, mm (v = 0 there; u = 0 on x = 0).
        incompatible_modes: QM6 elements in the linear elastic regions (no bending lock).
    """

    layers: tuple[Layer, ...] = REFERENCE_LAYERS
    materials: dict = field(default_factory=lambda: {
        "steel": SUS630, "solder": SN37PB, "copper": COPPER})
    half_length: float = 15.0
    mesh: MeshSpec = MeshSpec()
    plane: str = "stress"
    T_ref_C: float = 25.0
    cycle: ThermalCycle = REFERENCE_CYCLE
    stepping: TimeStepping = TimeStepping()
    points: dict = field(default_factory=lambda: {"A": (15.0, 4.5), "B": (15.0, -4.0)})
    origin: tuple[float, float] = (0.0, 0.0)
    incompatible_modes: bool = True

    def __post_init__(self) -> None:
        if self.plane not in ("stress", "strain"):
            raise ValueError(f"plane must be 'stress' or 'strain', got {self.plane!r}")
        for lay in self.layers:
            if lay.material not in self.materials:
                raise ValueError(f"layer {lay.name!r} uses unknown material {lay.material!r}")
