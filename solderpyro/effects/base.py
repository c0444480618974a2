"""Optional physical effects: the :class:`Effect` base class and their composition.

An effect is a piece of physics the baseline model lacks, with calibratable parameters on a
prior box. It enters the model through one seam (shared/style.md), as a hook that transforms a
baseline quantity, identity by default:

=====================  =========================================================================
seam                   hook
=====================  =========================================================================
temperature history    :meth:`Effect.temperature` (member temperature at a time of the cycle)
initial state          :meth:`Effect.stress_free` + :meth:`Effect.pre_history` (a simulated
                       history before t = 0; V is then reported relative to the state at t = 0)
material law           :meth:`Effect.thermal_strain`, :meth:`Effect.modulus`,
                       :meth:`Effect.back_stress_modulus` (solder back stress),
                       :meth:`Effect.plastic_band` + :meth:`Effect.yield_stress` (a band of
                       a linear region made elasto-plastic)
observation operator   :meth:`Effect.observe` (on the solver's V after the FE solve)
=====================  =========================================================================

Every hook receives ``q``, the effect's own columns of the parameter vector, ``(b, n_p)`` (one row
per batch member), so each member can carry its own effect values, and the hooks are plain torch
functions of ``q``: outputs are differentiable with respect to the effect parameters.
The solver core calls :class:`EffectSet` only; it never names an effect.

Units: temperatures degC, times s, displacements um, as everywhere at this surface.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import torch

from ..fem.loading import ThermalCycle
from ..params import Box


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
        return self.params.dim

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
            lo[i], hi[i] = _pair(self.name, key, pair)
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

    def pre_history(self) -> tuple[float, float] | None:
        """``(duration s, largest temperature change K)`` of a history simulated before t = 0
        (from the stress-free temperature to the program's start), or None for none."""
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


def _pair(name: str, key: str, pair: Sequence[float]) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in pair)
    except (TypeError, ValueError):
        raise ValueError(f"effect box {name}.{key} must be [lower, upper], got {pair!r}") from None
    if not lo < hi:
        raise ValueError(f"effect box {name}.{key}: lower {lo:g} must be < upper {hi:g}")
    return lo, hi


class EffectSet:
    """The effects switched on, in order, and their columns of the effect-parameter vector.

    The solver and the model hold one; :meth:`bind` specialises it to the output times (an
    observation effect may have one parameter per image).

    Args:
        effects: effect names (registry keys) or :class:`Effect` instances, no duplicates.
    """

    def __init__(self, effects: Sequence[str | Effect]) -> None:
        from . import get_effect

        self.effects: tuple[Effect, ...] = tuple(get_effect(e) for e in effects)
        keys = [e.name for e in self.effects]
        if len(set(keys)) != len(keys):
            raise ValueError(f"effects listed twice: {keys}")
        for hook in ("temperature", "pre_history", "plastic_band"):  # replace, not compose
            who = [e.name for e in self.effects if _overrides(e, hook)]
            if len(who) > 1:
                raise ValueError(f"effects {who} both override {hook}(); only one may")
        edges, n = [], 0
        for e in self.effects:
            edges.append((n, n + e.n_params))
            n += e.n_params
        self._edges = edges
        self.n_params = n

    def __len__(self) -> int:
        return len(self.effects)

    @property
    def keys(self) -> tuple[str, ...]:
        """Effect names, in order."""
        return tuple(e.name for e in self.effects)

    @property
    def names(self) -> tuple[str, ...]:
        """Parameter names ``(n_params,)`` in column order."""
        return tuple(n for e in self.effects for n in e.params.names)

    @property
    def box(self) -> Box:
        """Concatenated prior box of all parameters."""
        bs = [e.params for e in self.effects]
        return Box(self.names, tuple(v for b in bs for v in b.lower),
                   tuple(v for b in bs for v in b.upper), tuple(v for b in bs for v in b.log_scale),
                   tuple(v for b in bs for v in b.units))

    @property
    def off(self) -> tuple[float, ...]:
        """Baseline values ``(n_params,)``."""
        return tuple(v for e in self.effects for v in e.off)

    def bind(self, times: Sequence[float]) -> EffectSet:
        """The set for output times ``times`` (s; sorted here)."""
        ts = tuple(sorted(float(t) for t in times))
        return EffectSet([e.bind(ts) for e in self.effects])

    def rebind_params(self, q: torch.Tensor, times_from: Sequence[float],
                      times_to: Sequence[float]) -> torch.Tensor:
        """``q (b, n_params)`` of this set bound to ``times_from`` -> ``(b, n_params')`` of the
        set bound to ``times_to`` (:meth:`Effect.rebind_params` per effect)."""
        t0 = tuple(sorted(float(t) for t in times_from))
        t1 = tuple(sorted(float(t) for t in times_to))
        return torch.cat([e.rebind_params(qe, t0, t1)
                          for e, qe in zip(self.effects, self.split(q), strict=True)], 1)

    def settings(self) -> list[dict[str, Any]]:
        """Per effect, what the outputs depend on (for the run-store hash)."""
        return [e.settings() for e in self.effects]

    def split(self, q: torch.Tensor) -> list[torch.Tensor]:
        """Columns ``(b, n_p)`` of each effect from ``q`` ``(b, n_params)``."""
        return [q[:, a:b] for a, b in self._edges]

    def check(self, q: torch.Tensor) -> None:
        """Validate ``q`` ``(b, n_params)`` (shape, and each effect's own rules)."""
        if q.ndim != 2 or q.shape[1] != self.n_params:
            raise ValueError(f"effect parameters must have shape (B, {self.n_params}) for "
                             f"{', '.join(self.names)}; got {tuple(q.shape)}")
        for e, qe in zip(self.effects, self.split(q), strict=True):
            e.check(qe)

    # ------------------------------------------------------------------ composed hooks
    def pre_history(self) -> tuple[float, float] | None:
        """The one ``(duration s, largest |dT| K)`` pre-history, or None."""
        for e in self.effects:
            ph = e.pre_history()
            if ph is not None:
                return ph
        return None

    def stress_free(self, T_ref: float, q: torch.Tensor) -> torch.Tensor:
        """Stress-free temperature ``(b,)`` degC per member."""
        T = torch.full((q.shape[0],), float(T_ref), dtype=q.dtype, device=q.device)
        for e, qe in zip(self.effects, self.split(q), strict=True):
            T = e.stress_free(T, qe)
        return T

    def temperature(self, cycle: ThermalCycle, t: float, T_ref: float,
                    q: torch.Tensor) -> torch.Tensor:
        """Member temperature ``(b,)`` degC at time ``t`` s.

        For ``t < 0`` (pre-history of duration ``D``) the temperature goes linearly from the
        member's stress-free temperature at ``-D`` to the program's start at 0; from t = 0 on,
        the program ``cycle(t)`` transformed by the history hooks.
        """
        if t < 0.0:
            ph = self.pre_history()
            D = 1.0 if ph is None else ph[0]
            T0 = cycle(0.0)
            return T0 + (self.stress_free(T_ref, q) - T0) * (-t / D)
        T = torch.full((q.shape[0],), cycle(t), dtype=q.dtype, device=q.device)
        for e, qe in zip(self.effects, self.split(q), strict=True):
            T = e.temperature(T, t, cycle, qe)
        return T

    def thermal_strain(self, law: Any, T: torch.Tensor, T_ref: torch.Tensor,
                       q: torch.Tensor) -> torch.Tensor:
        """Free thermal strain ``(b,)`` of a material law (``law.thermal_strain``, ``law.alpha``)
        at ``T`` from ``T_ref`` (both ``(b,)`` degC)."""
        eps = law.thermal_strain(T, T_ref)
        for e, qe in zip(self.effects, self.split(q), strict=True):
            eps = e.thermal_strain(eps, law.alpha, T, T_ref, qe)
        return eps

    def modulus(self, law: Any, T: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """Young's modulus ``(b,)`` MPa of the solder law at ``T`` ``(b,)`` degC."""
        E = torch.as_tensor(law.modulus(T), dtype=T.dtype, device=T.device).expand_as(T)
        for e, qe in zip(self.effects, self.split(q), strict=True):
            E = e.modulus(E, T, qe)
        return E

    @property
    def kinematic(self) -> bool:
        """Whether an effect gives the solder a back stress (the state then carries ``X``)."""
        return any(_overrides(e, "back_stress_modulus") for e in self.effects)

    def back_stress_modulus(self, q: torch.Tensor) -> torch.Tensor | None:
        """Prager modulus ``(b,)`` MPa of the solder per member, or None (no back stress)."""
        C_k = None
        for e, qe in zip(self.effects, self.split(q), strict=True):
            C_k = e.back_stress_modulus(C_k, qe)
        return C_k

    def plastic_band(self) -> PlasticBand | None:
        """The one elasto-plastic band of a linear material, or None."""
        for e in self.effects:
            band = e.plastic_band()
            if band is not None:
                return band
        return None

    def yield_stress(self, q: torch.Tensor) -> torch.Tensor | None:
        """Yield stress ``(b,)`` MPa of the band per member (``inf``: elastic), or None."""
        for e, qe in zip(self.effects, self.split(q), strict=True):
            sy = e.yield_stress(qe)
            if sy is not None:
                return sy
        return None

    def observe(self, V: torch.Tensor, x: torch.Tensor, x_O: float,
                q: torch.Tensor) -> torch.Tensor:
        """Observed ``V`` ``(b, n_time, n_out)`` um; ``x`` ``(n_out,)`` mm."""
        for e, qe in zip(self.effects, self.split(q), strict=True):
            V = e.observe(V, x, x_O, qe)
        return V


def _overrides(e: Effect, hook: str) -> bool:
    return getattr(type(e), hook) is not getattr(Effect, hook)
