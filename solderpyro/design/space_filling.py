"""Designs of experiments over a parameter box (what the FE runs are computed at).

A design is drawn in the unit cube and mapped through :meth:`~solderpyro.params.Box.from_unit`,
so parameters flagged ``log_scale`` are spread evenly in their logarithm.

>>> from solderpyro.params import ParameterSpace
>>> space = ParameterSpace.seed()                   # s0, QR, xi, m
>>> theta = lhs(space, 8, seed=0)                   # (8, 4), MPa, K, -, -
>>> params = space.full(theta)                      # (8, 9) for the FE solver / run store
"""

from __future__ import annotations

import torch
from scipy.stats import qmc

from solderpyro.params import Box


def lhs(box: Box, n: int, seed: int | None = 0, dtype: torch.dtype = torch.float64,
        device: str | torch.device = "cpu") -> torch.Tensor:
    """Latin hypercube of ``n`` points over ``box``, in physical units.

    Each of the ``n`` equal-probability strata of every coordinate (in the unit cube, i.e. in
    ``log`` for log-scale coordinates) holds exactly one point. The same ``seed`` gives the same
    design in every process, which is what lets a rerun of a DOE reuse its stored runs.

    Args:
        box: the inputs (names, bounds, log-scale); ``dim = box.dim``.
        n: number of points (>= 1).
        seed: seed of scipy's generator (``None``: fresh entropy, not reproducible).
        dtype, device: of the returned tensor.

    Returns:
        ``(n, dim)`` tensor in the units of ``box`` (e.g. MPa, K for the Anand constants),
        inside ``[lower, upper]`` column by column.
    """
    if n < 1:
        raise ValueError(f"lhs needs n >= 1 points, got {n}")
    u = qmc.LatinHypercube(d=box.dim, seed=seed).random(n)  # (n, dim) in [0, 1)
    x = box.from_unit(torch.as_tensor(u, dtype=torch.float64))  # (n, dim), physical
    lo = torch.tensor(box.lower, dtype=torch.float64)
    hi = torch.tensor(box.upper, dtype=torch.float64)
    x = torch.minimum(torch.maximum(x, lo), hi)  # exp(log(lo)) may round just outside the box
    return x.to(dtype=dtype, device=device)
