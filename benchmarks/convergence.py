"""Mesh and time-step convergence of V_A, V_B at the four seed times (Liu 2008 constants).

Usage: python benchmarks/convergence.py [--out docs/convergence.json] [--quick]
Prints markdown tables (used in docs/verification.md) and writes the numbers as JSON.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import torch

from solderpyro.fem.loading import SEED_TIMES, TimeStepping
from solderpyro.fem.mesh import Layer, MeshSpec
from solderpyro.fem.problem import REFERENCE_LAYERS, Problem
from solderpyro.fem.solver import SpecimenSolver
from solderpyro.params import anand_tensor


def mesh_problem(scale: float) -> Problem:
    """The reference problem with every element count multiplied by ``scale``."""
    layers = tuple(Layer(lay.name, lay.material, lay.y0, lay.y1, max(1, round(lay.ny * scale)),
                         lay.grading, lay.toward) for lay in REFERENCE_LAYERS)
    return Problem(layers=layers, mesh=MeshSpec(nx=round(MeshSpec().nx * scale)))


def time_problem(scale: float, base: Problem | None = None) -> Problem:
    """Reference problem with every step-size control divided by ``scale``."""
    ts = TimeStepping()
    ts = dataclasses.replace(ts, dT_max=ts.dT_max / scale, dwell_dt0=ts.dwell_dt0 / scale,
                             dt_max=ts.dt_max / scale, dep_max=ts.dep_max / scale)
    return dataclasses.replace(base or Problem(), stepping=ts)


def run(problem: Problem) -> tuple[list[float], float, int, int]:
    solver = SpecimenSolver(problem)
    p = anand_tensor(dtype=torch.float64)[None]
    t = time.perf_counter()
    r = solver.solve(p, SEED_TIMES)
    return r.V[0].reshape(-1).tolist(), time.perf_counter() - t, solver.n_r, r.n_steps


def table(title: str, rows: list[dict]) -> str:
    ref = rows[-1]["V"]
    lines = [f"### {title}", "", "| level | " + " | ".join(
        f"V_{p}({t:g} s)" for t in SEED_TIMES for p in "AB") + " | max rel. diff to finest "
        "| max abs. diff (um) | dofs / steps | wall (s) |", "|" + "---|" * 13]
    for r in rows:
        d = [abs(a - b) for a, b in zip(r["V"], ref, strict=True)]
        rel = max(x / max(abs(b), 1e-12) for x, b in zip(d, ref, strict=True))
        lines.append(f"| {r['label']} | " + " | ".join(f"{v:.4f}" for v in r["V"])
                     + f" | {rel:.2e} | {max(d):.4f} | {r['size']} | {r['wall']:.1f} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="benchmarks/results/convergence.json")
    ap.add_argument("--quick", action="store_true", help="skip the finest levels")
    a = ap.parse_args()
    mesh_levels = [0.5, 1.0, 2.0] if a.quick else [0.5, 1.0, 2.0, 3.0]
    time_levels = [0.5, 1.0, 2.0] if a.quick else [0.5, 1.0, 2.0, 4.0, 8.0]
    euler = [1.0, 4.0]
    res: dict = {"mesh": [], "time": []}
    for s in mesh_levels:
        V, w, n, k = run(mesh_problem(s))
        res["mesh"].append({"label": f"mesh x{s:g}", "V": V, "wall": w, "size": f"{n} / {k}"})
        print(res["mesh"][-1], flush=True)
    for s in time_levels:
        V, w, n, k = run(time_problem(s))
        res["time"].append({"label": f"steps x{s:g}", "V": V, "wall": w, "size": f"{n} / {k}"})
        print(res["time"][-1], flush=True)
    res["euler"] = []
    for s in ([] if a.quick else euler):
        pr = time_problem(s)
        pr = dataclasses.replace(pr, stepping=dataclasses.replace(pr.stepping, scheme="euler"))
        V, w, n, k = run(pr)
        res["euler"].append({"label": f"euler x{s:g}", "V": V, "wall": w, "size": f"{n} / {k}"})
        print(res["euler"][-1], flush=True)
    print(table("Mesh convergence (default time steps)", res["mesh"]))
    print()
    print(table("Time-step convergence (default mesh)", res["time"]))
    if res["euler"]:
        print()
        print(table("Backward Euler instead of SDIRK2 (last row: SDIRK2 finest)",
                    res["euler"] + [res["time"][-1]]))
    with open(a.out, "w") as f:
        json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
