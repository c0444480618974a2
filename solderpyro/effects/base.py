"""Optional physical effects: the :class:`Effect` base class.

An effect is a piece of physics the baseline model lacks, with calibratable parameters on a
prior box. It enters the model through one seam, as a hook that transforms a
baseline quantity, identity by default:

=====================  =========================================================================
seam                   hook
=====================  =========================================================================
temperature history    :meth:`Effect.temperature` (member temperature at a time of the cycle)
initial state          :meth:`Effect.stress_free` + :meth:`Effect.pre_history` (a simulated
                       history before t = 0; V is then reported relative to the state at t = 0)
                       + :meth:`Effect.cooldown` and :meth:`Effect.cooldown_shape` (each
                       member's cool-down in it and how it runs)
material law           :meth:`Effect.thermal_strain`, :meth:`Effect.modulus`,
                       :meth:`Effect.back_stress_modulus` (solder back stress),
                       :meth:`Effect.back_stress_recovery` (its dynamic recovery),
                       :meth:`Effect.plastic_band` + :meth:`Effect.yield_stress` (a band of
                       a linear region made elasto-plastic)
observation operator   :meth:`Effect.observe` (on the solver's V after the FE solve)
=====================  =========================================================================

Every hook receives ``q``, the effect's own columns of the parameter vector, ``(b, n_p)`` (one row
per batch member), so each member can carry its own effect values, and the hooks are plain torch
functions of ``q``: outputs are differentiable with respect to the effect parameters.
The solver core calls :class:`~solderpyro.effects.EffectSet` (their composition, in the
package, beside the registry it resolves names in) only; it never names an effect.

Units: temperatures degC, times s, displacements um, as everywhere at this surface.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import torch

from solderpyro.fem.loading import ThermalCycle, TimeStepping
from solderpyro.params import Box


@dataclass(frozen=True)
class PlasticBand:
    """Elements of a linear elastic material next to the solder made elasto-plastic.

    The elements of ``material`` lying within ``depth`` mm of the nonlinear (solder) region
    follow rate-independent J2 plasticity with linear isotropic hardening
    (:func:`solderpyro.materials.j2.j2_update`); the rest of that material stays elastic and
    condensed. The yield stress comes per member from :meth:`Effect.yield_stress`.

    Attributes:
        material: key of the linear material (e.g. ``"copper"``).
        depth: band depth, mm (every node of a band element within it).
        H: linear isotropic hardening modulus, MPa.
        elastic_limit: yield stresses >= this (MPa) mean an elastic band: those members are
            solved on the baseline path; the solver warns when the band's elastic stress
            reaches it there.
    """

    material: str
    depth: float
    H: float
    elastic_limit: float


@dataclass(frozen=True)
class PreHistory:
    """A history simulated before t = 0: each member cools from its stress-free temperature to
    the program's start over its own cool-down, ending at t = 0, as ``s ** p`` of the way at
    the share ``s`` of its cool-down still to run, ``p`` its own shape (1: a constant rate;
    > 1: fastest at first, slowing as it nears the room; a subclass may shape the cool-down
    otherwise through :meth:`fraction` and :attr:`peak_rate`).

    Attributes:
        duration_s: the longest cool-down, s (the pre-history starts at ``-duration_s``; a
            member with a shorter one rests at its stress-free temperature until its
            cool-down starts, which changes nothing: the specimen is stress free there).
        dT: the largest ``|T_sf - T_start|``, K.
        shortest_s: the shortest cool-down, s (the fastest ramp the grid must resolve).
        shape_max: the largest shape ``p`` a member may have (>= 1).
    """

    duration_s: float
    dT: float
    shortest_s: float
    shape_max: float = 1.0

    def __post_init__(self) -> None:
        if not 0.0 < self.shortest_s <= self.duration_s:
            raise ValueError(f"PreHistory: need 0 < shortest_s <= duration_s, got "
                             f"{self.shortest_s} and {self.duration_s}")
        if not self.dT >= 0.0:
            raise ValueError(f"PreHistory: dT must be >= 0 K, got {self.dT}")
        if not self.shape_max >= 1.0:
            raise ValueError(f"PreHistory: shape_max must be >= 1, got {self.shape_max}")

    @property
    def peak_rate(self) -> float:
        """The cool-down's fastest rate over its mean rate: ``p`` at its start for ``s ** p``,
        so :attr:`shape_max` (1: a constant rate)."""
        return self.shape_max

    def fraction(self, s: torch.Tensor, shape: torch.Tensor | None = None) -> torch.Tensor:
        """How far ``(T - T_start) / (T_sf - T_start)`` the member is, ``(b,)``, at the share
        ``s`` ``(b,)`` in (0, 1] of its cool-down still to run (1 at its start): ``s ** shape``
        (``s`` where ``shape`` ``(b,)`` is None)."""
        return s if shape is None else s ** shape

    def grid(self, ts: TimeStepping) -> np.ndarray:
        """Step end times ``(n + 1,)`` s from ``-duration_s`` to 0, shared by the batch.

        At time ``t < 0`` only members whose cool-down is at least ``|t|`` are ramping, at
        most at ``dT / max(|t|, shortest_s)`` K/s, so the step there is
        ``min(dt_max, dT_max max(|t|, shortest_s) / dT)``: fine near 0, where the fastest
        cool-downs run, and growing geometrically back in time (about
        ``dT / dT_max (1 + ln(duration_s / shortest_s))`` steps in all).
        """
        out = [0.0]
        t = 0.0
        while t > -self.duration_s * (1.0 - 1e-12):
            rate = self.peak_rate * self.dT / max(-t, self.shortest_s)
            h = ts.dt_max if rate == 0.0 else min(ts.dt_max, ts.dT_max / rate)
            t = max(t - h, -self.duration_s)
            out.append(t)
        return np.array(out[::-1])


@dataclass(frozen=True)
class Effect:
    """One optional physical effect (subclass per effect, one module each).

    Subclasses set the class attributes ``name`` (the registry key) and ``seam``, implement
    :meth:`default_box` and :attr:`off`, and override the hooks they need. Dataclass fields of a
    subclass are physics settings (they enter the run-store hash through :meth:`settings`); a field
    with ``metadata={"prior": True}`` only shapes the prior box and is left out of the hash.

    Attributes:
        box: optional override of the prior box (same names as :meth:`default_box`); set it
            with :meth:`with_box`.
    """

    name: ClassVar[str] = ""
    seam: ClassVar[str] = ""
    #: parameters that carry the effect's form (how it acts: a cool-down, a law's shape), not
    #: its size; the data may inform them, and the diagnosis's screen varies the size alone,
    #: with these at "off" (:attr:`size_index`)
    nuisance: ClassVar[tuple[str, ...]] = ()
    #: whether the effect belongs to the solder or the materials (True: it carries over when
    #: a calibration's constants predict another assembly or cycle) rather than to the
    #: specimen, its history, the chamber or the measurement (False: it is left out there)
    transfers: ClassVar[bool] = False
    box: Box | None = field(default=None, compare=False, repr=False,
                            metadata={"prior": True})

    # ------------------------------------------------------------------ parameters
    def default_box(self) -> Box:
        """The prior box of the parameters (names, lower, upper, units)."""
        raise NotImplementedError

    @property
    def params(self) -> Box:
        """The prior box in force (:attr:`box` when set, else :meth:`default_box`)."""
        return self.default_box() if self.box is None else self.box

    @property
    def off(self) -> tuple[float, ...]:
        """Parameter values ``(n_p,)`` that give back the baseline model exactly."""
        raise NotImplementedError

    @property
    def n_params(self) -> int:
        """The number of the effect's parameters (its columns of the parameter vector)."""
        return self.params.dim

    @property
    def sized(self) -> tuple[str, ...]:
        """The names of the parameters that size the effect (every one not in
        :attr:`nuisance`), in the box's order."""
        return tuple(nm for nm in self.params.names if nm not in self.nuisance)

    @property
    def size_index(self) -> int | None:
        """Index of the one parameter that sizes the effect (all others are :attr:`nuisance`),
        or None when several do (e.g. one per Moire image)."""
        sized = self.sized
        return list(self.params.names).index(sized[0]) if len(sized) == 1 else None

    def bind(self, times: Sequence[float]) -> Effect:
        """This effect for the sorted output times ``times`` (s); most effects ignore them."""
        return self

    def rebind_params(self, q: torch.Tensor, times_from: Sequence[float],
                      times_to: Sequence[float]) -> torch.Tensor:
        """Parameters ``q (b, n_p)`` fitted with outputs at ``times_from`` (s) carried to the
        effect bound to ``times_to`` (e.g. to predict other times from a fit). Effects whose
        parameters do not depend on the output times return ``q`` unchanged."""
        return q

    def with_box(self, bounds: Mapping[str, Sequence[float]]) -> Effect:
        """A copy whose prior box has ``bounds`` ``{param: (lower, upper)}`` replaced.

        Raises:
            ValueError: naming an unknown key (and listing the valid ones) or a bad pair.
        """
        b = self.params
        lo, hi = list(b.lower), list(b.upper)
        for key, pair in bounds.items():
            if key not in b.names:
                raise ValueError(f"effect {self.name!r} has no parameter {key!r}; valid: "
                                 f"{', '.join(b.names)}")
            i = b.names.index(key)
            lo[i], hi[i] = box_pair(self.name, key, pair)
        return dataclasses.replace(self, box=Box(b.names, tuple(lo), tuple(hi),
                                                 b.log_scale, b.units))

    def settings(self) -> dict[str, Any]:
        """What the outputs depend on besides the parameters: ``{"name", field: value, ...}``
        (the run-store hash covers it; prior-only fields are left out)."""
        out: dict[str, Any] = {"name": self.name}
        for f in dataclasses.fields(self):
            if not f.metadata.get("prior", False):
                out[f.name] = getattr(self, f.name)
        return out

    def check(self, q: torch.Tensor) -> None:
        """Raise ``ValueError`` for physically meaningless values ``q`` ``(b, n_p)``."""

    # ------------------------------------------------------------------ hooks (identity)
    def temperature(self, T: torch.Tensor, t: float, cycle: ThermalCycle,
                    q: torch.Tensor) -> torch.Tensor:
        """Member temperature ``(b,)`` degC at time ``t >= 0`` s from the program's ``T``."""
        return T

    def stress_free(self, T_ref: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """Stress-free temperature ``(b,)`` degC of each member (baseline: ``T_ref``)."""
        return T_ref

    def pre_history(self) -> PreHistory | None:
        """The history simulated before t = 0 (from the stress-free temperature to the
        program's start), or None for none."""
        return None

    def cooldown(self, q: torch.Tensor) -> torch.Tensor | None:
        """Each member's cool-down ``(b,)`` s before t = 0 (None: the pre-history's whole
        duration)."""
        return None

    def cooldown_shape(self, q: torch.Tensor) -> torch.Tensor | None:
        """Each member's cool-down shape ``(b,)`` (dimensionless, :meth:`PreHistory.fraction`;
        None: a constant rate)."""
        return None

    def thermal_strain(self, eps: torch.Tensor, alpha: float, T: torch.Tensor,
                       T_ref: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """Free thermal strain ``(b,)`` of a material with CTE ``alpha`` (1/K at 25 degC) at
        ``T`` from the stress-free ``T_ref`` (both ``(b,)`` degC); ``eps`` is the baseline's."""
        return eps

    def modulus(self, E: torch.Tensor, T: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """Solder Young's modulus ``(b,)`` MPa at ``T`` ``(b,)`` degC from the baseline's ``E``."""
        return E

    def back_stress_modulus(self, C_k: torch.Tensor | None,
                            q: torch.Tensor) -> torch.Tensor | None:
        """Prager modulus ``(b,)`` MPa of the solder's back stress (``dX = 2/3 C_k deps_p``),
        from the baseline's ``C_k`` (None: no back stress, the isotropic Anand model)."""
        return C_k

    def back_stress_recovery(self, gamma_k: torch.Tensor | None,
                             q: torch.Tensor) -> torch.Tensor | None:
        """Armstrong-Frederick recovery ``(b,)`` (dimensionless) of the solder's back stress
        (``dX = 2/3 C_k deps_p - gamma_k X dp``), from the baseline's ``gamma_k`` (None: no
        recovery, the Prager law)."""
        return gamma_k

    def plastic_band(self) -> PlasticBand | None:
        """A band of a linear material made elasto-plastic (a setting), or None."""
        return None

    def yield_stress(self, q: torch.Tensor) -> torch.Tensor | None:
        """Yield stress ``(b,)`` MPa of the :meth:`plastic_band`'s material per member; ``inf``
        for a member whose band stays elastic (it is then solved on the baseline path)."""
        return None

    def observe(self, V: torch.Tensor, x: torch.Tensor, x_O: float,
                q: torch.Tensor) -> torch.Tensor:
        """Observed ``V`` ``(b, n_time, n_out)`` um from the FE's; ``x`` ``(n_out,)`` mm are the
        output points' abscissae, ``x_O`` that of the origin O."""
        return V


def box_pair(name: str, key: str, pair: Sequence[float]) -> tuple[float, float]:
    """A prior-box override ``pair = [lower, upper]`` of key ``key`` of effect ``name`` as
    floats ``(lower, upper)`` in the parameter's units (:meth:`Effect.with_box`).

    Raises:
        ValueError: when ``pair`` is not two numbers or ``lower >= upper``.
    """
    try:
        lo, hi = (float(v) for v in pair)
    except (TypeError, ValueError):
        raise ValueError(f"effect box {name}.{key} must be [lower, upper], got {pair!r}") from None
    if not lo < hi:
        raise ValueError(f"effect box {name}.{key}: lower {lo:g} must be < upper {hi:g}")
    return lo, hi
