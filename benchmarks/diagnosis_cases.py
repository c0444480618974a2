"""The diagnosis on data nobody here calibrates with.

Per case, exactly what a user types, default flags, on a measurement CSV made by a finer FE
than the calibration's (``mesh=fine``, 2 K / 150 s steps; see benchmarks/design_hidden.py):

    solderpyro calibrate --data DATA --out WORK/NAME/base --store STORE --quiet
    solderpyro diagnose WORK/NAME/base --quiet
    solderpyro calibrate --data DATA --out WORK/NAME/with --store STORE --quiet \
        --warm-from WORK/NAME/base effects=[SELECTED]          # when the diagnosis selects
    solderpyro compare WORK/NAME/base WORK/NAME/with
    (--with-hidden: the same recalibration and compare with the hidden effect, into
     WORK/NAME/with_HIDDEN, where the diagnosis did not select it)

A base run directory already there (e.g. from ``solderpyro sweep``) is used as it is
(``--base NAME=DIR``). Recorded per case (``--out`` JSON, each case as it ends; a rerun skips
finished ones): the hidden effects, the verdict, what was selected, whether it is explained,
each candidate's likelihood ratio, RMS after and flag, failed refits, the RMS before/after by
``compare`` (noise sd), the FE check after, which truths the intervals hold, the diagnosis's
cost. The cases run as one sweep (``--cluster local:2``: two at a time).

Usage: python benchmarks/diagnosis_cases.py --data NAME=CSV ... [--base NAME=DIR ...]
       [--work runs/diagnosis_cases] [--out benchmarks/results/diagnosis_cases.json]
       [--no-recalibrate] [--cluster local:2] [--keep-diagnosis] [--with-hidden]
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
from solderpyro.config.rundir import RunDir
from solderpyro.diagnose.hidden import TRUTH
from solderpyro.io.measurements import read_measurements


def _cli(args: list[str], log: Path) -> float:
    """Run ``solderpyro ARGS`` in a subprocess, its output to ``log``; returns the wall s."""
    t0 = time.perf_counter()
    with log.open("w") as f:
        rc = subprocess.run([sys.executable, "-m", "solderpyro.cli", *args], stdout=f,
                            stderr=subprocess.STDOUT).returncode
    if rc != 0:
        raise RuntimeError(f"solderpyro {args[0]} exited {rc}: see {log}")
    return round(time.perf_counter() - t0, 1)


def _truth(data: Path) -> tuple[str, dict[str, float]]:
    """The hidden effects' names and every true value, from the data file's metadata."""
    meta = read_measurements(data).meta
    truth = ast.literal_eval(meta["truth"]) if meta.get("truth") else dict(TRUTH)
    if meta.get("hidden_values"):
        truth.update(ast.literal_eval(meta["hidden_values"]))
    return meta.get("hidden_effect", "none"), truth


def _covered(run: Path, truth: dict[str, float], central: bool = False) -> dict[str, bool]:
    """Which truths the run's reported 95 % intervals hold: summary.csv's, or where a
    diagnosis of the run named effects the data cannot rule out, the intervals admitting them
    (``intervals_admitting.csv``, what the diagnosis reports for the constants then);
    ``central``: summary.csv's equal-tailed ones, as recorded before the face-anchored
    intervals."""
    with (run / "summary.csv").open() as f:
        rows = {r["parameter"]: r for r in csv.DictReader(f)}
    adm = run / "intervals_admitting.csv"
    admitted = {}
    if adm.exists() and not central:
        with adm.open() as f:
            admitted = {r["parameter"]: (float(r["lo95"]), float(r["hi95"]))
                        for r in csv.DictReader(f)}
    out = {}
    for k, v in truth.items():
        if k in rows:
            lo, hi = ((float(rows[k]["q2.5"]), float(rows[k]["q97.5"])) if central
                      else admitted.get(k) or reported_interval(rows[k]))
            out[k] = lo <= v <= hi
    return out


def _recalibrate(csv_p: Path, base: Path, wd: Path, effects: list[str], store: str,
                 truth: dict[str, float], wall: dict[str, float]) -> dict:
    """``calibrate --warm-from BASE effects=[...]`` into ``wd`` (unless there), then compare."""
    eff = ",".join(effects)
    if not (wd / "draws.npz").exists():
        wall[f"recalibrate {eff}"] = _cli(
            ["calibrate", "--data", str(csv_p), "--out", str(wd), "--store", store, "--quiet",
             "--warm-from", str(base), f"effects=[{eff}]"], wd.parent / f"{wd.name}.log")
    wall[f"compare {eff}"] = _cli(["compare", str(base), str(wd)],
                                  wd.parent / f"{wd.name}_compare.log")
    cmp = json.loads((wd / "comparison.json").read_text())
    info = RunDir.read(wd).info
    sig = float(info.sigma_known or 0.05)
    return {"rms_before_sd": cmp["before"]["rms_um"] / sig,
            "rms_after_sd": cmp["after"]["rms_um"] / sig,
            "fe_check_after": {k: info.checks.fe_check.get(k)
                               for k in ("rms_over_sigma", "ok")},
            "covered_after": _covered(wd, truth),
            "covered_after_central": _covered(wd, truth, central=True),
            "intervals_after": _intervals(wd)}


def _intervals(run: Path) -> dict[str, list]:
    """Each parameter's reported 95 % interval and its kind (central or from a box face)."""
    with (run / "summary.csv").open() as f:
        return {r["parameter"]: [*reported_interval(r), r.get("interval", "central")]
                for r in csv.DictReader(f)}


def caveat_runs(dg: dict) -> dict[str, list[str]]:
    """The recalibrations a diagnosis ``dg`` (diagnosis.json) advises beside its selection:
    run directory name -> effects, one per candidate that frees the constants the selection
    leaves on the box's faces (a ``cannot_rule_out`` entry with ``with``)."""
    out = {}
    for r in dg.get("cannot_rule_out") or []:
        if r.get("with"):
            effs = [*r["with"], r["effect"]]
            out["with_" + "+".join(effs)] = effs
    return out


def run_case(name: str, data: dict[str, str], bases: dict[str, str], work: str, store: str,
             recalibrate: bool, keep_diagnosis: bool = False, with_hidden: bool = False
             ) -> dict:
    """One case: calibrate (unless its base exists), diagnose, recalibrate, compare
    (``with_hidden``: also with the hidden effect when the diagnosis did not select it)."""
    w = Path(work) / name
    w.mkdir(parents=True, exist_ok=True)
    csv_p = Path(data[name]).resolve()
    base = Path(bases.get(name, w / "base"))
    wall: dict[str, float] = {}
    if not (base / "draws.npz").exists():
        wall["calibrate"] = _cli(["calibrate", "--data", str(csv_p), "--out", str(base),
                                  "--store", store, "--quiet"], w / "calibrate.log")
    if not (keep_diagnosis and (base / "diagnosis.json").exists()):
        wall["diagnose"] = _cli(["diagnose", str(base), "--quiet"], w / "diagnose.log")
    dg = json.loads((base / "diagnosis.json").read_text())
    hidden, truth = _truth(csv_p)
    rec: dict = {
        "case": name, "data": str(csv_p), "hidden": hidden, "base": str(base),
        "verdict": dg["verdict"], "misfit": dg["misfit"], "explained": dg.get("explained"),
        "selected": dg.get("selected", []), "tie": dg.get("indistinguishable", []),
        "base_fit": {k: (dg.get("base") or {}).get(k) for k in ("chi2", "start", "converged")},
        "ranking": [{k: r.get(k) for k in ("effect", "refit", "statistic", "dof",
                                           "rms_after_sd", "systematic_share", "clears_floor",
                                           "flagged", "fingerprint_correlation")}
                    for r in dg["ranking"]],
        "failed": [r["effect"] for r in dg.get("failed", [])],
        "first_is_hidden": bool(dg["ranking"]) and dg["ranking"][0]["effect"] in
        hidden.split("+"),
        "diagnose_timing": dg.get("timing", {}).get("total"), "wall_s": wall}
    if recalibrate and rec["selected"]:
        # a tie after the selection is about what remains: the advice is the selection
        rec.update(_recalibrate(csv_p, base, w / "with", rec["selected"], store, truth, wall))
        # where the selection leaves constants on the faces that another candidate frees at a
        # fit as good, the verdict advises recalibrating with it too: a user does both
        rec["caveat_recalibrated"] = {
            nm: _recalibrate(csv_p, base, w / nm, effs, store, truth, wall)
            for nm, effs in caveat_runs(dg).items()}
    elif recalibrate and rec["tie"]:
        # The verdict names no winner; a user tries each tied effect, as its advice says.
        rec["tie_recalibrated"] = {
            e: _recalibrate(csv_p, base, w / f"with_{e}", [e], store, truth, wall)
            for e in rec["tie"][0]}
    eff = [e for e in hidden.split("+") if e != "none"]
    tried = ([rec["selected"]] if rec["selected"] else []) + \
        ([[e] for e in rec["tie"][0]] if rec["tie"] and not rec["selected"] else [])
    if recalibrate and with_hidden and eff and eff not in tried:
        # "after adding the hidden effect": what a user who knows the effect does, also
        # where the data cannot tell it from the others (the point data)
        rec["hidden_recalibrated"] = _recalibrate(csv_p, base, w / f"with_{'+'.join(eff)}",
                                                  eff, store, truth, wall)
    return rec


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", nargs="+", action="extend", required=True, metavar="NAME=CSV")
    ap.add_argument("--base", nargs="*", action="extend", default=[], metavar="NAME=DIR",
                    help="existing base run directories (default WORK/NAME/base, calibrated "
                         "here when missing)")
    ap.add_argument("--work", default="runs/diagnosis_cases")
    ap.add_argument("--store", default=None, help="FE run store (default WORK/store)")
    ap.add_argument("--out", default="benchmarks/results/diagnosis_cases.json")
    ap.add_argument("--no-recalibrate", action="store_true")
    ap.add_argument("--keep-diagnosis", action="store_true",
                    help="use a base run's diagnosis.json as it is (default: diagnose again)")
    ap.add_argument("--with-hidden", action="store_true",
                    help="also recalibrate with the data's hidden effect where the diagnosis "
                         "did not select it (the issue's 'after adding the hidden effect')")
    ap.add_argument("--cluster", default=None, metavar="local:N")
    ap.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT")
    a = ap.parse_args()

    def pairs(items: list[str], what: str) -> dict[str, str]:
        bad = [s for s in items if "=" not in s]
        if bad:
            raise SystemExit(f"--{what} takes NAME=PATH, got {bad}")
        return dict(s.split("=", 1) for s in items)

    data, bases = pairs(a.data, "data"), pairs(a.base, "base")
    work = Path(a.work).resolve()
    work.mkdir(parents=True, exist_ok=True)
    store = str(Path(a.store).resolve()) if a.store else str(work / "store")
    outp = Path(a.out)
    done = json.loads(outp.read_text()) if outp.exists() else {"cases": []}
    with executor_from_options(a.cluster, a.scheduler) as ex:
        jobs = sweep(list(data), functools.partial(
            run_case, data=data, bases={k: str(Path(v).resolve()) for k, v in bases.items()},
            work=str(work), store=store, recalibrate=not a.no_recalibrate,
            keep_diagnosis=a.keep_diagnosis, with_hidden=a.with_hidden),
            work / "diagnosis_sweep.json", ex)
    for name in data:
        rec = jobs[name] if jobs[name].get("ok") else {"case": name, **jobs[name]}
        done["cases"] = [c for c in done["cases"] if c.get("case") != name] + [rec]
        print(json.dumps({k: rec.get(k) for k in ("case", "hidden", "selected", "explained",
                                                   "rms_after_sd", "error")}))
    outp.write_text(json.dumps(done, indent=1) + "\n")


if __name__ == "__main__":
    main()
