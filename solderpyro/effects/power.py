"""The power family ``(1 + n z) ** (1 / n)`` that the form parameters of two effects run along.

The modulus law's curvature ``n_E`` (:mod:`~solderpyro.effects.modulus_temperature`) and the
CTE rise's form ``n_alpha`` (:mod:`~solderpyro.effects.cte_temperature`) each choose a member
of this family: ``n = 1`` the linear ``1 + z``, ``n = 0`` the exponential ``exp(z)`` (its
limit), ``n = 2`` the square root, ``n = -1`` the hyperbola ``1 / (1 - z)``. Both need its
logarithm with the exponential exact and the derivative in ``n`` smooth through 0.

Units: dimensionless.
"""

from __future__ import annotations

import torch

#: below this |n| the logarithm is its series about the exponential (the dropped term is
#: ``n^2 z^3 / 3``: < 2e-11 of ``z`` for |z| <= 7.3, the modulus law's largest, k_E (T - 25)
#: / (1 - r_E) at the top of its boxes and 183 degC)
N_SERIES = 1e-6


def log_power(z: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """``log((1 + n z) ** (1 / n))`` ``(b,)`` for ``z`` ``(b,)`` and ``n`` ``(b,)``, where
    ``1 + n z > 0``.

    ``log1p(n z) / n`` (log1p keeps the digits of a small ``n z``); for ``|n|`` below
    :data:`N_SERIES` its series ``z - n z^2 / 2``, so ``n = 0`` gives ``z`` exactly and the
    derivative in ``n`` there is ``-z^2 / 2``. The branch not taken is evaluated at
    arguments that keep it finite, so gradients are finite everywhere.
    """
    tiny = n.abs() < N_SERIES
    ns = torch.where(tiny, torch.ones_like(n), n)
    zs = torch.where(tiny, torch.zeros_like(z), z)
    return torch.where(tiny, z - n * z * z / 2.0, torch.log1p(ns * zs) / ns)
