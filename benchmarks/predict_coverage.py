"""Coverage of ``predict``'s 95 % bands of the solder's inelastic work over noise seeds.

Usage: python benchmarks/predict_coverage.py [--seeds 20] [--work runs/predict_coverage]
       [--out benchmarks/results/predict_coverage.json] [--only i,j,...]

Known constants (the demo's truth: s0 12.92 MPa, Q/R 10,586 K, xi 2.04, m 0.1). For each
noise seed: the Moire points A and B at the seed's four times from the FE on the fine mesh
with half the default time step (data not made by the calibration's own discretization), plus
N(0, 0.05^2) um noise; then ``solderpyro calibrate --data D --out RUN --store S`` and
``solderpyro predict RUN`` with their defaults. The band of each quantity (the interface
rows' and the joint's inelastic strain energy density and inelastic strain per cycle, their
largest values) covers the truth or not; the truth is the quantity at the true constants on
the calibration's mesh (what the band describes), and, beside it, on the fine mesh (what the
band does not include: the discretization). A rerun reuses the calibrations and the solved
draws it finds in ``--work`` and overwrites the results file.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

TRUTH = {"s0": 12.92, "QR": 10586.0, "xi": 2.04, "m": 0.1}
NOISE_UM = 0.05
#: the data's discretization: the fine mesh, half the default steps
DATA_OVERRIDES = ["mesh=fine", "solver.stepping.dT_max=2.0", "solver.stepping.dwell_dt0=5.0",
                  "solver.stepping.dt_max=150.0"]
QUANTITIES = [("dW", "upper_interface"), ("dW", "lower_interface"), ("dW", "joint"),
              ("dW", "max"), ("dp", "upper_interface"), ("dp", "lower_interface"),
              ("dp", "joint"), ("dp", "max")]


def _data(path: Path, seed: int) -> None:
    from solderpyro.cli import simulate_table
    from solderpyro.config.compose import build, compose
    from solderpyro.io.measurements import from_arrays, write_measurements

    setup = build(compose(DATA_OVERRIDES))
    t, names, pts, V = simulate_table(setup, TRUTH, setup.times, field=False, progress=False)
    rng = np.random.default_rng(seed)
    V = V + NOISE_UM * rng.standard_normal(V.shape)
    temps = np.array([setup.problem.cycle(x) for x in t])
    write_measurements(path, from_arrays(t, names, pts, V, temperature_C=temps,
                                         sigma_um=np.full(V.shape, NOISE_UM),
                                         meta={"generator": "benchmarks/predict_coverage.py",
                                               "truth": str(TRUTH), "seed": str(seed),
                                               "overrides": " ".join(DATA_OVERRIDES)}))


def _truth(overrides: list[str]) -> dict[str, float]:
    """The quantities at the true constants (one draw through ``predict``'s own reduction,
    on a run-less model: the FE with the recorder and the same averages)."""
    import torch

    from solderpyro.config.compose import build, compose
    from solderpyro.predict import forward
    from solderpyro.predict.run import cycle_quantities, solder_regions
    from solderpyro.specimen import SpecimenModel

    setup = build(compose(overrides))
    model = SpecimenModel(setup.problem, setup.space, setup.times)
    th = torch.tensor([[TRUTH[n] for n in setup.space.names]], dtype=torch.float64)
    f = forward.solve_fields(model, tuple(setup.problem.cycle.cycle_ends), (), th)
    regs, w, _ = solder_regions(model)
    per, _ = cycle_quantities(f, False, regs, w)
    out = {f"{q}_{r}": float(v[0, -1]) for (q, r), v in per.items()}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--work", default="runs/predict_coverage")
    ap.add_argument("--out", default="benchmarks/results/predict_coverage.json")
    ap.add_argument("--only", default="", help="comma-separated seeds to run")
    a = ap.parse_args()
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    truth = _truth([])
    truth_fine = _truth(DATA_OVERRIDES)
    seeds = [int(s) for s in a.only.split(",")] if a.only else list(range(a.seeds))
    rows = []
    exe = [sys.executable, "-m", "solderpyro.cli"]
    for s in seeds:
        d = work / f"data_s{s}.csv"
        run = work / f"run_s{s}"
        t0 = time.perf_counter()
        if not d.exists():
            _data(d, s)
        if not (run / "draws.npz").exists():
            subprocess.run([*exe, "-q", "calibrate", "--data", str(d), "--out", str(run),
                            "--store", str(work / "store")], check=True)
        t1 = time.perf_counter()
        subprocess.run([*exe, "-q", "predict", str(run)], check=True, stdout=subprocess.DEVNULL)
        t2 = time.perf_counter()
        import csv

        with (run / "prediction" / "prediction.csv").open() as fh:
            bands = {(r["quantity"], r["region"]): r for r in csv.DictReader(fh)
                     if r["cycle"] == "1"}
        info = json.loads((run / "run.json").read_text())
        # a reused calibration's time is its own record's (its stages' seconds)
        cal_s = t1 - t0 if t1 - t0 > 1.0 else sum(info.get("timing_s", {}).values())
        row = {"seed": s, "calibrate_s": round(cal_s, 1), "predict_s": round(t2 - t1, 1),
               "calibration_reused": t1 - t0 <= 1.0, "posterior": info.get("posterior")}
        for q, r in QUANTITIES:
            b = bands[(q, r)]
            lo, hi = float(b["lo95"]), float(b["hi95"])
            k = f"{q}_{r}"
            row[k] = {"median": float(b["median"]), "lo95": lo, "hi95": hi,
                      "covers": bool(lo <= truth[k] <= hi),
                      "covers_fine": bool(lo <= truth_fine[k] <= hi)}
        rows.append(row)
        print(f"seed {s}: calibrate {row['calibrate_s']:.0f} s, predict "
              f"{row['predict_s']:.0f} s; dW upper "
              f"{row['dW_upper_interface']['lo95']:.4g}-{row['dW_upper_interface']['hi95']:.4g}"
              f" (truth {truth['dW_upper_interface']:.4g}): "
              f"{'in' if row['dW_upper_interface']['covers'] else 'OUT'}", flush=True)
    cov = {f"{q}_{r}": float(np.mean([x[f"{q}_{r}"]["covers"] for x in rows]))
           for q, r in QUANTITIES}
    cov_fine = {f"{q}_{r}": float(np.mean([x[f"{q}_{r}"]["covers_fine"] for x in rows]))
                for q, r in QUANTITIES}
    res = {"truth_constants": TRUTH, "noise_um": NOISE_UM, "data_overrides": DATA_OVERRIDES,
           "seeds": seeds, "truth": truth, "truth_fine_mesh": truth_fine, "coverage": cov,
           "coverage_of_fine_mesh_truth": cov_fine,
           "median_calibrate_s": float(np.median([x["calibrate_s"] for x in rows])),
           "median_predict_s": float(np.median([x["predict_s"] for x in rows])),
           "per_seed": rows}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(res, indent=1) + "\n")
    print(json.dumps({"coverage": cov, "coverage_fine": cov_fine}, indent=1))


if __name__ == "__main__":
    main()
