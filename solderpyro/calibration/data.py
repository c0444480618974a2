"""Calibration data in SEPIA's vocabulary: x_sim, theta_sim, y_sim, x_obs, y_obs."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from solderpyro.params import Box


def check_tensor(name: str, t: torch.Tensor, ndim: int) -> torch.Tensor:
    """Validate a data tensor: right number of dims, non-empty, finite. Returns ``t``."""
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if t.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimension(s), got shape {tuple(t.shape)}")
    if t.shape[0] == 0:
        raise ValueError(f"{name} is empty")
    if not torch.isfinite(t).all():
        bad = torch.nonzero(~torch.isfinite(t.reshape(t.shape[0], -1)).all(-1)).flatten()
        raise ValueError(f"{name} contains NaN or inf in rows {bad[:10].tolist()}")
    return t


@dataclass(frozen=True)
class InputAxes:
    """Names and boxes of the two kinds of input, x (controllable) and theta (calibrated).

    Attributes:
        x_names: names of the ``n_x`` columns of x (default ``x1, x2, ...``).
        theta_names: names of the ``n_theta`` columns of theta (default ``t1, t2, ...``).
        theta_box: box of theta, the support of its flat prior (default: range of the runs).
        x_box: box of x (default: around the runs' and the observations' x).
    """

    x_names: Sequence[str] | None = None
    theta_names: Sequence[str] | None = None
    theta_box: Box | None = None
    x_box: Box | None = None


@dataclass(frozen=True)
class CalibrationData:
    """Computer runs and observations of one scalar response (the seed's joint data).

    Attributes:
        x_sim: ``(n_sim, n_x)`` controllable inputs of the runs.
        theta_sim: ``(n_sim, n_theta)`` calibration inputs of the runs (physical units).
        y_sim: ``(n_sim,)`` run outputs.
        x_obs: ``(n_obs, n_x)`` controllable inputs of the observations.
        y_obs: ``(n_obs,)`` observed outputs (same units as ``y_sim``).
        x_box: box of x (default: around x_sim and x_obs).
        theta_box: box of theta, also the support of its flat prior (default: range of the runs).
    """

    x_sim: torch.Tensor
    theta_sim: torch.Tensor
    y_sim: torch.Tensor
    x_obs: torch.Tensor
    y_obs: torch.Tensor
    x_box: Box
    theta_box: Box

    @classmethod
    def create(cls, x_sim: torch.Tensor, theta_sim: torch.Tensor, y_sim: torch.Tensor,
               x_obs: torch.Tensor, y_obs: torch.Tensor, axes: InputAxes | None = None
               ) -> CalibrationData:
        """Validate shapes and values, fill default names and boxes; errors name the argument.

        Args:
            x_sim: ``(n_sim, n_x)``; theta_sim: ``(n_sim, n_theta)``; y_sim: ``(n_sim,)``.
            x_obs: ``(n_obs, n_x)``; y_obs: ``(n_obs,)`` (units of ``y_sim``).
            axes: the inputs' names and boxes (:class:`InputAxes`; None: all defaults).
        """
        ax = axes or InputAxes()
        for nm, t, nd in (("x_sim", x_sim, 2), ("theta_sim", theta_sim, 2), ("y_sim", y_sim, 1),
                          ("x_obs", x_obs, 2), ("y_obs", y_obs, 1)):
            check_tensor(nm, t, nd)
        m, n = y_sim.shape[0], y_obs.shape[0]
        for nm, t, rows in (("x_sim", x_sim, m), ("theta_sim", theta_sim, m),
                            ("x_obs", x_obs, n)):
            if t.shape[0] != rows:
                raise ValueError(f"{nm} has {t.shape[0]} rows, expected {rows}")
        if x_sim.shape[1] != x_obs.shape[1]:
            raise ValueError(f"x_sim has {x_sim.shape[1]} columns but x_obs has "
                             f"{x_obs.shape[1]}")
        xn = tuple(ax.x_names or [f"x{i + 1}" for i in range(x_sim.shape[1])])
        tn = tuple(ax.theta_names or [f"t{i + 1}" for i in range(theta_sim.shape[1])])
        if len(xn) != x_sim.shape[1]:
            raise ValueError(f"x_names has {len(xn)} names for {x_sim.shape[1]} columns")
        if len(tn) != theta_sim.shape[1]:
            raise ValueError(f"theta_names has {len(tn)} names for {theta_sim.shape[1]} columns")
        tb = ax.theta_box or Box.around(tn, theta_sim)
        xb = ax.x_box or Box.around(xn, torch.cat([x_sim, x_obs]))
        if tb.names != tn:
            raise ValueError(f"theta_box names {tb.names} differ from theta_names {tn}")
        return cls(x_sim, theta_sim, y_sim, x_obs, y_obs, xb, tb)

    @property
    def n_sim(self) -> int:
        return self.y_sim.shape[0]

    @property
    def n_obs(self) -> int:
        return self.y_obs.shape[0]
