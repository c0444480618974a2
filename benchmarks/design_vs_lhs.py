"""The adaptive design against plain Latin hypercubes at the same FE budget.

    python benchmarks/design_vs_lhs.py [--datasets 10] [--lhs 100,200] [--work runs/design_vs_lhs]
        [--out benchmarks/results/design_vs_lhs.json] [--cluster local:2]

Datasets: full-field data (the 31 x 18 grid + A, B at the four seed times, 2,240 values) of
the clean model, each at its own truth (a Latin hypercube over the middle 60 % of the
calibration box, in the box's own unit coordinates) with its own noise seed (N(0, 0.05^2) um),
made by a *finer* FE than the calibration's (``mesh=fine``, dT 2 K, dt 150 s: no inverse crime).

Per dataset, one sweep job each (kept in WORK/sweep.json as it ends; a rerun resumes):

- ``exact``: the reference, the FE-exact posterior of the calibration's own FE
  (:func:`solderpyro.pipeline.fe_exact.fe_exact`: the FE's best fit from the box's middle, the
  chi-square profile along the ridge, 4 AMIS rounds of 128 FE runs; no surrogate);
- ``adaptive``: ``solderpyro calibrate --data D --out DIR --store STORE --quiet``, the defaults;
- ``lhsN``: the same command with a fixed design, ``--start N --budget N+4 --exact off``: one
  round on an N-run Latin hypercube (the same one for every dataset: it is data-independent,
  so the run store solves it once), 4 FE check runs, then the final posterior.

Accuracy, as the issue sets it: for each parameter, the largest of the errors of the 2.5, 50
and 97.5 % quantiles against the FE-exact posterior's, divided by the FE-exact 95 % interval's
width; a dataset's error is the largest over the parameters. Monte Carlo error of the
reference (AMIS, ESS ~300) is about 0.02 (median) to 0.04 (interval ends) of the width.
Also recorded: FE runs, wall time, the FE check, which truths each 95 % interval holds.
The summary (``summary`` in the JSON, printed) gives, per design, the median and mean error
over datasets, the median FE runs, and whether the adaptive design reached the best fixed
design's median error with at most half of its runs.
"""

from __future__ import annotations

import argparse
import csv
import functools
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from solderpyro.compute.executor import executor_from_options
from solderpyro.compute.sweep import sweep
from solderpyro.config.compose import build, compose
from solderpyro.config.rundir import RunDir
from solderpyro.fem.loading import SEED_TIMES

FINE = ["mesh=fine", "solver.stepping.dT_max=2.0", "solver.stepping.dt_max=150"]
NOISE = 0.05
QS = ("q2.5", "median", "q97.5")


def truths(n: int, seed: int = 2026) -> list[dict[str, float]]:
    """``n`` truths of the clean model: a Latin hypercube over the middle 60 % of the
    calibration box's unit cube (log where the box is), in physical units."""
    from scipy.stats import qmc

    box = build(compose([])).space
    u = 0.2 + 0.6 * qmc.LatinHypercube(d=box.dim, seed=seed).random(n)
    th = box.from_unit(torch.as_tensor(u, dtype=torch.float64)).numpy()
    return [{nm: float(f"{v:.5g}") for nm, v in zip(box.names, row, strict=True)}
            for row in th]


def dataset(work: Path, i: int, truth: dict[str, float]) -> Path:
    """Dataset ``i`` (noise seed ``i``), made by the finer FE unless already there."""
    from solderpyro.diagnose.hidden import HiddenTruth, make_dataset

    path = work / f"d{i:02d}" / "data.csv"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.csv")
        make_dataset(build(compose(FINE)), None, tmp, True, SEED_TIMES, noise=NOISE, seed=i,
                     truth=HiddenTruth(anand=truth))
        tmp.replace(path)  # a crash mid-write leaves no half dataset
    return path


def _quantiles(path: Path) -> dict[str, list[float]]:
    with path.open() as f:
        return {r["parameter"]: [float(r[q]) for q in QS] for r in csv.DictReader(f)}


def run_exact(data: Path, store: Path, seed: int) -> dict:
    """The FE-exact posterior of the calibration's FE for one dataset (the clean model, a
    start at the box's middle)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))  # also on a Dask worker
    from exact_posterior import exact_reference

    torch.set_num_threads(1)
    space = build(compose([])).space
    start = np.array([[(lo + hi) / 2 for lo, hi in zip(space.lower, space.upper, strict=True)]])
    ref, info = exact_reference(data, [], start, store, 128, 4, seed, lm_iters=15, noise=NOISE)
    return {"quantiles": {k: ref[k] for k in space.names},
            "ess": info["ess"], "khat": info["khat"], "reliable": info["reliable"],
            "fe_runs": info["fe_runs"], "best_chi2": info["best_fit"]["chi2"]}


def run_calibrate(data: Path, out: Path, store: Path, extra: list[str]) -> dict:
    """``solderpyro calibrate`` as a user types it (plus ``extra`` flags)."""
    cmd = [sys.executable, "-m", "solderpyro.cli", "calibrate", "--data", str(data),
           "--out", str(out), "--store", str(store), "--quiet", *extra]
    r = subprocess.run(cmd, capture_output=True, text=True)
    out.mkdir(parents=True, exist_ok=True)
    (out / "stdout.log").write_text(r.stdout + r.stderr)
    if r.returncode != 0:
        raise RuntimeError(f"calibrate failed (rc {r.returncode}); see {out / 'stdout.log'}")
    info = RunDir.read(out).info
    sur = out / "summary_surrogate.csv"
    ex = info.exact or {}
    return {"command": "solderpyro " + " ".join(cmd[3:]),
            "quantiles": _quantiles(out / "summary.csv"),
            "surrogate_quantiles": _quantiles(sur if sur.exists() else out / "summary.csv"),
            "reported": info.posterior, "trust": info.trust,
            "design_reason": info.design.reason,
            "design_fe_runs": info.design.fe_runs,
            "exact_fe_runs": ex.get("fe_runs", 0),
            "fe_check_rms_sd": info.checks.fe_check["rms_over_sigma"],
            "fe_check_ok": info.checks.fe_check["ok"]}


def job(name: str, work: str, lhs: tuple[int, ...]) -> dict:
    """One sweep job ``dNN/KIND`` (KIND: exact, adaptive, lhsN)."""
    w = Path(work)
    ds, kind = name.split("/")
    data = w / ds / "data.csv"
    t0 = time.perf_counter()
    if kind == "exact":
        rec = run_exact(data, w / "store", int(ds[1:]))
    elif kind == "adaptive":
        rec = run_calibrate(data, w / ds / kind, w / "store", [])
    else:
        n = int(kind[3:])
        rec = run_calibrate(data, w / ds / kind, w / "store",
                            ["--start", str(n), "--budget", str(n + 4), "--exact", "off"])
    rec["wall_s"] = round(time.perf_counter() - t0, 1)
    return rec


def error(q: dict[str, list[float]], ref: dict[str, list[float]]) -> dict[str, float]:
    """Per parameter: max over the 2.5/50/97.5 % quantiles of |q - q_ref| / ref's width."""
    return {k: float(max(abs(a - b) for a, b in zip(q[k], r, strict=True)) / (r[2] - r[0]))
            for k, r in ref.items()}


def summarize(res: dict, truth_of: dict[str, dict], kinds: list[str]) -> dict:
    """Per dataset and design: the error against the FE-exact posterior, FE runs, coverage;
    then medians over datasets and the issue's verdict."""
    table: dict[str, dict] = {}
    for ds, truth in truth_of.items():
        ex = res.get(f"{ds}/exact")
        if not ex or not ex.get("ok") or not ex.get("reliable"):
            continue  # no trustworthy reference: the dataset is not judged
        row = {}
        for kind in kinds:
            r = res.get(f"{ds}/{kind}")
            if not r or not r.get("ok"):
                continue
            e = error(r["quantiles"], ex["quantiles"])
            es = error(r["surrogate_quantiles"], ex["quantiles"])
            cov = {k: r["quantiles"][k][0] <= v <= r["quantiles"][k][2]
                   for k, v in truth.items()}
            row[kind] = {"error": max(e.values()), "error_by_parameter": e,
                         "surrogate_error": max(es.values()),
                         "fe_runs": r["design_fe_runs"] + r["exact_fe_runs"],
                         "fe_check_ok": r["fe_check_ok"], "reported": r["reported"],
                         "covered": sum(cov.values()), "wall_s": r["wall_s"]}
        table[ds] = row
    per_kind = {}
    for kind in kinds:
        rows = [t[kind] for t in table.values() if kind in t]
        if rows:
            per_kind[kind] = {
                "datasets": len(rows),
                "median_error": float(np.median([r["error"] for r in rows])),
                "mean_error": float(np.mean([r["error"] for r in rows])),
                "median_fe_runs": float(np.median([r["fe_runs"] for r in rows])),
                "max_fe_runs": int(max(r["fe_runs"] for r in rows)),
                "fe_check_rejected": sum(not r["fe_check_ok"] for r in rows),
                "truths_covered": f"{sum(r['covered'] for r in rows)}/"
                                  f"{len(rows) * len(next(iter(truth_of.values())))}",
                "median_wall_s": float(np.median([r["wall_s"] for r in rows]))}
    verdict = None
    fixed = {k: v for k, v in per_kind.items() if k.startswith("lhs")}
    if "adaptive" in per_kind and fixed:
        best = min(fixed, key=lambda k: fixed[k]["median_error"])
        ad = per_kind["adaptive"]
        verdict = {"best_fixed": best,
                   "adaptive_median_error": ad["median_error"],
                   "best_fixed_median_error": fixed[best]["median_error"],
                   "adaptive_max_fe_runs": ad["max_fe_runs"],
                   "best_fixed_fe_runs": fixed[best]["median_fe_runs"],
                   "as_accurate": ad["median_error"] <= fixed[best]["median_error"],
                   "at_most_half_the_runs":
                       ad["max_fe_runs"] <= 0.5 * fixed[best]["median_fe_runs"]}
    return {"per_dataset": table, "per_design": per_kind, "verdict": verdict}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--datasets", type=int, default=10)
    ap.add_argument("--lhs", default="100,200", help="fixed designs' sizes, comma-separated")
    ap.add_argument("--only", default="", help="job kinds to run now, e.g. exact,adaptive")
    ap.add_argument("--subset", default="", help="datasets to run now, e.g. 2-5 (default all; "
                    "the summary covers every dataset recorded)")
    ap.add_argument("--work", default="runs/design_vs_lhs")
    ap.add_argument("--out", default="benchmarks/results/design_vs_lhs.json")
    ap.add_argument("--cluster", default=None, metavar="local:N",
                    help="run the jobs in parallel on a Dask LocalCluster "
                         "(solderpyro.compute.sweep)")
    ap.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT")
    a = ap.parse_args()
    work = Path(a.work).resolve()
    work.mkdir(parents=True, exist_ok=True)
    lhs = tuple(int(v) for v in a.lhs.split(","))
    kinds = ["exact", "adaptive", *(f"lhs{n}" for n in lhs)]
    run_kinds = [k for k in kinds if not a.only or k in a.only.split(",")]
    tr = truths(a.datasets)
    truth_of = {}
    for i, t in enumerate(tr, start=1):
        dataset(work, i, t)
        truth_of[f"d{i:02d}"] = t
    sub = set(truth_of)
    if a.subset:
        lo, _, hi = a.subset.partition("-")
        sub = {f"d{i:02d}" for i in range(int(lo), int(hi or lo) + 1)}
    names = [f"{ds}/{k}" for ds in truth_of for k in run_kinds if ds in sub]
    with executor_from_options(a.cluster, a.scheduler) as ex:
        res = sweep(names, functools.partial(job, work=str(work), lhs=lhs),
                    work / "sweep.json", ex)
    all_res = json.loads((work / "sweep.json").read_text()).get("jobs", {})  # every run so far
    all_res.update(res)
    summ = summarize(all_res, truth_of, kinds[1:])
    out = {"command": "python benchmarks/design_vs_lhs.py " + " ".join(sys.argv[1:]),
           "truths": truth_of, "jobs": all_res, **summ}
    Path(a.out).write_text(json.dumps(out, indent=1, default=float) + "\n")
    print(json.dumps({"per_design": summ["per_design"], "verdict": summ["verdict"]}, indent=1))


if __name__ == "__main__":
    main()
