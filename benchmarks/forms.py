"""Effects in forms other than the library's: the hidden physics of the diagnosis benchmarks.

Real physics never has exactly the library's form. Each form here keeps the name of the
library effect it resembles (so "the hidden effect was selected" means the diagnosis named that
effect) but computes the physics another way; they live in benchmarks/, never in the package,
so the library is not tested against itself.

========================  ===================================================================
form                      differs from the library's effect by
========================  ===================================================================
``modulus_linear``        E(T) = E25 (1 - k (T - 25)), floored at 5 % of E25. The library's
                          family runs from the exponential (its default) to this linear law
                          (n_E = 1, floored at 1 %): the data must move the form nuisance
``lag_second_order``      two first-order lags in series, each tau/2: the library's family at
                          split = 1/2 (its default is one lag, split = 0)
``lag_third_order``       three first-order lags in series, each tau/3: outside the library's
                          family (at most two stages)
``cte_quadratic``         alpha(T) = alpha25 (1 + c (T - 25) + (c (T - 25))^2 / 2) (the
                          library: linear in T)
``stress_free_slow``      stress free at 150 degC, cooled before the cycle by Newton's law
                          (fastest at first) at a mean 1 K/min (the library: a constant rate)
``stress_free_moderate``  the same from 100 degC at a mean 2 K/min
========================  ===================================================================

Each form has one parameter, its size (the library's form parameters have no truth here and
are not counted in the coverage).

:func:`form` returns the :class:`~solderpyro.effects.Effect` instance; ``FORMS`` lists them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from solderpyro.effects.base import PreHistory
from solderpyro.effects.cte_temperature import CteTemperature
from solderpyro.effects.modulus_temperature import K_MAX, ModulusTemperature
from solderpyro.effects.stress_free_temperature import StressFreeTemperature
from solderpyro.effects.thermal_lag import ThermalLag
from solderpyro.fem.loading import ThermalCycle
from solderpyro.params import Box


@dataclass(frozen=True)
class ModulusLinear(ModulusTemperature):
    """Linear softening ``E25 (1 - k_E (T - T0))``, floored at :attr:`floor` of E25."""

    floor: float = 0.05
    form: str = "linear"  # in the run-store hash: never mistaken for the library's runs

    def default_box(self) -> Box:
        """One parameter, the slope ``k_E`` (1/K): the form is fixed here."""
        return Box(("k_E",), (0.0,), (K_MAX,), units=("1/K",))

    @property
    def off(self) -> tuple[float, ...]:
        return (0.0,)

    def check(self, q: torch.Tensor) -> None:
        return None

    def modulus(self, E: torch.Tensor, T: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """``(b,)`` MPa."""
        return E * torch.clamp(1.0 - q[:, 0] * (T - self.T0_C), min=self.floor)


def second_order_lag(cycle: ThermalCycle, t: float, tau: torch.Tensor) -> torch.Tensor:
    """How far ``(b,)`` K two first-order lags in series, each of time constant ``tau / 2``
    (s), leave the temperature below the program ``cycle`` at ``t`` s (closed form per linear
    segment of the program; 0 where ``tau`` is 0).

    On a segment of rate ``r`` the first stage's lag ``e1`` and the stages' difference ``d``
    (``e2 = e1 + d``) evolve, with ``s = tau / 2`` and ``a = exp(-dt / s)``, as
    ``e1 = r s + (e1_0 - r s) a`` and ``d = r s (1 - a) + (e1_0 - r s) (dt / s) a + d_0 a``.
    """
    s = tau / 2.0
    pos = s > 0
    safe = torch.where(pos, s, torch.ones_like(s))
    e1 = torch.zeros_like(tau)
    d = torch.zeros_like(tau)
    kn = cycle.breakpoints
    for ta, tb in zip(kn[:-1], kn[1:], strict=False):
        if ta >= t:
            break
        r = (cycle(tb) - cycle(ta)) / (tb - ta)
        dt = min(t, tb) - ta
        a = torch.where(pos, torch.exp(-dt / safe), torch.zeros_like(s))
        rs = r * s
        e1, d = (rs + (e1 - rs) * a,
                 rs * (1.0 - a) + (e1 - rs) * (dt / safe) * a + d * a)
    return torch.where(pos, e1 + d, torch.zeros_like(tau))


@dataclass(frozen=True)
class LagSecondOrder(ThermalLag):
    """The specimen two first-order lags (each ``tau / 2``) behind the program."""

    form: str = "second order"

    def default_box(self) -> Box:
        """One parameter, the total time constant ``tau`` (s): the form is fixed here."""
        return Box(("tau",), (0.0,), (300.0,), units=("s",))

    @property
    def off(self) -> tuple[float, ...]:
        return (0.0,)

    def check(self, q: torch.Tensor) -> None:
        if bool((q[:, 0] < 0).any()):
            raise ValueError(f"lag_second_order: tau must be >= 0 s, got {q[:, 0].min():g}")

    def temperature(self, T: torch.Tensor, t: float, cycle: ThermalCycle,
                    q: torch.Tensor) -> torch.Tensor:
        """``(b,)`` degC."""
        return T - second_order_lag(cycle, t, q[:, 0])


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
class LagThirdOrder(LagSecondOrder):
    """The specimen three first-order lags (each ``tau / 3``) behind the program."""

    form: str = "third order"

    def temperature(self, T: torch.Tensor, t: float, cycle: ThermalCycle,
                    q: torch.Tensor) -> torch.Tensor:
        """``(b,)`` degC."""
        return T - cascade_lag(cycle, t, q[:, 0], 3)


@dataclass(frozen=True)
class CteQuadratic(CteTemperature):
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

    def fraction(self, s: torch.Tensor) -> torch.Tensor:
        """``(b,)``, 1 at the cool-down's start (``s`` = 1), 0 at t = 0."""
        return torch.expm1(self.a * s) / math.expm1(self.a)


@dataclass(frozen=True)
class StressFreeNewton(StressFreeTemperature):
    """The library's stress-free temperature and cool-down, the cool-down Newtonian
    (:class:`NewtonCooling`)."""

    form: str = "newton"  # in the run-store hash: never mistaken for the library's runs

    def pre_history(self) -> PreHistory:
        ph = super().pre_history()
        return NewtonCooling(ph.duration_s, ph.dT, ph.shortest_s)


def cooldown_s(rate_K_per_min: float, T_sf: float) -> float:
    """The cool-down, s, whose mean rate from ``T_sf`` to 25 degC is ``rate`` K/min."""
    return (T_sf - 25.0) / rate_K_per_min * 60.0


#: form name -> (the effect instance, the library effect it stands for, the hidden values to
#: use (None: sized by :func:`~solderpyro.diagnose.hidden.hidden_values`))
FORMS = {
    "modulus_linear": (ModulusLinear(), "modulus_temperature", None),
    "lag_second_order": (LagSecondOrder(), "thermal_lag", None),
    "lag_third_order": (LagThirdOrder(), "thermal_lag", None),
    "cte_quadratic": (CteQuadratic(), "cte_temperature", None),
    "stress_free_slow": (StressFreeNewton(), "stress_free_temperature",
                         (150.0, cooldown_s(1.0, 150.0))),
    "stress_free_moderate": (StressFreeNewton(), "stress_free_temperature",
                             (100.0, cooldown_s(2.0, 100.0))),
}


def form(name: str) -> tuple[object, str, tuple[float, ...] | None]:
    """``(effect, library name, hidden values or None)`` of form ``name``.

    Raises:
        SystemExit: naming the valid forms for an unknown one.
    """
    if name not in FORMS:
        raise SystemExit(f"unknown form {name!r}; valid: {', '.join(FORMS)}")
    return FORMS[name]
