"""Scale-out measurements: a 512-run DOE in-process vs on 1 and 2 Dask workers, and
reading a 10,000-run store back.

    python benchmarks/scaling.py doe   [--runs 512] [--batch 64] [--repeats 1]
    python benchmarks/scaling.py store [--runs 10000]

``doe``: an LHS design over the reference case's box (docs/configuration.md: the seed's four times,
points A and B, default mesh), solved through ``run_doe`` into a fresh store, under three
executors, each in its own process so that thread settings do not leak:

* ``inproc``: in this process with 2 torch threads (the default of a plain command);
* ``dask1`` / ``dask2``: ``--cluster local:1`` / ``local:2`` (single-threaded workers).

For the Dask runs two overheads are reported. ``overhead`` is ``1 - sum(FE seconds of the
tasks) / (workers x wall)``: everything that is not the FE (scheduling, pickling, building the
solver on each worker, store writes, the client and scheduler on the same two cores, a worker
idle at the end) as a share of the worker time. ``per_task_overhead`` is Dask's cost per task
against its FE time, from the task stream: the time a task occupies its worker beyond the FE
(solver lookup, records, store writes) plus the gaps between consecutive tasks on a worker
(scheduling, transfers). Cluster start-up is timed apart. The configurations run in turn,
``--repeats`` rounds; medians are reported.

``store``: writes ``--runs`` synthetic full-field records (4 times x 560 outputs, the size of a
calibration's field run) in the record format of the store, and times ``RunStore.records``
reading them all back; the same for 1/5 as many records in the old format (V as lists of
numbers), for scale.

Results: benchmarks/results/scaling.json (merged per subcommand).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

OUT = Path(__file__).parent / "results" / "scaling.json"

DOE_CHILD = """
import json, sys, time, torch
from pathlib import Path
from solderpyro.config.compose import build, compose
from solderpyro.design import lhs
from solderpyro.compute.executor import DaskExecutor, InProcess
from solderpyro.fem.solver import SpecimenSolver
from solderpyro.compute.runstore import RunStore
from solderpyro.compute.store import DoeOptions, run_doe

mode, n, batch, root = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
s = build(compose([]))
solver = SpecimenSolver(s.problem, None, dtype=s.dtype, device=s.device)
P = s.space.full(lhs(s.space, n, seed=7))
store = RunStore(root)
h = store.register(s.problem, s.times, False, s.dtype)
t0 = time.perf_counter()
if mode == "inproc":
    torch.set_num_threads(2)
    ex, start = InProcess(), 0.0
else:
    ex = DaskExecutor.start(f"local:{int(mode[4:])}")
    ex.client.wait_for_workers(int(mode[4:]))
    start = time.perf_counter() - t0
t1 = time.perf_counter()
extra = {}
if mode == "inproc":
    res = run_doe(solver, store, h, P, s.times, options=DoeOptions(batch, False, ex))
else:
    from distributed import get_task_stream
    with get_task_stream(ex.client) as ts:
        res = run_doe(solver, store, h, P, s.times, options=DoeOptions(batch, False, ex))
    spans = sorted((r["worker"], ss["start"], ss["stop"]) for r in ts.data
                   for ss in r["startstops"] if ss["action"] == "compute")
    busy = sum(b - a for _, a, b in spans)
    gaps = [a2 - b1 for (w1, _, b1), (w2, a2, _) in zip(spans, spans[1:]) if w1 == w2]
    # in a task beyond its FE (solver lookup, records, store writes), and between two tasks
    # on a worker (scheduling, transfers): the Dask overhead per task, against its FE time
    extra = {"tasks": len(spans), "task_s": busy,
             "in_task_overhead": busy / res.fe_s - 1,
             "gap_s_mean": sum(gaps) / len(gaps) if gaps else 0.0,
             "per_task_overhead": (busy + sum(gaps)) / res.fe_s - 1}
wall = time.perf_counter() - t1
workers = 1 if mode == "inproc" else int(mode[4:])
print(json.dumps({"mode": mode, "wall_s": wall, "start_s": start, "fe_s": res.fe_s,
                  "workers": workers, "n_ok": int(res.ok.sum()), "n": n,
                  "overhead": 1 - res.fe_s / (workers * wall), **extra}))
if mode != "inproc":
    ex.close()
"""


def bench_doe(a: argparse.Namespace) -> dict:
    rows: list[dict] = []
    modes = a.modes.split(",")
    for r in range(a.repeats):
        for mode in modes:
            with tempfile.TemporaryDirectory() as tmp:
                out = subprocess.run([sys.executable, "-c", DOE_CHILD, mode, str(a.runs),
                                      str(a.batch), tmp], capture_output=True, text=True,
                                     check=True)
            row = json.loads(out.stdout.strip().splitlines()[-1])
            row["round"] = r
            rows.append(row)
            print(json.dumps(row), flush=True)
    med = {m: statistics.median(x["wall_s"] for x in rows if x["mode"] == m) for m in modes}
    out = {"runs": a.runs, "batch": a.batch, "repeats": a.repeats, "rows": rows,
           "median_wall_s": med}
    for key in ("overhead", "per_task_overhead"):
        out[f"median_{key}"] = {m: statistics.median(x[key] for x in rows if x["mode"] == m)
                                for m in modes if m != "inproc"
                                and all(key in x for x in rows if x["mode"] == m)}
    if {"dask1", "dask2"} <= set(med):
        out["speedup_2_vs_1_worker"] = med["dask1"] / med["dask2"]
    if {"inproc", "dask2"} <= set(med):
        out["speedup_2_workers_vs_inproc_2_threads"] = med["inproc"] / med["dask2"]
    return out


def _records(root: Path, n: int, legacy: bool) -> float:
    """Write ``n`` synthetic field records under ``root``; returns write seconds."""
    import numpy as np

    from solderpyro.compute.runstore import RunRecord, RunStore, write_atomic
    from solderpyro.params import ANAND_NAMES

    store = RunStore(root)
    names = tuple(["A", "B"] + [f"g_{i:02d}_{j:02d}" for i in range(31) for j in range(18)])
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    for _ in range(n):
        rec = RunRecord(dict(zip(ANAND_NAMES, rng.uniform(1, 2, 9).tolist(), strict=True)),
                        True, "", (600.0, 2700.0, 4800.0, 7800.0), names,
                        rng.normal(size=(4, len(names))))
        d = rec.to_json()
        if legacy:  # the format before base64: V as nested lists of numbers
            d["V"] = rec.V.tolist()
        write_atomic(store.path("cfg", rec.values), d)
    return time.perf_counter() - t0


def bench_store(a: argparse.Namespace) -> dict:
    from solderpyro.compute.runstore import RunStore

    out = {}
    for label, n, legacy in (("base64", a.runs, False), ("lists", a.runs // 5, True)):
        with tempfile.TemporaryDirectory(dir=a.tmp) as tmp:
            w = _records(Path(tmp), n, legacy)
            t0 = time.perf_counter()
            recs = RunStore(tmp).records("cfg")
            r = time.perf_counter() - t0
            size = sum(p.stat().st_size for p in (Path(tmp) / "cfg" / "runs").glob("*.json"))
        assert len(recs) == n
        out[label] = {"runs": n, "write_s": round(w, 2), "read_s": round(r, 2),
                      "read_ms_per_run": round(1e3 * r / n, 3), "bytes_per_run": size // n}
        print(label, json.dumps(out[label]), flush=True)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="what", required=True)
    d = sub.add_parser("doe")
    d.add_argument("--runs", type=int, default=512)
    d.add_argument("--batch", type=int, default=64)
    d.add_argument("--repeats", type=int, default=1)
    d.add_argument("--modes", default="inproc,dask1,dask2",
                   help="which of inproc, dask1, dask2 to run, in this order each round")
    s = sub.add_parser("store")
    s.add_argument("--runs", type=int, default=10000)
    s.add_argument("--tmp", default=None, help="where to write the records (default: $TMPDIR)")
    a = p.parse_args()
    res = bench_doe(a) if a.what == "doe" else bench_store(a)
    done = json.loads(OUT.read_text()) if OUT.exists() else {}
    modes = getattr(a, "modes", "inproc,dask1,dask2")
    key = a.what if modes == "inproc,dask1,dask2" else f"{a.what}_{modes}"
    done[key] = {"command": " ".join(["python", *sys.argv]),
                    "cpus": __import__("os").cpu_count(), **res}
    OUT.write_text(json.dumps(done, indent=2) + "\n")
    print(json.dumps({k: v for k, v in res.items() if k != "rows"}, indent=2))


if __name__ == "__main__":
    main()
