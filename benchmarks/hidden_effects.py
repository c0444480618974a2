"""Proof on data with a hidden effect: calibrate -> diagnose -> add the top effect
-> calibrate again, for one dataset per effect plus a clean one, full-field and point data.

Usage: python benchmarks/hidden_effects.py [--kind field|point|both] [--effects a,b,...]
       [--budget N] [--start N] [--q N] [--chains 2] [--warmup 300] [--draws 500]
       [--exact auto|on|off] [--work runs/hidden] [--store DIR]
       [--out benchmarks/results/hidden_effects.json] [--cluster local:2 | --scheduler ADDRESS]

Every calibration is ``solderpyro calibrate``'s (solderpyro.pipeline.calibrate_specimen: the
adaptive design up to ``--budget`` FE runs, then NUTS); the FE-exact posterior and profile
intervals (``--exact``) apply to the 'add it' calibrations only: the base one misfits by
design (the hidden effect), so it runs with ``exact.mode=off``.

The cases run as one sweep (solderpyro.compute.sweep): one after another, or in parallel on a Dask
cluster with ``--cluster``/``--scheduler``. Each case's result is kept in WORK/sweep.json as
soon as it is done (a rerun skips finished cases; FE runs are reused from the run store), and
the JSON file gets every case at the end. Full-field data: the 31 x 18 grid (+ A, B) at
the four seed times; point data: A and B at the seven extended times; noise 0.05 um; the truth's
Anand constants are solderpyro.diagnose.hidden.TRUTH.
"""

from __future__ import annotations

import argparse
import ast
import functools
import json
import logging
import time
from pathlib import Path

import torch

from solderpyro.compute.executor import executor_from_options
from solderpyro.compute.sweep import sweep
from solderpyro.config.compose import build, compose
from solderpyro.config.rundir import RunDir
from solderpyro.config.settings import (
    DesignSettings,
    ExactSettings,
    SamplerSettings,
    SurrogateSettings,
)
from solderpyro.diagnose import diagnose
from solderpyro.diagnose.compare import compare
from solderpyro.diagnose.hidden import TRUTH, make_dataset
from solderpyro.effects import EFFECTS
from solderpyro.fem.loading import EXTENDED_TIMES, SEED_TIMES
from solderpyro.io.measurements import read_measurements
from solderpyro.pipeline import CalibrationSettings, calibrate_specimen
from solderpyro.specimen import output_points


def _settings(setup, a, refit: bool) -> CalibrationSettings:
    """``solderpyro calibrate``'s settings from this script's options; the FE-exact step
    (``--exact``) for the 'add it' fits only."""
    dflt = DesignSettings()
    start = a.start if a.start is not None else dflt.start
    return CalibrationSettings(
        design=DesignSettings(start=start, batch=a.q, budget=a.budget),
        surrogate=SurrogateSettings(**setup.surrogate),
        sampler=SamplerSettings(chains=a.chains, warmup=a.warmup, draws=a.draws),
        exact=ExactSettings(mode=a.exact if refit else "off", runs=a.exact_runs,
                            rounds=a.exact_rounds, profile=a.exact_profile,
                            profile_ci="off" if a.no_profile_ci else "on"),
        seed=0, store=a.store or a.work + "/store", progress=False)


def _calibrate(overrides, data, out, a, refit=False):
    setup = build(compose(overrides))
    meas = read_measurements(data, valid_points=output_points(setup.problem))
    return calibrate_specimen(setup, meas, out, _settings(setup, a, refit),
                              record={"overrides": overrides})


def _covered(run_dir: Path, truth: dict) -> dict:
    iv = _intervals(run_dir)
    return {k: iv[k][0] <= v <= iv[k][1] for k, v in truth.items() if k in iv}


def _intervals(run_dir: Path) -> dict:
    import csv

    with open(run_dir / "summary.csv", newline="") as fh:
        return {r["parameter"]: [float(r["q2.5"]), float(r["q97.5"])]
                for r in csv.DictReader(fh)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--kind", default="field", choices=("field", "point", "both"))
    ap.add_argument("--effects", default="", help="hidden effects (default: all + clean)")
    ds, es = DesignSettings(), ExactSettings()
    ap.add_argument("--budget", type=int, default=None,
                    help="most FE runs of each adaptive design (default: the calibration's, by "
                         "its number of FE parameters)")
    ap.add_argument("--start", type=int, default=None,
                    help=f"Latin-hypercube runs before the first round (default {ds.start})")
    ap.add_argument("--q", type=int, default=ds.batch, help="FE runs acquired per round")
    ap.add_argument("--chains", type=int, default=2)
    ap.add_argument("--warmup", type=int, default=300)
    ap.add_argument("--draws", type=int, default=500)
    ap.add_argument("--work", default="runs/hidden")
    ap.add_argument("--store", default="", help="FE run store (default: WORK/store)")
    ap.add_argument("--out", default="benchmarks/results/hidden_effects.json")
    ap.add_argument("--exact", default=es.mode, choices=("auto", "on", "off"),
                    help="the FE-exact posterior and profile-likelihood intervals of the 'add "
                         "it' calibrations (calibrate --exact; auto: when the design's budget "
                         "runs out with the FE disagreeing); the base calibrations: off")
    ap.add_argument("--exact-runs", type=int, default=es.runs,
                    help="FE runs per importance-sampling round")
    ap.add_argument("--exact-rounds", type=int, default=es.rounds)
    ap.add_argument("--exact-profile", type=int, default=es.profile)
    ap.add_argument("--no-profile-ci", action="store_true",
                    help="skip the profile-likelihood intervals after the FE-exact step "
                         "(else: whether they hold the truth is recorded)")
    ap.add_argument("--cluster", default=None, metavar="local:N",
                    help="run the cases in parallel on a Dask LocalCluster "
                         "(solderpyro.compute.sweep)")
    ap.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                    help="run the cases on a running Dask cluster")
    ap.add_argument("--with-dir", default="with_{e}",
                    help="directory name of an 'add it' calibration ({e}: the effect)")
    a = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    torch.set_num_threads(1)
    out = Path(a.out)
    done = json.loads(out.read_text()) if out.exists() else []
    seen = {(r["kind"], r["hidden"]) for r in done}
    kinds = ("field", "point") if a.kind == "both" else (a.kind,)
    hidden = [h.strip() for h in a.effects.split(",") if h.strip()] or ["none", *EFFECTS]
    jobs = [f"{kind}/{h}" for kind in kinds for h in hidden if (kind, h) not in seen]
    # one sweep job per case (solderpyro.compute.sweep): in turn, or in parallel with --cluster
    with executor_from_options(a.cluster, a.scheduler) as ex:
        res = sweep(jobs, functools.partial(run_case, a=a), Path(a.work) / "sweep.json", ex)
    for j in jobs:
        kind, h = j.split("/")
        rec = res[j] if res[j].get("ok") else {"kind": kind, "hidden": h, **res[j]}
        done.append(rec)
        print(json.dumps(rec), flush=True)
    out.write_text(json.dumps(done, indent=2) + "\n")


def run_case(job: str, a: argparse.Namespace) -> dict:
    """One case ``KIND/HIDDEN``: make the data, calibrate, diagnose, add the top effect."""
    torch.set_num_threads(1)
    kind, h = job.split("/")
    base = build(compose([]))
    times = SEED_TIMES if kind == "field" else EXTENDED_TIMES
    ov = [f"loading.output_times=[{','.join(str(t) for t in times)}]"]
    t0 = time.perf_counter()
    d = Path(a.work) / kind / h
    d.mkdir(parents=True, exist_ok=True)
    data = d / "data.csv"
    if not data.exists():  # a rerun reuses the dataset it wrote
        make_dataset(base, None if h == "none" else h, data, kind == "field", times,
                     seed=1)
    meta = read_measurements(data).meta
    if not (d / "base" / "draws.npz").exists():  # a rerun re-diagnoses finished ones
        _calibrate(ov, data, d / "base", a)
    dg = diagnose(d / "base", n_draws=2, progress=False)
    run = RunDir.read(d / "base").info
    rec = {"kind": kind, "hidden": h, "hidden_values": meta.get("hidden_values"),
           "surrogate": f"{run.surrogate.inputs} ({run.surrogate.kernel})"
           if run.surrogate else "None (None)",
           "design_base": {"reason": run.design.reason, "fe_runs": run.design.fe_runs},
           "hidden_rms_point_um": meta.get("hidden_rms_point_um"),
           "misfit": dg.misfit, "verdict": dg.verdict,
           "ranking": [(r["effect"], r["evidence"], r["flagged"]) for r in dg.ranking],
           "indistinguishable": dg.indistinguishable,
           "rank_of_hidden": next((i + 1 for i, r in enumerate(dg.ranking)
                                   if r["effect"] == h), None)}
    # what the diagnosis says to add (forward steps: possibly several effects); where it
    # cannot tell candidates apart, refit each one as a user would and keep the best by ELPD
    group = ([",".join(dg.selected)] if dg.selected and not dg.indistinguishable
             else list(dg.indistinguishable[0]) if dg.indistinguishable else [])
    rec["selected"], rec["explained"] = dg.selected, dg.explained
    if group:
        refits = {}
        for e in group:
            wd = d / a.with_dir.format(e=e.replace(",", "+"))
            if not (wd / "draws.npz").exists():
                _calibrate([*ov, f"effects=[{e}]"], data, wd, a, refit=True)
            cmp = compare(d / "base", wd)
            truth = dict(TRUTH)
            if h == e and meta.get("hidden_values"):
                truth.update(ast.literal_eval(meta["hidden_values"]))
            info = RunDir.read(wd).info
            ex = info.exact or {}
            refits[e] = {"rms_after_um": cmp["after"]["rms_um"],
                         "elpd_gain": cmp["elpd_gain"],
                         "covered_after": _covered(wd, truth),
                         "intervals": _intervals(wd),
                         "fe_check": info.checks.fe_check,
                         "design": {"reason": info.design.reason,
                                    "fe_runs": info.design.fe_runs},
                         "posterior": info.posterior,
                         **({"exact": {k: ex.get(k) for k in (
                             "ess", "khat", "reliable", "fe_runs", "coordinates")}}
                            if ex else {}),
                         **({"identifiability": ex["identifiability"]["advice"]}
                            if ex.get("identifiability") else {}),
                         **({"profile_ci": {p["parameter"]: [p["lower"], p["upper"]]
                                            for p in ex["profile_ci"]},
                             "covered_profile_ci": {
                                 p["parameter"]: p["lower"] <= truth[p["parameter"]]
                                 <= p["upper"] for p in ex["profile_ci"]
                                 if p["parameter"] in truth}}
                            if ex.get("profile_ci") else {})}
        best = max(refits, key=lambda e: refits[e]["elpd_gain"])
        rec.update({"added": best, "rms_before_um": cmp["before"]["rms_um"],
                    **refits[best]})
        if len(refits) > 1:
            rec["group_refits"] = refits
    rec["covered_base"] = _covered(d / "base", TRUTH)
    rec["seconds"] = time.perf_counter() - t0
    return rec


if __name__ == "__main__":
    main()
