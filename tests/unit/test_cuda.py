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


def test_the_specimen_model_moved_to_cuda_gives_the_cpu_reference(tmp_path) -> None:
    """``SpecimenModel.to("cuda")``: its buffers and its solver follow; V and dV/dtheta equal
    the CPU's reference values (tests/unit/specimen/test_model.py) to round-off, and the
    run-store path on the GPU equals the direct solve."""
    import sys
    from pathlib import Path

    import numpy as np

    sys.path.insert(0, str(Path(__file__).resolve().parent / "specimen"))
    from test_model import G_REF, THETA, V_REF, W

    from solderpyro import SpecimenModel
    from solderpyro.compute.runstore import RunStore
    from solderpyro.specimen import StoreUse

    f64 = torch.float64
    m = SpecimenModel().to("cuda")
    assert all(b.device.type == "cuda" for b in m.buffers())
    th = torch.tensor(THETA, dtype=f64, device="cuda", requires_grad=True)
    V = m(th)
    assert m.solver.tkw["device"].type == "cuda" and V.device.type == "cuda"
    (g,) = torch.autograd.grad((V * torch.tensor(W, dtype=f64, device="cuda")).sum(), th)
    torch.testing.assert_close(V.detach().cpu(), torch.tensor(V_REF, dtype=f64), rtol=1e-9,
                               atol=0)
    torch.testing.assert_close(g.cpu(), torch.tensor(G_REF, dtype=f64), rtol=1e-9, atol=0)
    ti, oi = np.array([0, 1, 2, 3, 3]), np.array([0, 0, 1, 0, 1])
    m.set_observations(ti, oi).use_store(StoreUse(RunStore(tmp_path / "store"), batch=2))
    Vs, ok = m.observed_runs(torch.tensor(THETA, dtype=f64))
    assert bool(ok.all())
    # two converged Newton solves (residual rtol 1e-10) on the GPU: CUDA's atomic scatter-adds
    # give each solve its own round-off, so Newton may stop one iteration apart; they agree to
    # the Newton tolerance times the stiffness's conditioning (5e-9 of max|V| on an H100)
    scale = float(V.detach().abs().max())
    torch.testing.assert_close(Vs, V.detach().cpu()[:, ti, oi], rtol=0, atol=5e-8 * scale)
    m.to("cpu")
    assert m.solver.tkw["device"].type == "cpu"
