"""The specimen model as a torch function of the calibration parameters.

>>> import torch
>>> from solderpyro import SpecimenModel
>>> model = SpecimenModel()                       # reference case, seed times, points A and B
>>> theta = torch.tensor([[12.9, 10586.0, 2.04, 0.2]], dtype=torch.float64)  # s0, QR, xi, m
>>> V = model(theta)                              # (1, 4, 2): (B, n_time, n_out) in um

With physical effects (:mod:`solderpyro.effects`) their parameters follow the Anand ones:

>>> model = SpecimenModel(effects=("thermal_lag",))
>>> model.param_names
['s0', 'QR', 'xi', 'm', 'tau']
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import torch

from .effects import Effect, EffectSet
from .fem.loading import SEED_TIMES
from .fem.problem import Problem, reference_grid
from .fem.solver import SolveResult, SpecimenSolver
from .params import Box, ParameterSpace, check_anand_values

log = logging.getLogger(__name__)


class SpecimenModel:
    """``theta (B, n_theta) -> V (B, n_time, n_out)`` in um, differentiable, batched.

    Args:
        problem: the FE problem (default: the reference case of shared/specimen.md).
        space: which Anand constants ``theta`` holds (default: s0, QR, xi, m with Liu's others).
        times: output times, s (default: the seed's four points (a)-(d)).
        field: also report V on the 31 x 18 grid of shared/specimen.md (after A, B).
        dtype, device: of the solve (float64 recommended; ``"cuda"`` works).
        observation: optional map ``V (B, n_time, n_out) -> V'`` applied to the FE outputs
            (after the effects' own observation operators).
        effects: physical effects switched on: names of :data:`solderpyro.effects.EFFECTS`,
            :class:`~solderpyro.effects.Effect` instances (e.g. with a box override), or an
            :class:`~solderpyro.effects.EffectSet`. Their parameters are the last columns of
            ``theta`` (:attr:`param_names`); their prior box is :attr:`effect_box`.
    """

    def __init__(self, problem: Problem | None = None, space: ParameterSpace | None = None,
                 times=SEED_TIMES, field: bool = False, dtype=torch.float64,
                 device="cpu", observation=None,
                 effects: EffectSet | Sequence[str | Effect] = ()) -> None:
        self.problem = problem or Problem()
        self.space = space or ParameterSpace.seed()
        self.times = tuple(float(t) for t in times)
        fx = effects if isinstance(effects, EffectSet) else EffectSet(effects)
        self.effects: EffectSet = fx.bind(self.times)
        self.solver = SpecimenSolver(self.problem, reference_grid() if field else None,
                                     dtype=dtype, device=device, effects=self.effects)
        self.observation = observation
        self.last: SolveResult | None = None

    @property
    def param_names(self) -> list[str]:
        """Names of the ``theta`` columns: ``space.names`` then the effects' parameters."""
        return [*self.space.names, *self.effects.names]

    @property
    def n_theta(self) -> int:
        """Columns of ``theta``: ``space.n_theta`` plus the effects' parameters."""
        return self.space.n_theta + self.effects.n_params

    @property
    def effect_box(self) -> Box:
        """Prior box of the effects' parameters (bound to :attr:`times`)."""
        return self.effects.box

    @property
    def output_names(self) -> list[str]:
        """Labels of the ``n_out`` outputs (``"A"``, ``"B"``, then grid labels)."""
        return list(self.solver.names)

    @property
    def output_points(self):
        """``(n_out, 2)`` coordinates (mm) of the outputs."""
        pts = [self.problem.points[n] for n in self.problem.points]
        if len(self.solver.names) > len(pts):
            pts += [tuple(p) for p in reference_grid()[1]]
        return torch.tensor(pts, dtype=torch.float64)

    def run(self, theta: torch.Tensor, progress: bool = False) -> SolveResult:
        """Solve for ``theta`` ``(B, n_theta)`` (physical units: the calibrated Anand constants,
        then the effects' parameters); returns the full result."""
        theta = torch.as_tensor(theta, **self.solver.tkw)
        if theta.ndim == 1:
            theta = theta[None]
        self._check(theta)
        k = self.space.n_theta
        params = torch.cat([self.space.full(theta[:, :k]), theta[:, k:]], -1)  # (B, 9 + n_eff)
        res = self.solver.solve(params, self.times, progress=progress)
        for i, why in enumerate(res.reasons):
            if why:
                log.warning("batch member %d (theta=%s) failed: %s", i, theta[i].tolist(), why)
        self.last = res
        return res

    def __call__(self, theta: torch.Tensor) -> torch.Tensor:
        """``(B, n_theta) -> (B, n_time, n_out)`` in um; NaN rows for failed members."""
        V = self.run(theta).V
        return V if self.observation is None else self.observation(V)

    def _check(self, theta: torch.Tensor) -> None:
        if theta.ndim != 2 or theta.shape[-1] != self.n_theta:
            raise ValueError(f"theta must have shape (B, {self.n_theta}) for "
                             f"{', '.join(self.param_names)}; got {tuple(theta.shape)}")
        if not torch.isfinite(theta).all():
            raise ValueError("theta contains NaN or inf")
        for j, nm in enumerate(self.space.names):  # the extremes of each column decide
            check_anand_values({nm: theta[:, j].min().item()})
            check_anand_values({nm: theta[:, j].max().item()})
        self.effects.check(theta[:, self.space.n_theta:])
