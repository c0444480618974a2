"""FE throughput on the reference case: batched solves vs sequential single runs.

Usage: python benchmarks/bench_fe.py [--sizes 1,8,64,256] [--sequential 64] [--lhs 50]
       [--device cpu|cuda] [--threads N] [--no-native] [--check-cpu N] [--split B1,B2,...]
       [--out benchmarks/results/bench_fe.json]

``--split``: for each batch size, the same parameter sets solved in one process on torch's
threads and split over every core's one-thread process (:func:`solderpyro.compute.executor.
solve_split`, the in-process default), paired, with the largest |dV|
between the two.

On a GPU (``--device cuda``) one small solve runs first, untimed (CUDA context and kernel
loading), and ``--check-cpu N`` solves N of the parameter sets on the CPU too and records the
largest |V_cuda - V_cpu| (um): the CUDA path must give the CPU's answer.

Every batch is a Latin hypercube over the seed box (s0, QR, xi, m) with Liu's other constants,
through the full cycle at the default mesh and steps, outputs at the seed times. The ratio
"batched vs sequential" is measured in the same run on the same parameter sets, so it is
robust to the machine's load; absolute times are not. The JSON records whether the native CPU
kernels ran (``--no-native``: the torch path, as ``SOLDERPYRO_NATIVE=0``) and the load average
before and after.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import torch
from scipy.stats import qmc

from solderpyro import _native
from solderpyro.fem.loading import SEED_TIMES
from solderpyro.fem.problem import Problem
from solderpyro.fem.solver import SpecimenSolver
from solderpyro.params import ParameterSpace


def lhs(n: int, seed: int = 0) -> torch.Tensor:
    """``(n, 4)`` Latin hypercube over the seed box, physical units."""
    space = ParameterSpace.seed()
    u = torch.as_tensor(qmc.LatinHypercube(d=space.n_theta, seed=seed).random(n))
    return space.full(space.from_unit(u))


def timed(solver: SpecimenSolver, p: torch.Tensor) -> tuple[float, bool]:
    if p.device.type == "cuda":
        torch.cuda.synchronize()
    t = time.perf_counter()
    r = solver.solve(p, SEED_TIMES)
    if p.device.type == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter() - t, bool(r.ok.all())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--sizes", default="1,8,64,256")
    ap.add_argument("--sequential", type=int, default=64)
    ap.add_argument("--lhs", type=int, default=50)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--dtype", default="float64")
    ap.add_argument("--threads", type=int, default=0,
                    help="torch intra-op threads (0: torch's default); 1 is the robust choice "
                         "on a machine shared with other jobs")
    ap.add_argument("--no-native", action="store_true",
                    help="the torch path only (no compiled kernels)")
    ap.add_argument("--check-cpu", type=int, default=0, metavar="N",
                    help="with a GPU device: solve N parameter sets on the CPU too and record "
                         "the largest difference of V")
    ap.add_argument("--split", default="", metavar="B1,B2",
                    help="batch sizes to time whole on torch's threads against split over "
                         "the cores (CPU only)")
    ap.add_argument("--out", default="benchmarks/results/bench_fe.json")
    a = ap.parse_args()
    if a.no_native:
        os.environ["SOLDERPYRO_NATIVE"] = "0"
    if a.threads:
        torch.set_num_threads(a.threads)
    dtype = getattr(torch, a.dtype)
    solver = SpecimenSolver(Problem(), dtype=dtype, device=a.device)
    res = {"device": a.device, "dtype": a.dtype, "threads": torch.get_num_threads(),
           "machine": platform.processor() or platform.machine(), "torch": torch.__version__,
           "n_retained_dofs": solver.n_r, "native": _native.library() is not None,
           "simd_width": _native.simd_width(), "loadavg_before": os.getloadavg(), "rows": []}
    if a.device.startswith("cuda"):
        res["gpu"] = torch.cuda.get_device_name()
        timed(solver, lhs(2, seed=1).to(device=a.device, dtype=dtype))  # warm-up, not counted
        if a.check_cpu:
            p = lhs(a.check_cpu, seed=7).to(dtype=dtype)
            r_gpu = solver.solve(p.to(a.device), SEED_TIMES)
            r_cpu = SpecimenSolver(Problem(), dtype=dtype).solve(p, SEED_TIMES)
            dv = float((r_gpu.V.cpu() - r_cpu.V).abs().max())
            res["check_cpu"] = {"n": a.check_cpu, "max_abs_dV_um": dv,
                                "max_abs_V_um": float(r_cpu.V.abs().max()),
                                "all_ok": bool(r_gpu.ok.all()) and bool(r_cpu.ok.all())}
            print(f"CUDA vs CPU on {a.check_cpu} parameter sets: max |dV| {dv:.3g} um "
                  f"(max |V| {res['check_cpu']['max_abs_V_um']:.3g} um)", flush=True)
    for B in [int(b) for b in a.sizes.split(",") if b]:
        p = lhs(B, seed=B).to(device=a.device, dtype=dtype)
        w, ok = timed(solver, p)
        res["rows"].append({"B": B, "wall_s": w, "runs_per_s": B / w, "all_ok": ok})
        print(f"B={B:4d}: {w:8.2f} s  {B / w:7.3f} runs/s  ok={ok}", flush=True)
    if a.sequential:
        S = a.sequential
        p = lhs(S, seed=S).to(device=a.device, dtype=dtype)
        wb, _ = timed(solver, p)
        ws = sum(timed(solver, p[i:i + 1])[0] for i in range(S))
        res["sequential"] = {"B": S, "batched_s": wb, "sequential_s": ws, "speedup": ws / wb}
        print(f"B={S}: batched {wb:.1f} s, {S} sequential single runs {ws:.1f} s, "
              f"speedup {ws / wb:.2f}x", flush=True)
    if a.split:
        from solderpyro.compute.executor import local_cores, solve_batch, solve_split
        from solderpyro.params import ANAND_NAMES

        res["split"] = []
        procs = local_cores()
        for B in [int(b) for b in a.split.split(",") if b]:
            p = lhs(B, seed=B + 1)
            t = time.perf_counter()
            whole = solve_batch(solver, p, SEED_TIMES, ANAND_NAMES)
            tw = time.perf_counter() - t
            t = time.perf_counter()
            split = solve_split(solver, p, SEED_TIMES, ANAND_NAMES, procs)
            ts = time.perf_counter() - t
            dv = max(float(abs(x.V - y.V).max()) for x, y in zip(whole, split, strict=True))
            row = {"B": B, "processes": procs, "whole_s": tw, "split_s": ts,
                   "speedup": tw / ts, "max_abs_dV_um": dv,
                   "all_ok": all(r.ok for r in whole + split)}
            res["split"].append(row)
            print(f"B={B:4d}: whole {tw:.2f} s ({torch.get_num_threads()} threads), split over "
                  f"{procs} processes {ts:.2f} s: {tw / ts:.2f}x, max |dV| {dv:.2g} um",
                  flush=True)
    if a.lhs:
        p = lhs(a.lhs, seed=2024).to(device=a.device, dtype=dtype)
        w, ok = timed(solver, p)
        res["lhs"] = {"n": a.lhs, "wall_s": w, "all_ok": ok}
        print(f"seed-style LHS of {a.lhs} runs through the full cycle: {w:.1f} s, ok={ok}")
    res["loadavg_after"] = os.getloadavg()
    print(f"load average before {res['loadavg_before']}, after {res['loadavg_after']}")
    with open(a.out, "w") as f:
        json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
