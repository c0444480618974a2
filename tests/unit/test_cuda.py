"""The CUDA path gives the CPU's answer (runs where a GPU is; BENCHMARKS.md "CUDA" has the
H200 figures: 2.8e-13 um over 16 parameter sets)."""

import pytest
import torch

from solderpyro.fem.loading import SEED_TIMES
from solderpyro.fem.problem import Problem
from solderpyro.fem.solver import SpecimenSolver
from solderpyro.params import ParameterSpace

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(),
                                reason="no CUDA device: the GPU path is checked on a GPU machine")


def test_a_batched_cuda_solve_equals_the_cpu_solve() -> None:
    space = ParameterSpace.seed()
    u = torch.tensor([[0.1, 0.2, 0.3, 0.4], [0.9, 0.5, 0.7, 0.05], [0.5, 0.5, 0.5, 0.5]],
                     dtype=torch.float64)
    p = space.full(space.from_unit(u))  # (3, n_anand) physical
    cpu = SpecimenSolver(Problem(), dtype=torch.float64).solve(p, SEED_TIMES)
    gpu = SpecimenSolver(Problem(), dtype=torch.float64, device="cuda").solve(
        p.to("cuda"), SEED_TIMES)
    assert bool(cpu.ok.all()) and bool(gpu.ok.all())
    assert gpu.V.device.type == "cuda"
    # the same Newton iterations in the same order: agreement to round-off (1e-13 um measured,
    # ~1e-14 of max|V|), bounded by 1e-10 of max|V|
    assert float((gpu.V.cpu() - cpu.V).abs().max()) < 1e-10 * float(cpu.V.abs().max())
