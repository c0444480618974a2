"""The specimen model as a torch function of the calibration parameters.

>>> import torch
>>> from solderpyro import SpecimenModel
>>> model = SpecimenModel()                       # reference case, seed times, points A and B
>>> theta = torch.tensor([[12.9, 10586.0, 2.04, 0.2]], dtype=torch.float64)  # s0, QR, xi, m
>>> V = model(theta)                              # (1, 4, 2): (B, n_time, n_out) in um
"""

from __future__ import annotations

import logging

import torch

from .fem.loading import SEED_TIMES
from .fem.problem import Problem, reference_grid
from .fem.solver import SolveResult, SpecimenSolver
from .params import ParameterSpace, check_anand_values

log = logging.getLogger(__name__)


class SpecimenModel:
    """``theta (B, n_theta) -> V (B, n_time, n_out)`` in um, differentiable, batched.

    Args:
        problem: the FE problem (default: the reference case of shared/specimen.md).
        space: which Anand constants ``theta`` holds (default: s0, QR, xi, m with Liu's others).
        times: output times, s (default: the seed's four points (a)-(d)).
        field: also report V on the 31 x 18 grid of shared/specimen.md (after A, B).
        dtype, device: of the solve (float64 recommended; ``"cuda"`` works).
        observation: optional map ``V (B, n_time, n_out) -> V'`` applied to the FE outputs (the
            seam for observation-side effects, e.g. a Moire rigid offset and rotation per image).
    """

    def __init__(self, problem: Problem | None = None, space: ParameterSpace | None = None,
                 times=SEED_TIMES, field: bool = False, dtype=torch.float64,
                 device="cpu", observation=None) -> None:
        self.problem = problem or Problem()
        self.space = space or ParameterSpace.seed()
        self.times = tuple(float(t) for t in times)
        self.solver = SpecimenSolver(self.problem, reference_grid() if field else None,
                                     dtype=dtype, device=device)
        self.observation = observation
        self.last: SolveResult | None = None

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
        """Solve for ``theta`` ``(B, n_theta)`` (physical units); returns the full result."""
        theta = torch.as_tensor(theta, **self.solver.tkw)
        if theta.ndim == 1:
            theta = theta[None]
        self._check(theta)
        res = self.solver.solve(self.space.full(theta), self.times, progress=progress)
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
        if theta.ndim != 2 or theta.shape[-1] != self.space.n_theta:
            raise ValueError(f"theta must have shape (B, {self.space.n_theta}) for "
                             f"{', '.join(self.space.names)}; got {tuple(theta.shape)}")
        if not torch.isfinite(theta).all():
            raise ValueError("theta contains NaN or inf")
        for j, nm in enumerate(self.space.names):  # the extremes of each column decide
            check_anand_values({nm: theta[:, j].min().item()})
            check_anand_values({nm: theta[:, j].max().item()})
