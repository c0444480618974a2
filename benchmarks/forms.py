"""Effects in forms other than the library's: the hidden physics of the diagnosis benchmarks.

Real physics never has exactly the library's form. Each form here keeps the name of the
library effect it resembles (so "the hidden effect was selected" means the diagnosis named that
effect) but computes the physics another way; they live in benchmarks/, never in the package,
so the library is not tested against itself.

========================  ===================================================================
form                      differs from the library's effect by
========================  ===================================================================
``modulus_linear``        E(T) = E25 (1 - k (T - 25)), floored at 5 % of E25: the library's
                          family at n_E = 1, r_E = 0.05 (its default is the exponential
                          approaching a 1 % plateau): the data must move both form nuisances
``lag_second_order``      two first-order lags in series, each tau/2: the library's family at
                          split = 1/2 (its default is one lag, split = 0)
``lag_third_order``       three first-order lags in series, each tau/3: outside the library's
                          family (at most two stages)
``cte_quadratic``         alpha(T) = alpha25 (1 + c (T - 25) + (c (T - 25))^2 / 2). The
                          library's family runs from the exponential through the linear law
                          (its default) to the square root: the exponential agrees with this
                          to second order in c (T - 25) and differs at the third
``stress_free_slow``      stress free at 150 degC, cooled before the cycle by Newton's law
                          (exponential in time, fastest at first) at a mean 1 K/min (the
                          library: a power of time, from a constant rate to three times the
                          mean rate at first)
``stress_free_moderate``  the same from 100 degC at a mean 2 K/min
``kinematic_af``          an Armstrong-Frederick back stress with a fixed recovery gamma_k = 50
                          (saturating at C_k / 50), sized by C_k: the library's family at
                          gamma_k = 50 (its default is Prager, gamma_k = 0)
========================  ===================================================================

Each form has one parameter, its size (:class:`FixedForm`: the library's form parameters have
no truth here, are not in a form's box and are not counted in the coverage); the residual
stress keeps its cool-down's duration too, and fixes only the cool-down's shape.

:func:`form` returns the :class:`~solderpyro.effects.Effect` instance; ``FORMS`` lists them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import ClassVar

import torch

from solderpyro.effects.base import Effect, PreHistory
from solderpyro.effects.cte_temperature import CteTemperature
from solderpyro.effects.kinematic_hardening import KinematicHardening
from solderpyro.effects.modulus_temperature import ModulusTemperature
from solderpyro.effects.stress_free_temperature import StressFreeTemperature
from solderpyro.effects.thermal_lag import ThermalLag
from solderpyro.fem.loading import ThermalCycle
from solderpyro.params import Box


class FixedForm:
    """Mixin (listed before the library effect) for a form that fixes the library effect's
    form parameters :attr:`FIXED` (all of :attr:`Effect.nuisance` where None): they have no
    meaning in a form that fixes its own shape, so they leave its box, its "off" values and
    any box the config gives (:meth:`with_box` drops them). The library's :meth:`check`
    sees them at their "off" values."""

    FIXED: ClassVar[tuple[str, ...] | None] = None

    def _fixed(self) -> tuple[str, ...]:
        return self.nuisance if self.FIXED is None else self.FIXED  # type: ignore[attr-defined]

    def _kept(self) -> list[int]:
        lib = super().default_box()  # type: ignore[misc]
        return [i for i, nm in enumerate(lib.names) if nm not in self._fixed()]

    def default_box(self) -> Box:
        """The library effect's box without its form parameters."""
        lib, k = super().default_box(), self._kept()  # type: ignore[misc]
        pick = lambda xs: tuple(xs[i] for i in k) if xs else ()  # noqa: E731
        return Box(pick(lib.names), pick(lib.lower), pick(lib.upper), pick(lib.log_scale),
                   pick(lib.units))

    @property
    def off(self) -> tuple[float, ...]:
        lib_off = super().off  # type: ignore[misc]
        return tuple(lib_off[i] for i in self._kept())

    def with_box(self, bounds: Mapping[str, Sequence[float]]) -> Effect:
        """:meth:`Effect.with_box` without the library's form parameters (an unknown name
        still raises)."""
        fixed = self._fixed()
        return super().with_box(  # type: ignore[misc]
            {k: v for k, v in bounds.items() if k not in fixed})

    def check(self, q: torch.Tensor) -> None:
        """The library's check, the form parameters at their "off" values."""
        lib_off = torch.tensor(super().off, dtype=q.dtype)  # type: ignore[misc]
        full = lib_off.expand(len(q), len(lib_off)).clone()
        full[:, self._kept()] = q
        super().check(full)  # type: ignore[misc]


@dataclass(frozen=True)
class ModulusLinear(FixedForm, ModulusTemperature):
    """Linear softening ``E25 (1 - k_E (T - T0))``, floored at :attr:`floor` of E25."""

    floor: float = 0.05
    form: str = "linear"  # in the run-store hash: never mistaken for the library's runs

    def modulus(self, E: torch.Tensor, T: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """``(b,)`` MPa."""
        return E * torch.clamp(1.0 - q[:, 0] * (T - self.T0_C), min=self.floor)


@dataclass(frozen=True)
class KinematicAF(FixedForm, KinematicHardening):
    """Armstrong-Frederick back stress with the fixed recovery :attr:`gamma_k` (saturation at
    ``C_k / gamma_k``), sized by ``C_k`` alone."""

    gamma_k: float = 50.0  # in the run-store hash: never mistaken for the library's runs

    def back_stress_recovery(self, gamma_k: torch.Tensor | None,
                             q: torch.Tensor) -> torch.Tensor:
        """``(b,)``: :attr:`gamma_k` for every member (dimensionless)."""
        return torch.full((q.shape[0],), self.gamma_k, dtype=q.dtype, device=q.device)


def cascade_lag(cycle: ThermalCycle, t: float, tau: torch.Tensor, stages: int) -> torch.Tensor:
    """How far ``(b,)`` K ``stages`` equal first-order lags in series, each ``tau / stages``
    (s), leave the temperature below the program at ``t`` s: the lags ``e_k = T_prog - T_k``
    solve ``de_1/dt = r - e_1/s``, ``de_k/dt = r - (e_k - e_(k-1))/s``, propagated exactly over
    each linear segment of the program by the matrix exponential of the system augmented with
    the constant rate (0 where ``tau`` is 0)."""
    s = tau / stages
    pos = s > 0
    inv = torch.where(pos, 1.0 / torch.where(pos, s, torch.ones_like(s)), torch.zeros_like(s))
    b, n = len(tau), stages + 1
    A = torch.zeros(b, n, n, dtype=tau.dtype)
    for k in range(stages):
        A[:, k, k] = -inv
        if k:
            A[:, k, k - 1] = inv
        A[:, k, stages] = 1.0  # d e_k / dt gets + r, the last state
    z = torch.zeros(b, n, dtype=tau.dtype)
    kn = cycle.breakpoints
    for ta, tb in zip(kn[:-1], kn[1:], strict=False):
        if ta >= t:
            break
        r = (cycle(tb) - cycle(ta)) / (tb - ta)
        z = z.clone()
        z[:, stages] = r
        z = (torch.matrix_exp(A * (min(t, tb) - ta)) @ z[:, :, None])[:, :, 0]
    return torch.where(pos, z[:, stages - 1], torch.zeros_like(tau))


@dataclass(frozen=True)
class LagCascade(FixedForm, ThermalLag):
    """The specimen :attr:`stages` equal first-order lags (each ``tau / stages``) behind the
    program (:func:`cascade_lag`)."""

    stages: int = 2  # in the run-store hash

    def temperature(self, T: torch.Tensor, t: float, cycle: ThermalCycle,
                    q: torch.Tensor) -> torch.Tensor:
        """``(b,)`` degC."""
        return T - cascade_lag(cycle, t, q[:, 0], self.stages)


@dataclass(frozen=True)
class CteQuadratic(FixedForm, CteTemperature):
    """``alpha(T) = alpha25 (1 + c u + (c u)^2 / 2)``, ``u = T - T0``: the thermal strain is
    its integral from the stress-free temperature."""

    form: str = "quadratic"

    def thermal_strain(self, eps: torch.Tensor, alpha: float, T: torch.Tensor,
                       T_ref: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """``(b,)``: the baseline ``eps`` plus ``alpha`` times the integral of
        ``c u + (c u)^2 / 2`` from ``T_ref`` to ``T``."""
        c = q[:, 0]
        T0 = self.T0_C

        def F(x: torch.Tensor) -> torch.Tensor:
            u = x - T0
            return c * u**2 / 2.0 + c**2 * u**3 / 6.0

        return eps + alpha * (F(T) - F(T_ref))


@dataclass(frozen=True)
class NewtonCooling(PreHistory):
    """A cool-down that slows as it nears the room (Newton's law of cooling: the temperature
    relaxes exponentially, fastest at the start), instead of the library's constant rate:
    ``(T - T_start) / (T_sf - T_start) = expm1(a s) / expm1(a)`` at the share ``s`` of the
    cool-down still to run; its fastest rate is ``a e^a / (e^a - 1)`` times the mean."""

    a: float = 3.0

    @property
    def peak_rate(self) -> float:
        return self.a * math.exp(self.a) / math.expm1(self.a)

    def fraction(self, s: torch.Tensor, shape: torch.Tensor | None = None) -> torch.Tensor:
        """``(b,)``, 1 at the cool-down's start (``s`` = 1), 0 at t = 0 (``shape``: none
        here, the form is fixed)."""
        return torch.expm1(self.a * s) / math.expm1(self.a)


@dataclass(frozen=True)
class StressFreeNewton(FixedForm, StressFreeTemperature):
    """The library's stress-free temperature and cool-down duration, the cool-down Newtonian
    (:class:`NewtonCooling`) instead of the library's shapes."""

    FIXED = ("cooldown_shape",)
    form: str = "newton"  # in the run-store hash: never mistaken for the library's runs

    def cooldown_shape(self, q: torch.Tensor) -> torch.Tensor | None:
        """None: the shape is :class:`NewtonCooling`'s."""
        return None

    def pre_history(self) -> PreHistory:
        ph = super().pre_history()
        return NewtonCooling(ph.duration_s, ph.dT, ph.shortest_s)


def cooldown_s(rate_K_per_min: float, T_sf: float) -> float:
    """The cool-down, s, whose mean rate from ``T_sf`` to 25 degC is ``rate`` K/min."""
    return (T_sf - 25.0) / rate_K_per_min * 60.0


#: form name -> (the effect instance, the library effect it stands for, the hidden values to
#: use (None: sized by :func:`~solderpyro.diagnose.hidden.hidden_values`))
FORMS: dict[str, tuple[Effect, str, tuple[float, ...] | None]] = {
    "modulus_linear": (ModulusLinear(), "modulus_temperature", None),
    "lag_second_order": (LagCascade(stages=2), "thermal_lag", None),
    "lag_third_order": (LagCascade(stages=3), "thermal_lag", None),
    "cte_quadratic": (CteQuadratic(), "cte_temperature", None),
    "stress_free_slow": (StressFreeNewton(), "stress_free_temperature",
                         (150.0, cooldown_s(1.0, 150.0))),
    "stress_free_moderate": (StressFreeNewton(), "stress_free_temperature",
                             (100.0, cooldown_s(2.0, 100.0))),
    "kinematic_af": (KinematicAF(), "kinematic_hardening", None),
}


def form(name: str) -> tuple[Effect, str, tuple[float, ...] | None]:
    """``(effect, library name, hidden values or None)`` of form ``name``.

    Raises:
        SystemExit: naming the valid forms for an unknown one.
    """
    if name not in FORMS:
        raise SystemExit(f"unknown form {name!r}; valid: {', '.join(FORMS)}")
    return FORMS[name]
