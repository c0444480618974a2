"""The hidden-effect cases' table from the run directories of benchmarks/diagnosis_cases.py.

Read from what ``benchmarks/diagnosis_cases.py --work WORK`` leaves (BENCHMARKS.md, "Hidden
effects: diagnose, recalibrate, cover the truths"): per case the base run's design, the
diagnosis's first candidate and selection, each recalibration's posterior kind, RMS (noise sd,
``compare``), FE check, truths covered by the 95 % intervals, R-hat / min bulk ESS, design,
discretization check, and wall times.

Then the benchmark's bars over all cases (:func:`bars`): the hidden effect selected, false
alarms on clean data, the truths inside the reported 95 % intervals after adding the selected
effects (per parameter), the error after them, and the loop's wall time (calibrate, diagnose,
recalibrate; median). ``--json`` writes ``{"cases": [...], "bars": {...}}``.

Usage: python benchmarks/cases_table.py WORK [--data-dir runs/hidden_effect_data] [--json OUT]
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from diagnosis_cases import _covered, _truth, caveat_runs  # noqa: E402

from solderpyro.config.rundir import RUN_JSON, RunDir  # noqa: E402

#: the calibrated Anand constants (every other truth is an effect's parameter)
ANAND = ("s0", "QR", "xi", "m")


def _run(d: Path) -> dict:
    info = RunDir.read(d).info
    with (d / "summary.csv").open() as f:
        rows = list(csv.DictReader(f))
    rep = (d / "report.md").read_text().splitlines()
    rh, ess = [], []
    for line in rep:  # the report's posterior table: | p | ... | R-hat | ESS |
        cells = [c.strip() for c in line.strip("|").split("|")]
        # 7 cells before the reported-interval column, 8 since
        if len(cells) in (7, 8) and cells[0] in {r["parameter"] for r in rows}:
            try:
                rh.append(float(cells[-2]))
                ess.append(float(cells[-1]))
            except ValueError:
                pass
    chk = info.checks.fe_check
    disc = info.checks.discretization
    return {"posterior": info.posterior, "design": info.design.reason,
            "runs": info.n_runs, "fe_check_sd": round(chk["rms_over_sigma"], 2),
            "fe_ok": chk["ok"], "rhat": max(rh) if rh else None,
            "ess": min(ess) if ess else None,
            "discretization_chi2": disc.get("shift_chi2"),
            "seconds": round(sum(info.timing_s.values()))}


def final_runs(rec: dict) -> list[dict]:
    """The runs a user ends with: the recalibration with the selected effects (``with``),
    and with them and each candidate the verdict cannot rule out beside them (``caveat_runs``,
    as it advises); in a tie, the recalibration with each tied effect (``with_EFFECT``, as the
    verdict advises); else the base run."""
    if rec.get("with"):
        return [rec["with"]] + [rec[k] for k in rec.get("caveat_runs") or [] if rec.get(k)]
    tied = [rec[f"with_{e}"] for e in (rec.get("tie") or [[]])[0] if rec.get(f"with_{e}")]
    return tied or [rec["base"]]


def loop_seconds(rec: dict) -> list[tuple[str, float | None]]:
    """A case's loop by stage: ``[("calibrate", s), ("diagnose", s), ("recalibrate", s)
    per run a user ends with]`` (None where not timed)."""
    return [("calibrate", rec["base"].get("seconds")), ("diagnose", rec.get("diagnose_seconds")),
            *[("recalibrate", f.get("seconds")) for f in final_runs(rec)
              if f is not rec["base"]]]


def bars(records: list[dict]) -> dict:
    """The hidden-effect benchmark's figures over ``records`` (one per case, as :func:`main`
    makes them).

    Returns:
        ``selected``: cases with a hidden effect whose diagnosis selected every hidden effect,
        of those cases; ``named``: the same, counting a tie that names them (the verdict then
        advises recalibrating with each); ``caveat``: of the cases with a hidden effect not all
        selected (and no tie naming them), those where the selection and what the verdict says
        the data cannot rule out name every hidden effect together (the model fits and
        :mod:`solderpyro.diagnose.ruleout` names it, or the selected effects leave constants on
        the box's faces that it frees); ``false_alarms``:
        clean cases (hidden "none") with a selection, a tie or a misfit flagged, of the clean
        cases; ``coverage``: truths inside the 95 % intervals of the runs a user ends with
        (:func:`final_runs`), overall and per parameter (``[inside, of]``), and over the
        Anand constants alone (``coverage_constants``: an effect's size in a form other than
        the library's is a different quantity from the library parameter that stands for it);
        ``rms_after_sd_max``: the largest error after them in noise sd (``compare``; None
        where not run); ``loop_s_median``: the median over cases of calibrate + diagnose +
        recalibrate seconds (each tied recalibration counted); ``loop_s_by_threads``: that
        median per thread count a case ran with (``threads``; a case without one ran on one
        thread), ``{threads: [median, cases]}``: two cases at a time on 2 cores run one
        thread each, one case alone both.
    """
    hid = [r for r in records if r["hidden"] != "none"]
    clean = [r for r in records if r["hidden"] == "none"]

    def has(r: dict, names: list[str]) -> bool:
        return set(r["hidden"].split("+")) <= set(names)

    def is_named(r: dict) -> bool:  # selected, or named by a tie
        return has(r, r.get("selected") or []) or has(r, (r.get("tie") or [[]])[0])

    sel = sum(has(r, r.get("selected") or []) for r in hid)
    named = sum(is_named(r) for r in hid)
    unnamed = [r for r in hid if not is_named(r)]
    caveat = sum(has(r, (r.get("selected") or []) + (r.get("cannot_rule_out") or []))
                 for r in unnamed)
    alarms = sum(bool(r.get("selected") or r.get("tie") or r.get("misfit")) for r in clean)
    per: dict[str, list[int]] = {}
    rms = []
    loops = []
    by_threads: dict[str, list[float]] = {}
    for r in records:
        finals = final_runs(r)
        for f in finals:
            for k in f.get("truths", []):
                c = per.setdefault(k, [0, 0])
                c[0] += k not in f.get("missed", [])
                c[1] += 1
            if f.get("compare_rms_um") and r.get("sigma_um"):
                rms.append(f["compare_rms_um"][1] / r["sigma_um"])
        parts = loop_seconds(r)
        if all(v is not None for _, v in parts):
            loops.append(sum(v for _, v in parts))
            by_threads.setdefault(str(r.get("threads") or 1), []).append(loops[-1])
    inside, of = sum(c[0] for c in per.values()), sum(c[1] for c in per.values())
    anand = [c for k, c in per.items() if k in ANAND]
    return {"cases": len(records), "selected": [sel, len(hid)], "named": [named, len(hid)],
            "caveat": [caveat, len(unnamed)],
            "false_alarms": [alarms, len(clean)], "coverage": [inside, of],
            "coverage_constants": [sum(c[0] for c in anand), sum(c[1] for c in anand)],
            "coverage_per_parameter": per,
            "rms_after_sd_max": round(max(rms), 3) if rms else None,
            "loop_s_median": round(statistics.median(loops)) if loops else None,
            "loop_cases_timed": len(loops),
            "loop_s_by_threads": {k: [round(statistics.median(v)), len(v)]
                                  for k, v in sorted(by_threads.items())}}


def case_record(case: Path, data: Path) -> dict:
    """One case's row from its directory (``base``, the ``with*`` recalibrations) and its
    data CSV (the truth)."""
    hidden, truth = _truth(data)
    rec = {"case": case.name, "hidden": hidden, "base": _run(case / "base")}
    dj = case / "base" / "diagnosis.json"
    if dj.exists():
        dg = json.loads(dj.read_text())
        rec["selected"] = dg.get("selected")
        rec["misfit"] = dg.get("misfit")
        rec["verdict"] = dg.get("verdict")
        rec["tie"] = dg.get("indistinguishable") or []
        rec["cannot_rule_out"] = [r["effect"] for r in dg.get("cannot_rule_out") or []]
        rec["caveat_runs"] = list(caveat_runs(dg))
        rec["diagnose_seconds"] = round((dg.get("timing") or {}).get(
            "total", {}).get("seconds", 0)) or None
    rec["sigma_um"] = RunDir.read(case / "base").info.sigma_known
    withs = sorted(p for p in case.iterdir()
                   if p.name.startswith("with") and (p / "summary.csv").exists())
    for w in withs or [case / "base"]:
        cov = _covered(w, truth)
        r = _run(w)
        cmp = w / "comparison.json"
        if cmp.exists():
            c = json.loads(cmp.read_text())
            r["compare_rms_um"] = [round(c["before"]["rms_um"], 4),
                                   round(c["after"]["rms_um"], 4)]
        r["intervals"] = ("admitting" if (w / "intervals_admitting.csv").exists()
                          else "reported")
        r["covered"] = f"{sum(cov.values())}/{len(cov)}"
        r["missed"] = [k for k, v in cov.items() if not v]
        r["truths"] = list(cov)
        rec[w.name] = r
    return rec


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("work")
    ap.add_argument("--data-dir", default="runs/hidden_effect_data",
                    help="the cases' data CSVs, CASE.csv per case directory in WORK")
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    out = []
    for case in sorted(p for p in Path(a.work).iterdir() if (p / "base" / RUN_JSON).exists()):
        rec = case_record(case, Path(a.data_dir) / f"{case.name}.csv")
        out.append(rec)
        print(json.dumps(rec))
    b = bars(out)
    print(json.dumps({"bars": b}))
    if a.json:
        Path(a.json).write_text(json.dumps({"cases": out, "bars": b}, indent=1) + "\n")


if __name__ == "__main__":
    main()
