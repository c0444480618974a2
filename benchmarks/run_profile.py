"""The FE's profile-likelihood interval of chosen parameters of finished calibrations.

Does a reported interval that misses the truth miss it because the likelihood excludes the
truth, or because the flat prior's volume ends the posterior short of where the likelihood
still admits it? For each run directory: the model rebuilt from its ``run.json`` (config
overrides, data, run store), the data less the discretization correction the run used
(``discretization_correction.npz``), and the profile of each ``--parameter`` through the FE,
every other parameter (form nuisances included) refitted by Levenberg-Marquardt from the run's
FE-exact samples (:func:`solderpyro.exact.posterior.profile_intervals`, the calibration's own
profile intervals); beside it the run's reported interval (summary.csv) and, with ``--truth``,
whether each holds the true value. The FE runs go through the run's store.

Usage: python benchmarks/run_profile.py RUN_DIR [RUN_DIR ...] --parameter T_sf [--truth 150]
       [--data-root OLD=NEW] [--json benchmarks/results/run_profile.json]
(e.g. the forms benchmark's slow residual stress near the faces, WORK/cases/NAME/with and its
noise seeds WORK/seeds/cases/NAME_seedS/with, --parameter T_sf --truth 150)
Prints, and writes to the results file (overwritten), each run's intervals and profile.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from pathlib import Path

import numpy as np

from solderpyro.config.compose import build, compose
from solderpyro.exact.posterior import profile_intervals
from solderpyro.io.measurements import read_measurements
from solderpyro.pipeline.problem import CalibrationProblem

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import Results, json_option  # noqa: E402


def moved(path: str, roots: list[tuple[str, str]]) -> str:
    """``path`` with the first matching ``OLD`` prefix of ``roots`` replaced by its ``NEW``."""
    for old, new in roots:
        if path.startswith(old):
            return new + path[len(old):]
    return path


def profile_run(run: Path, names: list[str], truth: list[float] | None,
                roots: list[tuple[str, str]]) -> dict:
    """The profiles of ``names`` in run directory ``run`` and its reported intervals."""
    info = json.loads((run / "run.json").read_text())
    meas = read_measurements(moved(info["data"], roots))
    cp = CalibrationProblem.build(build(compose(info["overrides"])), meas,
                                  moved(info["store"], roots), 64, False)
    y = cp.y.numpy()
    corr = run / "discretization_correction.npz"
    if corr.exists():
        z = np.load(corr)
        y = z["y_measured"] - z["delta"]
    samples = np.load(run / "exact_samples.npz")
    space = list(cp.space.names)
    if [str(n) for n in samples["names"]] != space:
        raise SystemExit(f"{run}: the FE-exact samples' parameters {list(samples['names'])} "
                         f"are not the model's {space}")
    missing = sorted(set(names) - set(space))
    if missing:
        raise SystemExit(f"{run}: no parameter {', '.join(missing)} (it has {', '.join(space)})")
    theta = samples["theta"]
    ssr = ((cp.observed(theta) - y[None]) ** 2).sum(1)  # the store holds these runs
    sigma = float(cp.priors.sigma_known or np.sqrt(np.nanmin(ssr) / len(y)))
    with (run / "summary.csv").open() as f:
        reported = {r["parameter"]: r for r in csv.DictReader(f)}
    t0 = time.perf_counter()
    pis = profile_intervals(cp.observed, cp.space, y, sigma, theta, ssr,
                            params=[space.index(n) for n in names])
    rows: list[dict] = []
    for k, p in enumerate(pis):
        rep = reported[p.parameter]
        row = {"parameter": p.parameter, "profile": [p.lower, p.upper],
               "reaches_bound": [bool(p.at_lower_bound), bool(p.at_upper_bound)],
               "reported": [float(rep["lo95"]), float(rep["hi95"]), rep["interval"]],
               "grid": p.grid.tolist(), "delta_chi2": (p.chi2 - p.chi2.min()).tolist()}
        if truth is not None:
            v = truth[k]
            row["truth"] = v
            row["inside"] = {"profile": bool(p.lower <= v <= p.upper),
                             "reported": bool(row["reported"][0] <= v <= row["reported"][1])}
        rows.append(row)
        print(f"{run}: {p.parameter} profile {p.lower:.4g}-{p.upper:.4g}, reported "
              f"{row['reported'][0]:.4g}-{row['reported'][1]:.4g}"
              + (f", truth {truth[k]:g} inside: {row['inside']}" if truth is not None else ""),
              flush=True)
    return {"run": str(run), "sigma_um": sigma, "profiles": rows,
            "profile_s": round(time.perf_counter() - t0, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, metavar="RUN_DIR")
    ap.add_argument("--parameter", required=True, help="comma-separated parameter names")
    ap.add_argument("--truth", default=None, help="comma-separated true values, in order")
    ap.add_argument("--data-root", action="append", default=[], metavar="OLD=NEW",
                    help="where a run's data or store moved since it ran (repeatable)")
    json_option(ap, __file__)
    a = ap.parse_args()
    names = [n for n in a.parameter.split(",") if n]
    truth = None if a.truth is None else [float(v) for v in a.truth.split(",")]
    if truth is not None and len(truth) != len(names):
        raise SystemExit(f"--truth: {len(truth)} values for {len(names)} parameters")
    if any("=" not in r for r in a.data_root):
        raise SystemExit("--data-root: give OLD=NEW")
    roots = [(r.split("=", 1)[0], r.split("=", 1)[1]) for r in a.data_root]
    res = Results(a.json)
    runs = [profile_run(r, names, truth, roots) for r in a.runs]
    res.write({"runs": runs}, runs=[str(r) for r in a.runs])


if __name__ == "__main__":
    main()
