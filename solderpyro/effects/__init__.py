"""Library of optional physical effects, one module per effect.

>>> from solderpyro.effects import EFFECTS
>>> eff = EFFECTS["thermal_lag"]
>>> eff.params.names, eff.off
(('tau',), (0.0,))

Every module of this package except :mod:`.base` (the :class:`Effect` base class) defines
``EFFECT``, an instance of an :class:`Effect` subclass; the registry collects them by
``EFFECT.name``, so adding an effect is adding one module. :class:`EffectSet`, the effects
switched on and their composition, lives here beside the registry it resolves names in (the
effect modules import :mod:`.base`, and this package imports them, never the other way).
The solver takes effect names (or instances) through ``SpecimenSolver(..., effects=(...))``;
see docs/effects.md for the physics, boxes and units.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch

from solderpyro.effects.base import Effect, PlasticBand, PreHistory
from solderpyro.fem.loading import ThermalCycle
from solderpyro.params import Box


def _discover() -> dict[str, Effect]:
    out: dict[str, Effect] = {}
    for mod in sorted(m.name for m in pkgutil.iter_modules(__path__)):
        if mod == "base":
            continue
        eff = getattr(importlib.import_module(f"{__name__}.{mod}"), "EFFECT", None)
        if isinstance(eff, Effect):
            out[eff.name] = eff
    return out


#: Registry: effect name -> default :class:`Effect` instance.
EFFECTS: dict[str, Effect] = _discover()


def get_effect(effect: str | Effect) -> Effect:
    """The registered effect named ``effect`` (an :class:`Effect` passes through).

    Raises:
        ValueError: for an unknown name, listing the valid ones.
    """
    if isinstance(effect, Effect):
        return effect
    if effect not in EFFECTS:
        raise ValueError(f"unknown effect {effect!r}; valid effects: {', '.join(sorted(EFFECTS))}")
    return EFFECTS[effect]


def effect_box(effects: Sequence[str | Effect], times: Sequence[float] | None = None,
               bounds: Mapping[str, Mapping[str, Sequence[float]]] | None = None) -> Box:
    """The prior box of the effects' parameters, in column order.

    Args:
        effects: effect names or instances.
        times: output times, s (they fix the number of per-image parameters of an observation
            effect); None keeps each effect's default.
        bounds: per effect name, ``{param: (lower, upper)}`` overrides (see
            :meth:`Effect.with_box`).
    """
    return effect_set(effects, times, bounds).box


def effect_set(effects: Sequence[str | Effect], times: Sequence[float] | None = None,
               bounds: Mapping[str, Mapping[str, Sequence[float]]] | None = None) -> EffectSet:
    """An :class:`EffectSet` of ``effects`` with box overrides ``bounds``, bound to ``times``."""
    bounds = dict(bounds or {})
    for key in bounds:
        get_effect(key)
    effs = [get_effect(e) for e in effects]
    effs = [e.with_box(bounds[e.name]) if e.name in bounds else e for e in effs]
    fx = EffectSet(effs)
    return fx if times is None else fx.bind(times)


class EffectSet:
    """The effects switched on, in order, and their columns of the effect-parameter vector.

    The solver and the model hold one; :meth:`bind` specialises it to the output times (an
    observation effect may have one parameter per image).

    Args:
        effects: effect names (registry keys) or :class:`Effect` instances, no duplicates.
    """

    def __init__(self, effects: Sequence[str | Effect]) -> None:
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
    def pre_history(self) -> PreHistory | None:
        """The one pre-history (:class:`~solderpyro.effects.base.PreHistory`), or None."""
        for e in self.effects:
            ph = e.pre_history()
            if ph is not None:
                return ph
        return None

    def _first_set(self, hook: Callable[[Effect, torch.Tensor], torch.Tensor | None],
                   q: torch.Tensor) -> torch.Tensor | None:
        """``hook(effect, q_effect)`` of the first effect for which it is not None, else None."""
        for e, qe in zip(self.effects, self.split(q), strict=True):
            v = hook(e, qe)
            if v is not None:
                return v
        return None

    def cooldown(self, q: torch.Tensor) -> torch.Tensor:
        """Each member's cool-down ``(b,)`` s: the first effect that sets one, else the
        pre-history's whole duration."""
        c = self._first_set(lambda e, qe: e.cooldown(qe), q)
        if c is not None:
            return c
        ph = self.pre_history()
        return torch.full((q.shape[0],), 1.0 if ph is None else ph.duration_s, dtype=q.dtype,
                          device=q.device)

    def cooldown_shape(self, q: torch.Tensor) -> torch.Tensor | None:
        """Each member's cool-down shape ``(b,)``: the first effect that sets one, else None
        (a constant rate)."""
        return self._first_set(lambda e, qe: e.cooldown_shape(qe), q)

    def stress_free(self, T_ref: float, q: torch.Tensor) -> torch.Tensor:
        """Stress-free temperature ``(b,)`` degC per member."""
        T = torch.full((q.shape[0],), float(T_ref), dtype=q.dtype, device=q.device)
        for e, qe in zip(self.effects, self.split(q), strict=True):
            T = e.stress_free(T, qe)
        return T

    def temperature(self, cycle: ThermalCycle, t: float, T_ref: float,
                    q: torch.Tensor) -> torch.Tensor:
        """Member temperature ``(b,)`` degC at time ``t`` s.

        For ``t < 0`` (the pre-history) the temperature goes from the member's stress-free
        temperature at ``-D`` (its :meth:`cooldown`; before that it rests there) to the
        program's start at 0, as the pre-history's
        :meth:`~solderpyro.effects.base.PreHistory.fraction` shapes it (with the member's
        :meth:`cooldown_shape`; linearly in time where none is set); from
        t = 0 on, the program ``cycle(t)`` transformed by the history hooks.
        """
        if t < 0.0:
            T0 = cycle(0.0)
            ph = self.pre_history()
            s = torch.clamp(-t / self.cooldown(q), max=1.0)
            frac = s if ph is None else ph.fraction(s, self.cooldown_shape(q))
            return T0 + (self.stress_free(T_ref, q) - T0) * frac
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

    @property
    def recovery(self) -> bool:
        """Whether an effect gives the solder's back stress a dynamic recovery (the state then
        carries the lagged rate ``p_rate``)."""
        return any(_overrides(e, "back_stress_recovery") for e in self.effects)

    def back_stress_recovery(self, q: torch.Tensor) -> torch.Tensor | None:
        """Armstrong-Frederick recovery ``(b,)`` (dimensionless) of the solder's back stress per
        member, or None (none: the Prager law)."""
        gamma_k = None
        for e, qe in zip(self.effects, self.split(q), strict=True):
            gamma_k = e.back_stress_recovery(gamma_k, qe)
        return gamma_k

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


__all__ = ["EFFECTS", "Effect", "EffectSet", "PreHistory", "effect_box", "effect_set",
           "get_effect"]
