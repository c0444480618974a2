"""The hidden-effect cases' table from the run directories of benchmarks/diagnosis_cases.py.

Read from what ``benchmarks/diagnosis_cases.py --work WORK`` leaves (BENCHMARKS.md, "Hidden
effects: diagnose, recalibrate, cover the truths"): per case the base run's design, the
diagnosis's first candidate and selection, each recalibration's posterior kind, RMS (noise sd,
``compare``), FE check, truths covered by the 95 % intervals, R-hat / min bulk ESS, design,
discretization check, and wall times.

Usage: python benchmarks/cases_table.py WORK [--data-dir runs/hidden_effect_data] [--json OUT]
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from diagnosis_cases import _covered, _truth  # noqa: E402

from solderpyro.config.rundir import RUN_JSON, RunDir  # noqa: E402


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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("work")
    ap.add_argument("--data-dir", default="runs/hidden_effect_data",
                    help="the cases' data CSVs, CASE.csv per case directory in WORK")
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    out = []
    for case in sorted(p for p in Path(a.work).iterdir() if (p / "base" / RUN_JSON).exists()):
        hidden, truth = _truth(Path(a.data_dir) / f"{case.name}.csv")
        rec = {"case": case.name, "hidden": hidden, "base": _run(case / "base")}
        dj = case / "base" / "diagnosis.json"
        if dj.exists():
            dg = json.loads(dj.read_text())
            rec["selected"] = dg.get("selected")
        withs = sorted(p for p in case.iterdir()
                       if p.name.startswith("with") and (p / "summary.csv").exists())
        runs = withs or [case / "base"]
        for w in runs:
            cov = _covered(w, truth)
            r = _run(w)
            cmp = w / "comparison.json"
            if cmp.exists():
                c = json.loads(cmp.read_text())
                r["compare_rms_um"] = [round(c["before"]["rms_um"], 4),
                                       round(c["after"]["rms_um"], 4)]
            r["covered"] = f"{sum(cov.values())}/{len(cov)}"
            r["missed"] = [k for k, v in cov.items() if not v]
            rec[w.name] = r
        out.append(rec)
        print(json.dumps(rec))
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
