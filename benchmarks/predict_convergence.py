"""Convergence of the solder's inelastic work per cycle under mesh and time-step refinement.

Usage: python benchmarks/predict_convergence.py [--out benchmarks/results/predict_convergence.json]

The reference specimen and cycle with Liu's constants (seed Table IV). ``predict``'s
quantities of the cycle (the inelastic strain energy density averaged over the upper and
lower interface rows and the whole joint, its largest Gauss-point value; the same for the
equivalent inelastic strain) on four meshes, each twice the last in every direction (the
coarse, default and fine meshes, then twice the fine), and on four time grids (the default
``dT_max``, ``dwell_dt0``, ``dt_max`` times 2, 1, 1/2, 1/4). Per quantity: the changes
between levels and the observed order ``log2(|q1 - q2| / |q2 - q3|)``.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

MESHES = {"coarse": ["mesh=coarse"], "default": [], "fine": ["mesh=fine"],
          "fine x2": ["mesh=fine", "mesh.nx=120", "mesh.rows.copper.ny=32",
                      "mesh.rows.solder.ny=16", "mesh.rows.steel.ny=32"]}
STEPS = {f"x{f:g}": [f"solver.stepping.dT_max={4.0 * f}", f"solver.stepping.dwell_dt0={10.0 * f}",
                     f"solver.stepping.dt_max={300.0 * f}"] for f in (2.0, 1.0, 0.5, 0.25)}


def quantities(overrides: list[str]) -> tuple[dict[str, float], float, int]:
    """The cycle's quantities at Liu's constants, the solve's seconds and grid steps."""
    import torch

    from solderpyro.config.compose import build, compose
    from solderpyro.params import LIU2008
    from solderpyro.predict import forward
    from solderpyro.predict.run import cycle_quantities, solder_regions
    from solderpyro.specimen import SpecimenModel

    setup = build(compose(overrides))
    model = SpecimenModel(setup.problem, setup.space, setup.times)
    th = torch.tensor([[LIU2008[n] for n in setup.space.names]], dtype=torch.float64)
    t0 = time.perf_counter()
    f = forward.solve_fields(model, tuple(setup.problem.cycle.cycle_ends), (), th)
    sec = time.perf_counter() - t0
    regs, w, _ = solder_regions(model)
    per, _ = cycle_quantities(f, False, regs, w)
    out = {f"{q}_{r}": float(v[0, -1]) for (q, r), v in per.items()}
    return out, sec, len(f.t)


def orders(levels: dict[str, dict[str, float]]) -> dict[str, list[float | None]]:
    """Per quantity, the observed orders of consecutive level triples."""
    names = list(levels)
    out: dict[str, list[float | None]] = {}
    for q in levels[names[0]]:
        v = [levels[n][q] for n in names]
        rates: list[float | None] = []
        for i in range(len(v) - 2):
            d1, d2 = abs(v[i] - v[i + 1]), abs(v[i + 1] - v[i + 2])
            rates.append(math.log2(d1 / d2) if d1 > 0 and d2 > 0 else None)
        out[q] = rates
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="benchmarks/results/predict_convergence.json")
    a = ap.parse_args()
    res: dict = {"constants": "Liu 2008 (seed Table IV)", "mesh": {}, "steps": {}}
    for kind, table in (("mesh", MESHES), ("steps", STEPS)):
        for name, ov in table.items():
            q, sec, n = quantities(ov)
            res[kind][name] = {"overrides": ov, "seconds": round(sec, 1), "grid_steps": n, **q}
            print(f"{kind} {name}: {sec:.1f} s, {n} steps, dW upper {q['dW_upper_interface']:.6g}"
                  f" joint {q['dW_joint']:.6g} max {q['dW_max']:.6g}", flush=True)
        vals = {k: {q: v for q, v in d.items() if q.startswith("d")}
                for k, d in res[kind].items()}
        res[f"{kind}_orders"] = orders(vals)
        print(kind, json.dumps(res[f"{kind}_orders"]), flush=True)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(res, indent=1) + "\n")


if __name__ == "__main__":
    main()
