"""Thermal lag: the specimen temperature follows the chamber program through one or two
first-order stages in series, a form the data may inform.

    dT1/dt = (T_prog(t) - T1) / tau_1,   dT/dt = (T1 - T) / tau_2,   T1(0) = T(0) = T_prog(0)

with ``tau_1 = (1 - s) tau`` and ``tau_2 = s tau``: ``tau >= 0`` s sizes the lag (off: 0) and
the split ``s`` in [0, 1/2] is its form. ``s = 0`` is one first-order lag (a lumped heat
capacity, the default); ``s = 1/2`` two equal stages (a second-order, critically damped lag:
the chamber air and the fixture, or a surface and a core). Which holds is rarely known; on a
ramp of rate ``r`` every split trails the program by the same ``r tau`` once settled (the
stages' lags add), but the split changes how ramps start and dwells settle, which the data see
when tau is large. (The cascade of linear stages commutes, so ``s`` and ``1 - s`` are the same
law and ``s <= 1/2`` covers all.)

Uniform over the specimen (copper and steel bars conduct fast compared with the chamber's
convection). On a linear segment of the program the lags ``e1 = T_prog - T1`` and
``e = T_prog - T`` solve ``de1/dt = r - e1/tau_1``, ``de/dt = r - (e - e1)/tau_2`` in closed
form: with ``a_i = exp(-dt/tau_i)``,

    e1(t) = r tau_1 + (e1_a - r tau_1) a_1,
    e(t)  = r tau + (e_a - r tau) a_2 + (e1_a - r tau_1) tau_1 (a_1 - a_2) / (tau_1 - tau_2),

where ``(a_1 - a_2) / (tau_1 - tau_2)`` is evaluated through ``expm1`` when the stages are
close (its limit at ``tau_1 = tau_2`` is ``a dt / tau_i^2``), and is ``a_1 / tau_1`` at
``tau_2 = 0`` (then ``e = e1``: the first-order lag exactly). So ramps end ``~ r tau`` below
their target and dwells approach it exponentially. At ``tau = 0`` the exponentials are replaced
by their limit 0 (also in the derivative), so the program is recovered exactly and
``de/dtau = r`` there (the one-sided derivative).
Seam: the temperature history (per batch member).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from solderpyro.effects.base import Effect
from solderpyro.fem.loading import ThermalCycle
from solderpyro.params import Box

#: the split's largest value: two equal stages
SPLIT_MAX = 0.5
#: stages closer than this fraction of tau_1 use the expm1 form of the divided difference
_CLOSE = 1e-3


def _divided_difference(a1: torch.Tensor, a2: torch.Tensor, t1: torch.Tensor, t2: torch.Tensor,
                        dt: float) -> torch.Tensor:
    """``(a1 - a2) / (t1 - t2)`` ``(b,)`` 1/s for ``a_i = exp(-dt / t_i)``, ``t1 > 0``, ``t2 >= 0``.

    Direct where the stages differ by more than :data:`_CLOSE` of ``t1``; else
    ``a2 * dt / (t1 t2) * expm1(x) / x`` with ``x = dt (t1 - t2) / (t1 t2)`` (no cancellation;
    ``expm1(x) / x`` by its series ``1 + x/2 + x^2/6`` below |x| = 1e-5, error < 1e-16).
    """
    d = t1 - t2
    far = d > _CLOSE * t1
    direct = (a1 - a2) / torch.where(far, d, torch.ones_like(d))
    t2s = torch.where(far, torch.ones_like(t2), t2)
    t1s = torch.where(far, torch.ones_like(t1), t1)
    x = torch.where(far, torch.zeros_like(d), dt * d / (t1s * t2s))
    tiny = x.abs() < 1e-5
    xs = torch.where(tiny, torch.ones_like(x), x)
    phi = torch.where(tiny, 1.0 + x / 2.0 + x * x / 6.0, torch.expm1(xs) / xs)
    close = a2 * dt / (t1s * t2s) * phi
    return torch.where(far, direct, close)


def lag(cycle: ThermalCycle, t: float, tau: torch.Tensor,
        split: torch.Tensor | None = None) -> torch.Tensor:
    """Lag ``T_prog(t) - T(t)`` ``(b,)`` K of the specimen behind the program.

    Args:
        cycle: the piecewise-linear program (degC, s); the system starts on it at ``times[0]``.
        t: time, s (clamped to the program's span).
        tau: ``(b,)`` total time constants, s (>= 0; 0 means no lag).
        split: ``(b,)`` share of ``tau`` in the second stage, in [0, 1/2]; None or 0 is the
            first-order lag.
    """
    if split is None:
        split = torch.zeros_like(tau)
    pos = tau > 0
    t1 = (1.0 - split) * tau  # the stages; their where-masked copies below are only divided
    t2 = split * tau          # by, so d e / d tau at tau = 0 stays the program's rate r
    t1s = torch.where(pos, t1, torch.ones_like(tau))
    two = pos & (t2 > 0)
    t2s = torch.where(two, t2, torch.ones_like(t2))
    zero = torch.zeros_like(tau)
    # the second stage where there is one, and (for the one-stage branch below) where not
    t2_two, t2_one = torch.where(two, t2, zero), torch.where(two, zero, t2)
    e1 = torch.zeros_like(tau)
    e = torch.zeros_like(tau)
    kn, Tk = cycle.times, cycle.temps_C
    for i in range(len(kn) - 1):
        ta, tb = kn[i], kn[i + 1]
        if t <= ta:
            break
        r = (Tk[i + 1] - Tk[i]) / (tb - ta)
        dt = min(t, tb) - ta
        a1 = torch.where(pos, torch.exp(-dt / t1s), zero)
        a2 = torch.where(two, torch.exp(-dt / t2s), zero)
        # one stage: a2 = 0 and (a1 - a2) / (t1 - t2) = a1 / (t1 - t2) with t2 = 0, written
        # with t2 so that the one-sided derivative in the split at 0 is the two stages' one
        g = torch.where(two, _divided_difference(a1, a2, t1s, t2_two, dt), a1 / (t1s - t2_one))
        rt1, rt = r * t1, r * tau
        e1, e = (rt1 + (e1 - rt1) * a1,
                 rt + (e - rt) * a2 + (e1 - rt1) * t1 * g)
    return e


@dataclass(frozen=True)
class ThermalLag(Effect):
    """Thermal lag of the specimen behind the program: size ``tau`` (s), form ``split`` (-)."""

    name = "thermal_lag"
    seam = "temperature history"
    nuisance = ("split",)

    def default_box(self) -> Box:
        # a 9 mm thick steel/copper stack in a forced-convection chamber: tens of seconds to
        # a few minutes; 300 s leaves the 75 degC dwell start ~22 K short of its target
        return Box(("tau", "split"), (0.0, 0.0), (300.0, SPLIT_MAX), units=("s", "-"))

    @property
    def off(self) -> tuple[float, ...]:
        return (0.0, 0.0)

    def check(self, q: torch.Tensor) -> None:
        if bool((q[:, 0] < 0).any()):
            raise ValueError(f"thermal_lag: tau must be >= 0 s, got {q[:, 0].min().item():g}")
        s = q[:, 1]
        if bool(((s < 0) | (s > SPLIT_MAX)).any()):
            raise ValueError(f"thermal_lag: split (the second stage's share of tau) must be "
                             f"within [0, {SPLIT_MAX:g}], got {s.min().item():g} to "
                             f"{s.max().item():g}")

    def temperature(self, T: torch.Tensor, t: float, cycle: ThermalCycle,
                    q: torch.Tensor) -> torch.Tensor:
        """``T - lag`` ``(b,)`` degC (``T`` is the program's value at ``t``)."""
        return T - lag(cycle, t, q[:, 0], q[:, 1])


EFFECT = ThermalLag()
