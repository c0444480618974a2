"""The diagnosis benchmark on physics in forms other than the library's, case by case.

Every case is a dataset the finer FE makes (``mesh=fine``, 2 K / 150 s steps, noise 0.05 um,
the 31 x 18 grid plus A and B, its own noise seed) with hidden effects in the forms of
benchmarks/forms.py, then the loop a user runs with default flags
(:func:`diagnosis_cases.run_case`: calibrate, diagnose, recalibrate with the selection,
compare), each case with its own FE run store so its wall times are those of a fresh user.

The plan (:func:`plan`): each sized form at three sizes (0.2, 0.4, 1.2 um RMS change of the
point data) crossed with three sets of Anand constants (the seed's, an interior one, one near
the box's faces) as a Latin square (each size once, each set once; ``--full``: all nine); the
two residual-stress forms at each set; two-effect cases; ten clean datasets (the three sets
in turn). Cases run in an interleaved order, so the first N of them are a fair sample of all;
``--cases N`` runs the next N not yet finished, ``--parallel K`` K at a time (the cores
shared among them: one thread each on 2 cores at K = 2, both at K = 1); ``--rerun A,B``
runs the named cases again (their earlier run directories move to ``WORK/old``);
``--recalibrate A,B`` reruns only their recalibrations, from a fresh FE store, keeping the
base calibration and diagnosis with their wall times (for a change that touches only the
recalibration; the record says which stages it reused and from which commit). Each
case's record is written as it ends to ``WORK/records/NAME.json`` (a rerun
skips it, and a case stopped part way keeps the stages it finished); the bars over every
finished case (:func:`cases_table.bars`) go to ``--out``.
The cases already in ``--out`` count as finished too and are kept there, so the benchmark
spans machines whose WORK does not persist: commit the results file and the next run goes on
from it (``--fresh``: start over). Each case records the commit it ran (``git rev-parse`` of
this checkout, or ``$BENCH_COMMIT`` for a snapshot without .git) and the machine's load.

``--noise-seeds NAME:S,S`` runs one case again on data that differ only in the noise seed
(in ``WORK/seeds``; bars, rows and figure of every such run, with the case's own row, to
``*_seeds.json`` and ``.png`` beside ``--out``): whether a truth outside its interval is the
case's draw of noise or a bias of its form.

Usage: python benchmarks/forms_benchmark.py WORK [--cases N] [--parallel 2] [--full]
       [--rerun NAME,NAME] [--recalibrate NAME,NAME] [--noise-seeds NAME:S,S]
       [--out benchmarks/results/forms_benchmark.json] [--list]
       [--summary] [--table]
(the figure: the ``--out`` path with ``.png``)
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

#: Anand sets in turn (see make_hidden_data.ANAND_SETS)
SETS = ("truth", "interior", "near_faces")
#: the forms sized by the RMS change they make, and their sizes (um)
SIZED = ("modulus_linear", "lag_second_order", "lag_third_order", "cte_quadratic", "kinematic_af")
SIZES = (0.2, 0.4, 1.2)
#: forms at their own fixed values
FIXED = ("stress_free_slow", "stress_free_moderate")
#: two hidden effects: ((form, size), (form, size)) at a set
PAIRS = (
    (("modulus_linear", 0.4), ("lag_second_order", 1.2), "truth"),
    (("stress_free_moderate", None), ("lag_second_order", 0.4), "interior"),
    (("cte_quadratic", 0.4), ("modulus_linear", 1.2), "near_faces"),
    (("lag_third_order", 0.4), ("modulus_linear", 0.2), "truth"),
)
CLEAN = 10


@dataclass(frozen=True)
class Case:
    """One dataset: its hidden forms with sizes (None: the form's fixed values), its Anand
    set and noise seed."""

    name: str
    forms: tuple[tuple[str, float | None], ...]
    anand: str
    seed: int


def plan(full: bool = False) -> list[Case]:
    """Every case, interleaved: round k takes the k-th case of each group in turn.

    Args:
        full: every size at every set for the sized forms (default: one Latin square).
    """
    groups: list[list[Case]] = []
    for f in SIZED:
        # Latin squares: every three cases hold each size and each set once
        groups.append([Case(f"{f}_{SIZES[(j + r) % 3]:g}_{a}", ((f, SIZES[(j + r) % 3]),),
                            a, 0) for r in range(3 if full else 1)
                       for j, a in enumerate(SETS)])
    groups.append([Case(f"{f}_{a}", ((f, None),), a, 0) for a in SETS for f in FIXED])
    groups.append([Case("+".join(f"{f}_{'fixed' if s is None else f'{s:g}'}" for f, s in fs)
                        + f"_{a}", fs, a, 0) for *fs, a in PAIRS])  # type: ignore[misc]
    groups.append([Case(f"clean_{SETS[i % 3]}_s{i}", (), SETS[i % 3], i)
                   for i in range(CLEAN)])
    out: list[Case] = []
    for k in range(max(len(g) for g in groups)):
        out += [g[k] for g in groups if k < len(g)]
    # one noise seed per dataset
    return [Case(c.name, c.forms, c.anand, c.seed if not c.forms else 100 + i)
            for i, c in enumerate(out)]


def make_data(case: Case, path: Path) -> float:
    """The case's CSV by the finer FE (kept when there); returns the seconds it took."""
    if path.exists():
        return 0.0
    import numpy as np
    from forms import form
    from make_hidden_data import ANAND_SETS, FINE

    from solderpyro.config.compose import build, compose
    from solderpyro.diagnose.hidden import HiddenTruth, hidden_values, make_dataset
    from solderpyro.fem.loading import SEED_TIMES

    t0 = time.perf_counter()
    setup = build(compose(FINE))
    truth = ANAND_SETS[case.anand]
    effs, vals = [], []
    for name, size in case.forms:
        eff, _, fixed = form(name)
        effs.append(eff)
        vals.append(np.asarray(fixed, float) if size is None else
                    hidden_values(setup, eff, target_rms=size, anand=truth)[0])
    tmp = path.with_suffix(".tmp.csv")
    make_dataset(setup, tuple(effs) or None, tmp, True, SEED_TIMES, noise=0.05,
                 seed=case.seed, truth=HiddenTruth(
                     np.concatenate(vals) if vals else None, truth))
    tmp.replace(path)
    return round(time.perf_counter() - t0, 1)


def run(case: Case, work: str, reused: dict | None = None) -> dict:
    """Make the data and run the loop of one case; its record (also written to
    ``WORK/records/NAME.json``). ``reused``: the earlier record of a case whose base
    calibration and diagnosis are kept (``--recalibrate``): their wall times and commit go
    into this record."""
    from diagnosis_cases import run_case

    w = Path(work)
    data = w / "data" / f"{case.name}.csv"
    data.parent.mkdir(parents=True, exist_ok=True)
    made = make_data(case, data)
    t0 = time.perf_counter()
    try:
        rec = run_case(case.name, {case.name: str(data)}, {}, str(w / "cases"),
                       str(w / "cases" / case.name / "store"), recalibrate=True,
                       keep_diagnosis=True)
    except Exception as e:  # noqa: BLE001 - the benchmark records a failed case and goes on
        rec = {"case": case.name, "error": f"{type(e).__name__}: {e}"}
    if reused is not None and "wall_s" in rec:
        kept = {k: v for k, v in (reused.get("wall_s") or {}).items()
                if k in ("calibrate", "diagnose")}
        rec["wall_s"] = {**kept, **rec["wall_s"]}
        # a record that itself reused its stages passes on where they ran
        rec["reused"] = {"stages": sorted(kept), "commit": (reused.get("reused") or {}).get(
            "commit", reused.get("commit"))}
    rec.update({"anand_set": case.anand, "forms": case.forms, "seed": case.seed,
                "data_s": made, "case_s": round(time.perf_counter() - t0, 1),
                "commit": commit(), "load_1min": round(os.getloadavg()[0], 2),
                "threads": int(os.environ.get("OMP_NUM_THREADS", "0")) or None})
    out = w / "records" / f"{case.name}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(rec, indent=1) + "\n")
    return rec


def commit() -> str | None:
    """The commit the benchmark runs: ``$BENCH_COMMIT``, else ``git rev-parse`` of this
    checkout (None outside one)."""
    if os.environ.get("BENCH_COMMIT"):
        return os.environ["BENCH_COMMIT"]
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=Path(__file__).parent,
                              capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def earlier(out: Path) -> list[dict]:
    """The case rows of an earlier results file at ``out`` (none when there is none)."""
    return json.loads(out.read_text()).get("cases", []) if out.exists() else []


def summarize(work: Path, out: Path, keep: list[dict],
              command: str = "python benchmarks/forms_benchmark.py WORK") -> dict:
    """The bars over every finished case, with each case's row, to ``out``: the cases in
    WORK (from their run directories, as cases_table reads them) and the rows ``keep`` of
    cases WORK does not hold (an earlier results file's); ``command`` is recorded as what
    made them."""
    from cases_table import bars, case_record

    recs = sorted((json.loads(p.read_text()) for p in (work / "records").glob("*.json")),
                  key=lambda r: r["case"]) if (work / "records").exists() else []
    rows = [{**case_record(work / "cases" / r["case"], work / "data" / f"{r['case']}.csv"),
             **{k: r.get(k) for k in ("forms", "anand_set", "seed", "commit", "reused",
                                      "load_1min", "threads")}}
            for r in recs if "error" not in r]
    here = {r["case"] for r in rows}
    rows = sorted(rows + [r for r in keep if r["case"] not in here], key=lambda r: r["case"])
    res = {"command": command, "bars": bars(rows), "cases": rows,
           "errors": [r for r in recs if "error" in r]}
    out.write_text(json.dumps(res, indent=1) + "\n")
    return res


def figure(res: dict, path: Path) -> None:
    """``path`` (png): per case, the loop's wall seconds by stage against the 5-minute bar
    (left), and per parameter whether the reported 95 % interval of the run a user ends with
    holds the truth (right; the row's label says what the diagnosis selected and the error
    after, in noise sd)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from cases_table import final_runs, loop_seconds

    rows = res["cases"]
    params = sorted({k for r in rows for f in final_runs(r) for k in f.get("truths", [])},
                    key=lambda k: (("s0", "QR", "xi", "m", k).index(k), k))
    h = 0.32 * len(rows) + 1.6
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(16, h), width_ratios=(1, 1.3),
                                  sharey=True)
    labels = []
    colours = {"calibrate": "#8da0cb", "diagnose": "#fc8d62", "recalibrate": "#66c2a5"}
    shown: set[str] = set()
    for i, r in enumerate(rows):
        finals = final_runs(r)
        left = 0.0
        for name, v in loop_seconds(r):
            ax.barh(i, v or 0.0, left=left, color=colours[name],
                    label=None if name in shown else name)
            shown.add(name)
            left += v or 0.0
        for j, f in enumerate(finals):  # several runs a user ends with: one above another
            y = i + 0.3 * (j - 0.5 * (len(finals) - 1))
            for k in f.get("truths", []):
                ax2.scatter(params.index(k), y, marker="o" if k not in f["missed"] else "x",
                            color="#1a9850" if k not in f["missed"] else "#d73027",
                            s=40 if len(finals) == 1 else 22)
        cro = r.get("cannot_rule_out") or []
        sel = ("+".join(r.get("selected") or []) or ("tie" if r.get("tie") else "none")) + (
            f"; caveat: {cro[0]}" + (f" +{len(cro) - 1}" if len(cro) > 1 else "")
            if cro and not r.get("tie") else "")
        rms = [f["compare_rms_um"][1] / r["sigma_um"] for f in finals
               if f.get("compare_rms_um") and r.get("sigma_um")]
        labels.append(f"{r['case']}  [{sel}{f', {rms[0]:.2f} sd' if rms else ''}]")
    ax.axvline(300.0, color="k", ls="--", lw=1, label="5 min")
    ax.set_yticks(range(len(rows)), labels, fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel("loop wall time, s (on 2 cores: one or two threads per case, see the table)")
    ax.legend(fontsize=7, loc="upper right")
    ax2.set_xticks(range(len(params)), params, rotation=60, fontsize=7)
    ax2.set_xlim(-0.5, len(params) - 0.5)
    b = res["bars"]
    ax2.set_title(f"truth inside the reported 95 % interval (o) or not (x): "
                  f"{b['coverage'][0]} of {b['coverage'][1]}\n(several runs a user ends "
                  f"with: one row each; Anand constants "
                  f"{b['coverage_constants'][0]} of {b['coverage_constants'][1]})", fontsize=9)
    clean = (f"clean flagged {b['false_alarms'][0]} of {b['false_alarms'][1]}; "
             if b["false_alarms"][1] else "")
    ax.set_title(f"selected {b['selected'][0]} of {b['selected'][1]} (of the others, the "
                 f"caveat names it: {b['caveat'][0]} of {b['caveat'][1]});\n{clean}loop "
                 f"median {b['loop_s_median']} s", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight")  # the longest case labels whole
    plt.close(fig)


def table(res: dict) -> str:
    """BENCHMARKS.md's per-case table of a results file's rows ``res["cases"]`` (markdown):
    what was selected (or the caveat), the error after, the truths outside the reported
    intervals, the loop's seconds by stage, and where and how the case ran."""
    from cases_table import final_runs, loop_seconds

    out = ["| case | selected (or the caveat) | RMS after (noise sd) | truths outside the 95 % "
           "intervals | loop s: calibrate + diagnose + recalibrate | commit (stages reused from), "
           "threads, load |",
           "|---|---|---|---|---|---|"]
    for r in res["cases"]:
        fin = final_runs(r)
        sel = "+".join(r.get("selected") or []) or (
            "tie " + "/".join(r["tie"][0]) if r.get("tie") else "none")
        if r.get("cannot_rule_out") and not r.get("tie"):
            sel += " (cannot rule out " + ", ".join(r["cannot_rule_out"]) + ")"
        rms = [f"{f['compare_rms_um'][1] / r['sigma_um']:.2f}" for f in fin
               if f.get("compare_rms_um")]
        miss = [m for f in fin for m in f.get("missed", [])]
        tot = sum(len(f.get("truths") or []) for f in fin)
        parts = loop_seconds(r)
        ls = " + ".join(str(round(v)) if v is not None else "-" for _, v in parts)
        ru = r.get("reused") or {}
        at = (r.get("commit") or "-")[:7] + (
            f" ({' and '.join(ru['stages'])} {(ru.get('commit') or '-')[:7]})" if ru else "")
        out.append(f"| {r['case']} | {sel} | {', '.join(rms) or '-'} | "
                   f"{', '.join(miss) or 'none'} (of {tot}) | {ls} = "
                   f"{round(sum(v or 0 for _, v in parts))} | {at}, "
                   f"{r.get('threads') or 1}, {r.get('load_1min')} |")
    return "\n".join(out)


def set_aside(paths: list[Path], old: Path) -> None:
    """Move those of ``paths`` that exist into the folder ``old`` (made when one does)."""
    for src in paths:
        if src.exists():
            old.mkdir(parents=True, exist_ok=True)
            src.rename(old / src.name)


def run_all(todo: list[Case], work: Path, parallel: int, reused: dict | None = None) -> None:
    """Run the cases ``todo`` in WORK, ``parallel`` at once (the cores shared among them),
    printing a line per case as it ends."""
    # the cores shared among the cases at once (torch and the FE's thread pool read it)
    os.environ["OMP_NUM_THREADS"] = str(max(1, (os.cpu_count() or 1) // max(parallel, 1)))
    with cf.ProcessPoolExecutor(parallel) as ex:
        futs = {ex.submit(run, c, str(work), (reused or {}).get(c.name)): c for c in todo}
        for f in cf.as_completed(futs):
            r = f.result()
            print(json.dumps({k: r.get(k) for k in ("case", "hidden", "selected", "explained",
                                                     "error", "case_s")}), flush=True)


def noise_seeds(spec: str, cases: list[Case], work: Path, out: Path, parallel: int) -> dict:
    """``--noise-seeds NAME:S,S``: case NAME on data that differ from its own only in the noise
    seed (datasets ``NAME_seedS``, run in ``WORK/seeds`` as the benchmark runs a case; those
    already there are kept), then the bars, table rows and figure of every seed run there,
    with NAME's own row from the results file ``out``, to ``*_seeds.json`` and ``.png``
    beside ``out``. Returns those results."""
    name, _, seeds = spec.partition(":")
    base = next((c for c in cases if c.name == name), None)
    if base is None:
        raise SystemExit(f"--noise-seeds: no case named {name!r} (--list lists them)")
    try:
        values = [int(v) for v in seeds.split(",") if v]
    except ValueError:
        raise SystemExit(f"--noise-seeds: seeds must be integers, got {seeds!r}") from None
    if not values or base.seed in values:
        raise SystemExit(f"--noise-seeds: give seeds other than the case's own ({base.seed}), "
                         f"e.g. {name}:{base.seed + 1000},{base.seed + 1001}")
    where = work / "seeds"
    done = {p.stem for p in (where / "records").glob("*.json")}
    todo = [Case(f"{name}_seed{v}", base.forms, base.anand, v) for v in values]
    run_all([c for c in todo if c.name not in done], where, parallel)
    own = [r for r in earlier(out) if r["case"] == name]
    stem = out.with_name(out.stem + "_seeds")
    res = summarize(where, stem.with_suffix(".json"), own,
                    f"python benchmarks/forms_benchmark.py WORK --noise-seeds {spec}")
    figure(res, stem.with_suffix(".png"))
    print(json.dumps(res["bars"]))
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("work")
    ap.add_argument("--cases", type=int, default=None, help="run the next N pending cases")
    ap.add_argument("--parallel", type=int, default=2)
    ap.add_argument("--out", default="benchmarks/results/forms_benchmark.json")
    ap.add_argument("--full", action="store_true", help="all nine size x set cases per form")
    ap.add_argument("--fresh", action="store_true",
                    help="ignore the cases already in --out (start the benchmark over)")
    ap.add_argument("--rerun", default="", metavar="NAME,NAME",
                    help="run these cases again (their run directories move to WORK/old)")
    ap.add_argument("--recalibrate", default="", metavar="NAME,NAME",
                    help="run these cases' recalibrations again from a fresh FE store, keeping "
                    "their base calibration and diagnosis (and those stages' wall times and "
                    "commit, recorded under 'reused'): for a change that touches only the "
                    "recalibration (the earlier runs and store move to WORK/old)")
    ap.add_argument("--noise-seeds", default="", metavar="NAME:S,S",
                    help="run case NAME again on data that differ from its own only in the "
                    "noise seed, one dataset NAME_seedS per seed S (in WORK/seeds, results "
                    "beside --out as *_seeds.json and .png, with NAME's own row from --out): "
                    "whether a truth outside its interval is the case's noise or its form")
    ap.add_argument("--list", action="store_true")
    ap.add_argument("--summary", action="store_true",
                    help="only the bars and the figure of the finished cases")
    ap.add_argument("--table", action="store_true",
                    help="print BENCHMARKS.md's per-case table of --out and stop")
    a = ap.parse_args()
    if a.table:
        print(table(json.loads(Path(a.out).read_text())))
        return
    work = Path(a.work).resolve()
    cases = plan(a.full)
    if a.noise_seeds:
        noise_seeds(a.noise_seeds, cases, work, Path(a.out), a.parallel)
        return
    keep = [] if a.fresh else earlier(Path(a.out))
    again = [nm for nm in a.rerun.split(",") if nm]
    unknown = sorted(set(again) - {c.name for c in cases})
    if unknown:
        raise SystemExit(f"--rerun: no case named {', '.join(unknown)} (--list lists them)")
    for nm in again:  # nothing is deleted: the earlier run moves aside
        set_aside([work / "cases" / nm, work / "records" / f"{nm}.json"],
                  work / "old" / time.strftime("%Y%m%d-%H%M%S"))
    recal = [nm for nm in a.recalibrate.split(",") if nm]
    unknown = sorted(set(recal) - {c.name for c in cases})
    if unknown:
        raise SystemExit(f"--recalibrate: no case named {', '.join(unknown)} (--list lists them)")
    reused = {}
    for nm in recal:  # the base and its diagnosis stay; the rest moves aside
        rp = work / "records" / f"{nm}.json"
        before = (json.loads(rp.read_text()) if rp.exists() else
                  next((r for r in keep if r["case"] == nm), None))
        cd = work / "cases" / nm
        if before is None or not (cd / "base" / "diagnosis.json").exists():
            raise SystemExit(f"--recalibrate: {nm} has no finished base and diagnosis in {work}")
        reused[nm] = before
        set_aside([*cd.glob("with*"), cd / "store", rp],
                  work / "old" / time.strftime("%Y%m%d-%H%M%S") / nm)
    again += recal
    keep = [r for r in keep if r["case"] not in again]
    done = {p.stem for p in (work / "records").glob("*.json")} | {r["case"] for r in keep}
    todo = [c for c in cases if c.name not in done]
    if a.list:
        for c in cases:
            print(("done  " if c.name in done else "      ") + c.name)
        print(f"{len(done)} of {len(cases)} done")
        return
    todo = [] if a.summary else todo[:a.cases] if a.cases is not None else todo
    run_all(todo, work, a.parallel, reused)
    if (work / "records").exists() or keep:
        res = summarize(work, Path(a.out), keep)
        figure(res, Path(a.out).with_suffix(".png"))
        print(json.dumps(res["bars"]))


if __name__ == "__main__":
    main()
