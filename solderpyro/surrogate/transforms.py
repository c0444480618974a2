"""Explicit, invertible output standardization (the input map lives on :class:`params.Box`)."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class Standardizer:
    """Per-column affine map ``z = (y - mean) / scale``.

    Attributes:
        mean: ``(n_y,)`` column means of the training outputs.
        scale: ``(n_y,)`` column standard deviations (1 where a column is constant).
    """

    mean: torch.Tensor
    scale: torch.Tensor

    @classmethod
    def fit(cls, y: torch.Tensor) -> Standardizer:
        """From training outputs ``(n, n_y)``."""
        sd = y.std(0) if y.shape[0] > 1 else torch.ones_like(y[0])
        return cls(y.mean(0), torch.where(sd > 0, sd, torch.ones_like(sd)))

    def forward(self, y: torch.Tensor) -> torch.Tensor:
        """``(..., n_y)`` physical -> standardized."""
        return (y - self.mean) / self.scale

    def inverse(self, z: torch.Tensor) -> torch.Tensor:
        """``(..., n_y)`` standardized -> physical."""
        return self.mean + z * self.scale
