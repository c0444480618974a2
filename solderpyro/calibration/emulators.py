"""What the observation likelihood sees of the computer model at a calibration point t.

An emulator maps ``t (n_theta,)`` (physical units) and optional prediction inputs
``x (n, n_x)`` to the code output's mean ``(n,)`` and covariance ``(n, n)`` there (``None``
when the code is evaluated exactly). ``x=None`` means the observation inputs.

- :class:`FunctionEmulator`: the computer model itself (the direct mode; cheap models, and the
  ground truth a surrogate posterior is checked against).
- :class:`GPEmulator`: a fitted :class:`~solderpyro.surrogate.GPSurrogate` (the modular mode:
  hyperparameters fixed, code uncertainty propagated through the GP's predictive covariance).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from solderpyro.surrogate import GPSurrogate


class FunctionEmulator:
    """Direct evaluation of ``f(x (n, n_x), t (n_theta,)) -> (n,)``.

    Args:
        f: the computer model, differentiable in ``t`` for NUTS.
        x_obs: ``(n_obs, n_x)`` observation inputs.
    """

    def __init__(self, f: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
                 x_obs: torch.Tensor) -> None:
        self.f, self.x_obs = f, x_obs

    def __call__(self, t: torch.Tensor, x: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor | None]:
        return self.f(self.x_obs if x is None else x, t), None


class GPEmulator:
    """A fitted GP surrogate seen at the observation inputs.

    Two layouts:
    - ``x_obs`` given: the GP's inputs are ``(x, t)`` concatenated (the seed's scalar layout);
      ``gp.box`` lists the x columns first.
    - ``x_obs=None``: the GP's inputs are ``t`` only and its outputs ``(n_y,)`` are the
      observations themselves (``"batched"`` or ``"pca"`` surrogates of a multi-output code).

    Args:
        gp: fitted surrogate.
        x_obs: ``(n_obs, n_x)`` or None.
    """

    def __init__(self, gp: GPSurrogate, x_obs: torch.Tensor | None = None) -> None:
        if gp.model is None:
            raise ValueError("gp must be fitted before it is used as an emulator")
        n_x = 0 if x_obs is None else x_obs.shape[1]
        if x_obs is not None and gp.output != "scalar":
            raise ValueError("x_obs is only meaningful for a 'scalar' surrogate with x inputs")
        self.gp, self.x_obs, self.n_x = gp, x_obs, n_x

    def __call__(self, t: torch.Tensor, x: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor | None]:
        if self.x_obs is None:
            if x is not None:
                raise ValueError("this emulator predicts the observed outputs only (x=None)")
            return self.gp.mean_cov(t.unsqueeze(0))
        xx = self.x_obs if x is None else x
        inp = torch.cat([xx, t.expand(xx.shape[0], t.shape[-1])], dim=-1)  # (n, n_x + n_theta)
        return self.gp.mean_cov(inp)

    def lowrank(self, t: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
        """``(mean (n_obs,), F (n_obs, k), d (n_obs,))`` with code covariance ``F F^T + diag(d)``
        for a PCA surrogate of the observations (``x_obs=None``); None for other layouts, whose
        covariance :meth:`__call__` gives densely."""
        if self.x_obs is not None or self.gp.output != "pca":
            return None
        return self.gp.mean_lowrank(t)


class ObservedEmulator:
    """An emulator of the FE outputs followed by additive observation-side effects.

    Observation effects (e.g. a Moire rigid offset and rotation per image) act on the observed
    V after the FE, additively, so the surrogate need not learn them: ``t = (t_fe, q)`` and the
    prediction is ``mean(t_fe) + offset(q)`` with the code covariance of ``t_fe`` unchanged.

    Args:
        base: emulator of the observations from ``t_fe (n_fe,)`` (a :class:`GPEmulator`).
        n_fe: number of leading entries of ``t`` that the base emulator takes.
        offset: ``q (n_q,) -> (n_obs,)`` additive offset of each observation, um
            (differentiable).
    """

    def __init__(self, base: Any, n_fe: int, offset: Callable[[torch.Tensor], torch.Tensor]
                 ) -> None:
        self.base, self.n_fe, self.offset = base, n_fe, offset
        self.x_obs = None

    def __call__(self, t: torch.Tensor, x: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor | None]:
        m, c = self.base(t[..., :self.n_fe], x)
        return m + self.offset(t[..., self.n_fe:]), c

    def lowrank(self, t: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
        """As :meth:`GPEmulator.lowrank`, shifted by the offset."""
        lr = getattr(self.base, "lowrank", None)
        out = None if lr is None else lr(t[..., :self.n_fe])
        if out is None:
            return None
        return out[0] + self.offset(t[..., self.n_fe:]), out[1], out[2]
