"""Library of optional physical effects (issue 6 section 2), one module per effect.

>>> from solderpyro.effects import EFFECTS
>>> eff = EFFECTS["thermal_lag"]
>>> eff.params.names, eff.off
(('tau',), (0.0,))

Every module of this package except :mod:`.base` defines ``EFFECT``, an instance of an
:class:`Effect` subclass; the registry collects them by ``EFFECT.name``, so adding an effect is
adding one module. The solver takes effect names (or instances) through
``SpecimenSolver(..., effects=(...))``; see docs/effects.md for the physics, boxes and units.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Mapping, Sequence

from ..params import Box
from .base import Effect, EffectSet


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


__all__ = ["EFFECTS", "Effect", "EffectSet", "effect_box", "effect_set", "get_effect"]
