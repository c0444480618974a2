"""The adaptive design on data nobody here calibrates with.

For each case: full-field data (the 31 x 18 grid + A, B at the four seed times, noise 0.05 um)
made by a *finer* FE than the calibration's (``mesh=fine``, time steps dT 2 K / dt 150 s: no
inverse crime), with one hidden effect (or none); then exactly what a user types, with the
default flags and the true effect switched on:

    solderpyro calibrate --data DATA --out DIR --store STORE --quiet effects=[EFFECT]

Recorded per case (appended to the JSON as soon as it is done; a rerun skips finished cases):
wall time, why the design stopped and its FE runs, the FE check (best RMS over posterior draws
in noise sd, ok), which truths lie in the 95 % intervals (summary.csv), the trust line.

Usage: python benchmarks/design_hidden.py [--cases modulus_temperature,none,...]
       [--work runs/design_hidden] [--out benchmarks/results/design_hidden.json]
       [--cluster local:2 | --scheduler tcp://HOST:PORT]

The cases run as one sweep (:mod:`solderpyro.compute.sweep`): one after another by default, in
parallel on a Dask cluster with ``--cluster``/``--scheduler``; each finished case is kept in
WORK/sweep.json as it ends, so a rerun resumes.
"""

from __future__ import annotations

import argparse
import ast
import csv
import functools
import json
import subprocess
import sys
import time
from pathlib import Path

from solderpyro.calibration.intervals import reported_interval
from solderpyro.compute.executor import executor_from_options
from solderpyro.compute.sweep import sweep
from solderpyro.config.compose import build, compose
from solderpyro.config.rundir import RunDir
from solderpyro.diagnose.hidden import TRUTH, make_dataset
from solderpyro.fem.loading import SEED_TIMES

FINE = ["mesh=fine", "solver.stepping.dT_max=2.0", "solver.stepping.dt_max=150"]


def _rhat_max(nc: Path) -> float:
    """The largest R-hat of the surrogate posterior (ArviZ) in ``nc``."""
    import arviz as az

    r = az.rhat(az.from_netcdf(str(nc)))
    return float(max(float(r[v].max()) for v in r.data_vars))


def record(case: str, data: Path, run: Path, command: str, wall: float) -> dict:
    """One case's result from its run directory."""
    info = RunDir.read(run).info
    truth = dict(TRUTH)
    for line in data.read_text().splitlines():
        if line.startswith("# hidden_values:"):
            truth.update(ast.literal_eval(line.split(":", 1)[1].strip()))
    with (run / "summary.csv").open() as f:
        rows = {row["parameter"]: row for row in csv.DictReader(f)}
    ivs = {k: reported_interval(rows[k]) for k in truth if k in rows}
    cover = {k: lo <= truth[k] <= hi for k, (lo, hi) in ivs.items()}
    chk = info.checks.fe_check
    return {"case": case, "command": command, "wall_s": round(wall, 1),
            "design": {"reason": info.design.reason, "fe_runs": info.design.fe_runs},
            "rounds": len(info.design.record["rounds"]),
            "fe_check_rms_sd": chk["rms_over_sigma"], "fe_check_ok": chk["ok"],
            "covered": cover, "n_covered": sum(cover.values()), "n_truth": len(cover),
            "intervals": {k: list(iv) for k, iv in ivs.items()},
            "r_hat_max": _rhat_max(run / "posterior.nc"),
            "posterior": info.posterior, "trust": info.trust,
            "timing_s": info.timing_s}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", default="modulus_temperature,none",
                    help="hidden effects, comma-separated ('none': clean data)")
    ap.add_argument("--work", default="runs/design_hidden")
    ap.add_argument("--out", default="benchmarks/results/design_hidden.json")
    ap.add_argument("--seed", type=int, default=0, help="noise seed of the data")
    ap.add_argument("--cluster", default=None, metavar="local:N",
                    help="run the cases in parallel on a Dask LocalCluster "
                         "(solderpyro.compute.sweep)")
    ap.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                    help="run the cases on a running Dask cluster")
    ap.add_argument("--record", default="", metavar="CASE:DATA:RUN_DIR:WALL_S",
                    help="record a run made by hand with this script's command instead")
    a = ap.parse_args()
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    outp = Path(a.out)
    done = json.loads(outp.read_text()) if outp.exists() else {"cases": []}
    have = {c["case"] for c in done["cases"]}
    if a.record:
        case, data_s, run_s, wall_s = a.record.split(":")
        rec = record(case, Path(data_s), Path(run_s),
                     f"solderpyro calibrate --data {data_s} --out {run_s} --quiet "
                     f"effects=[{case}]", float(wall_s))
        done["cases"] = [c for c in done["cases"] if c["case"] != case] + [rec]
        outp.write_text(json.dumps(done, indent=1) + "\n")
        print(json.dumps(rec, indent=1))
        return
    cases = [c.strip() for c in a.cases.split(",") if c.strip()]
    todo = [c for c in cases if c not in have]
    for c in set(cases) - set(todo):
        print(f"{c}: done already")
    # one sweep job per case (solderpyro.compute.sweep): in turn, or in parallel with --cluster
    with executor_from_options(a.cluster, a.scheduler) as ex:
        jobs = sweep(todo, functools.partial(run_case, work=str(work.resolve()), seed=a.seed),
                     work / "sweep.json", ex)
    for case in todo:
        rec = jobs[case] if jobs[case].get("ok") else {"case": case, **jobs[case]}
        done["cases"] = [c for c in done["cases"] if c["case"] != case] + [rec]
        print(json.dumps(rec, indent=1))
    outp.write_text(json.dumps(done, indent=1) + "\n")


def run_case(case: str, work: str, seed: int) -> dict:
    """One case: the finer FE makes the data (unless there), then the default calibrate."""
    w = Path(work)
    data = w / f"data_{case}.csv"
    if not data.exists():  # the finer FE makes the data
        make_dataset(build(compose(FINE)), None if case == "none" else case, data, True,
                     SEED_TIMES, noise=0.05, seed=seed)
    run = w / f"cal_{case}"
    cmd = [sys.executable, "-m", "solderpyro.cli", "calibrate", "--data", str(data),
           "--out", str(run), "--store", str(w / "store"), "--quiet"]
    if case != "none":
        cmd.append(f"effects=[{case}]")
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    (w / f"cal_{case}.log").write_text(r.stdout + r.stderr)
    if r.returncode != 0:
        raise RuntimeError(f"{case}: calibrate failed (rc {r.returncode}); see cal_{case}.log")
    return record(case, data, run, " ".join(cmd[1:]), wall)

if __name__ == "__main__":
    main()
