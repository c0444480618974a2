"""Temperature-dependent CTE of all three materials: a rise whose form the data may inform.

    alpha(T) = alpha25 * (1 + n_alpha * c_alpha * (T - 25 degC)) ** (1 / n_alpha)

One relative coefficient ``c_alpha`` (1/K, off: 0) for steel, solder and copper alike, the
slope of alpha / alpha25 at 25 degC; ``alpha25`` is each material's configured CTE. Their CTEs
rise by a few (steel, copper) to ~10-20 % (Sn37Pb) per 100 K; the box's upper value 3e-3 /K
(+30 % per 100 K) is generous. ``n_alpha`` in [-1, 2] is the rise's form, a nuisance the data
inform: ``n_alpha = 1`` the linear rise (the default), ``n_alpha = 0`` the exponential
``alpha25 exp(c_alpha (T - 25))``, ``n_alpha = -1`` the hyperbola ``alpha25 / (1 - c_alpha
(T - 25))`` (convex), ``n_alpha = 2`` the square root ``alpha25 sqrt(1 + 2 c_alpha (T - 25))``
(concave: a CTE that levels off). Measured CTE curves are fitted by quadratics
``alpha25 (1 + c u + k (c u)^2)``, ``u = T - 25``, of either curvature; to second order in
``c u`` the family holds every one with ``k`` from -1/2 to 1 (``n_alpha = 1 - 2 k``). At
the box's top and 183 degC the exponential law's strain above the constant CTE's is 18 % more
than the linear law's (the square root's 12 % less), so a form fixed at the linear one would
leave c_alpha (the slope at 25 degC) to take the chord of the data's curve instead. Every
member of the family has the same slope at 25 degC, so the diagnosis's score test at "off"
(c_alpha = 0, where n_alpha changes nothing) is the same for all of them.

The free thermal strain is the integral from the stress-free temperature T_ref,

    eps_th = int_{T_ref}^{T} alpha = alpha25 * [(T - T_ref) + G(T - 25) - G(T_ref - 25)],
    G(u) = int_0^u ((1 + n c v)^(1/n) - 1) dv = ((1 + n c u)^((n+1)/n) - 1) / (c (n + 1)) - u,

added to the baseline ``alpha25 (T - T_ref)`` as the second term (:func:`excess_strain`; at
n = 1, ``G = c u^2 / 2``). It enters the solder update and the condensed thermal loads and
observation offsets of the bars. The power needs ``1 + n c (T - 25) > 0``: at the box's
corners down to -141 degC (n = 2) and up to 358 degC (n = -1); :meth:`CteTemperature.check`
rejects members for which it fails between :data:`T_COLDEST_C` and :data:`T_HOTTEST_C`.
Seam: the material laws (thermal strain).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from solderpyro.effects.base import Effect
from solderpyro.effects.power import log_power
from solderpyro.params import Box

#: the form's box: -1 hyperbolic, 0 exponential, 1 linear (the default), 2 square root
N_MIN, N_MAX = -1.0, 2.0
#: the coldest temperature a member's law must hold at, degC (JEDEC's coldest cycling
#: condition, -65 degC)
T_COLDEST_C = -65.0
#: ... and the hottest, degC: the Sn37Pb eutectic (the solder melts above it)
T_HOTTEST_C = 183.0
#: below this |c u| the excess strain is its series (the first dropped term is
#: ``|z|^4 / 120`` of ``z / 2``: < 2e-14 relative); above it the closed form loses at most
#: ``2 eps / |z|``, about 4e-13 relative
_Z_SERIES = 1e-3
#: below this |(n + 1) L| the integral's ``expm1((n+1) L) / (n+1)`` is its series (the dropped
#: term is ``(aL)^3 / 24`` of it: < 5e-14 relative)
_A_SERIES = 1e-4


def excess_strain(u: torch.Tensor, c: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """``G(u) = int_0^u ((1 + n c v)^(1/n) - 1) dv`` ``(b,)`` K for ``u = T - 25`` ``(b,)`` K,
    ``c = c_alpha`` ``(b,)`` 1/K and the form ``n = n_alpha`` ``(b,)``: what the family's
    alpha / alpha25 adds to the constant CTE's strain, per unit alpha25.

    Written as ``u g(z)``, ``z = c u``: ``g = expm1((n+1) L) / ((n+1) z) - 1`` with
    ``L = log1p(n z) / n`` (:func:`~solderpyro.effects.power.log_power`: the exponential n = 0
    exact; ``expm1((n+1) L) / (n+1)`` by its series near n = -1, where it is ``L``, the
    hyperbola's logarithm), and for ``|z|`` below 1e-3 its series
    ``z/2 + (1-n) z^2/6 + (1-n)(1-2n) z^3/24 + (1-n)(1-2n)(1-3n) z^4/120``; every branch's
    argument is masked so that gradients stay finite at c = 0.
    """
    z = c * u
    small = z.abs() < _Z_SERIES
    zs = torch.where(small, torch.full_like(z, _Z_SERIES), z)
    L = log_power(zs, n)
    # expm1(a L) / a with a = n + 1, its series where a L is small (n = -1: the logarithm)
    a = n + 1.0
    aL = a * L
    near = aL.abs() < _A_SERIES
    As = torch.where(near, torch.ones_like(a), a)
    h = torch.where(near, L * (1.0 + aL / 2.0 + aL * aL / 6.0), torch.expm1(As * L) / As)
    closed = h / zs - 1.0
    a1, a2, a3 = 1.0 - n, 1.0 - 2.0 * n, 1.0 - 3.0 * n
    series = z * (0.5 + z * (a1 / 6.0 + z * (a1 * a2 / 24.0 + z * a1 * a2 * a3 / 120.0)))
    return u * torch.where(small, series, closed)


@dataclass(frozen=True)
class CteTemperature(Effect):
    """Rise of every material's CTE with temperature: size ``c_alpha`` (1/K), form
    ``n_alpha`` (-).

    Attributes:
        T0_C: temperature at which the configured CTEs hold, degC.
    """

    name = "cte_temperature"
    seam = "material laws (thermal strain)"
    transfers = True
    nuisance = ("n_alpha",)
    T0_C: float = 25.0

    def default_box(self) -> Box:
        return Box(("c_alpha", "n_alpha"), (0.0, N_MIN), (3e-3, N_MAX), units=("1/K", "-"))

    @property
    def off(self) -> tuple[float, ...]:
        return (0.0, 1.0)

    def check(self, q: torch.Tensor) -> None:
        n = q[:, 1]
        if bool(((n < N_MIN) | (n > N_MAX)).any()):
            raise ValueError(f"cte_temperature: n_alpha (the rise's form: -1 hyperbolic, 0 "
                             f"exponential, 1 linear, 2 square root) must be within "
                             f"[{N_MIN:g}, {N_MAX:g}], got {n.min().item():g} to "
                             f"{n.max().item():g}")
        nc = n * q[:, 0]
        base = torch.minimum(1.0 + nc * (T_COLDEST_C - self.T0_C),
                             1.0 + nc * (T_HOTTEST_C - self.T0_C))
        if bool((base <= 0).any()):
            raise ValueError(f"cte_temperature: n_alpha * c_alpha reaches "
                             f"{nc.min().item():g} to {nc.max().item():g} /K: the CTE would "
                             f"vanish between {T_COLDEST_C:g} and {T_HOTTEST_C:g} degC "
                             f"(1 + n_alpha c_alpha (T - 25) must stay > 0); narrow the box "
                             f"of c_alpha or n_alpha")

    def thermal_strain(self, eps: torch.Tensor, alpha: float, T: torch.Tensor,
                       T_ref: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """``eps + alpha (G(T - T0) - G(T_ref - T0))`` ``(b,)`` (:func:`excess_strain`)."""
        c, n = q[:, 0], q[:, 1]
        return eps + alpha * (excess_strain(T - self.T0_C, c, n)
                              - excess_strain(T_ref - self.T0_C, c, n))


EFFECT = CteTemperature()
