"""Stationary correlation functions as pure torch functions (differentiable, batched).

Parameterizations follow the seed and GPyTorch:
- ``gaussian``: R = exp(-sum_k theta_k (x_k - x'_k)^2)  (seed Eq. 4; GPyTorch's RBF with
  theta = 1 / (2 lengthscale^2)).
- ``matern52``: r = ||(x - x') / lengthscale||, R = (1 + sqrt5 r + 5 r^2 / 3) exp(-sqrt5 r).
"""

from __future__ import annotations

import math

import torch


def sqdist(x1: torch.Tensor, x2: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Weighted squared distances.

    Args:
        x1: ``(..., n1, d)``; x2: ``(..., n2, d)``; w: weights ``(..., d)`` or ``(..., 1)``.

    Returns:
        ``(..., n1, n2)``: sum_k w_k (x1_k - x2_k)^2.
    """
    diff = x1.unsqueeze(-2) - x2.unsqueeze(-3)  # (..., n1, n2, d)
    return (diff.square() * w.unsqueeze(-2).unsqueeze(-2)).sum(-1)


def gaussian(x1: torch.Tensor, x2: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """Gaussian correlation ``exp(-sum_k theta_k dx_k^2)``; theta ``(..., d)`` or ``(..., 1)``."""
    return torch.exp(-sqdist(x1, x2, theta))


def matern52(x1: torch.Tensor, x2: torch.Tensor, lengthscale: torch.Tensor) -> torch.Tensor:
    """Matern 5/2 correlation; lengthscale ``(..., d)`` or ``(..., 1)``; returns ``(..., n1, n2)``.

    The distance is clamped below at 1e-15 so the gradient at coincident points is finite.
    """
    r = sqdist(x1, x2, lengthscale.pow(-2)).clamp_min(1e-30).sqrt()
    s5r = math.sqrt(5.0) * r
    return (1.0 + s5r + s5r.square() / 3.0) * torch.exp(-s5r)


KERNELS = {"gaussian": gaussian, "matern52": matern52}
