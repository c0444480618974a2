"""Sweeps: many independent jobs (calibrations of many datasets, benchmark cases) on the same
executor as the FE campaigns.

Why Dask and not Hydra's multirun launchers: the FE campaigns already run on a Dask cluster
(:mod:`solderpyro.compute.executor`), so one cluster, one address and one set of HPC settings
(``dask_jobqueue``) serve both; a sweep's results come back to one process that records each
job as it completes (crash-safe, and a rerun skips finished jobs), where a Hydra multirun
leaves one output directory per job to be gathered afterwards. Hydra still composes each
job's configuration (``key=value`` overrides are passed through).

Each job is one task. A job that calls the FE runs it in-process on its worker (one thread),
so a sweep never waits on the FE tasks of its own jobs.
"""

from __future__ import annotations

import json
import logging
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)


def _load(record: Path) -> dict[str, dict]:
    if not record.exists():
        return {}
    d = json.loads(record.read_text())
    if not isinstance(d, dict) or not isinstance(d.get("jobs"), dict):
        raise ValueError(f"{record}: not a sweep record (expected {{'jobs': {{...}}}})")
    return d["jobs"]


def _save(record: Path, jobs: dict[str, dict]) -> None:
    from solderpyro.compute.runstore import write_atomic

    write_atomic(record, {"jobs": jobs})


def _outcomes(fn: Callable[[str], dict], names: list[str], executor: Any
              ) -> Iterator[tuple[str, dict]]:
    """``(name, result)`` as each job finishes: in order in-process, as completed on Dask."""
    from solderpyro.compute.executor import DaskExecutor

    if not isinstance(executor, DaskExecutor):
        for n in names:
            yield n, _guarded(fn, n)
        return
    from distributed import as_completed

    tag = uuid.uuid4().hex[:8]
    futs = {executor.client.submit(_guarded, fn, n, pure=False, key=f"sweep-{n}-{tag}"): n
            for n in names}
    for fut in as_completed(list(futs)):
        try:
            res = fut.result()
        except Exception as e:  # the worker died on every attempt (KilledWorker) or similar
            res = {"ok": False, "error": f"{type(e).__name__}: {e}"}
        yield futs[fut], res


def _guarded(fn: Callable[[str], dict], name: str) -> dict:
    """``fn(name)`` with its wall time; an exception becomes ``{"ok": False, "error": ...}``
    so one bad job does not stop the sweep."""
    t0 = time.perf_counter()
    try:
        out = dict(fn(name))
        out.setdefault("ok", True)
    except Exception as e:  # noqa: BLE001 -- recorded, and the sweep goes on
        out = {"ok": False, "error": f"{type(e).__name__}: {e}"}
    out["wall_s"] = round(time.perf_counter() - t0, 2)
    return out


def sweep(names: Sequence[str], fn: Callable[[str], dict], record: str | Path,
          executor: Any = None, rerun_failed: bool = False) -> dict[str, dict]:
    """Run ``fn(name) -> dict`` (JSON-able) for every job ``name`` not yet in ``record``.

    Args:
        names: job names (distinct); each one's result goes into ``record`` under its name.
        fn: the job; on Dask it travels to the workers (a module-level function, or one
            defined in a script, which cloudpickle sends by value).
        record: JSON file of finished jobs, rewritten atomically as each job completes; a
            rerun skips the jobs it holds (and those that failed, unless ``rerun_failed``).
        executor: :class:`~solderpyro.compute.executor.DaskExecutor` to run jobs as parallel tasks;
            None: :func:`~solderpyro.compute.executor.current_executor` (in-process: one after
        another). rerun_failed: run again the jobs recorded with ``ok: False``.

    Returns:
        ``{name: result}`` for every job (recorded ones included), each result with ``ok``
        and ``wall_s`` (s), and ``error`` when the job raised.
    """
    from tqdm.auto import tqdm

    from solderpyro.compute.executor import current_executor

    if len(set(names)) != len(names):
        raise ValueError(f"sweep job names must be distinct, got {list(names)}")
    record = Path(record)
    jobs = _load(record)
    todo = [n for n in names if n not in jobs or (rerun_failed and not jobs[n].get("ok"))]
    ex = executor if executor is not None else current_executor()
    log.info("sweep: %d jobs, %d recorded in %s, %d to run (%s)", len(names),
             len(names) - len(todo), record, len(todo), ex.describe())
    with tqdm(total=len(todo), desc="sweep", unit="job",
              disable=not todo or not sys.stderr.isatty()) as bar:
        for name, res in _outcomes(fn, todo, ex):
            jobs[name] = res
            _save(record, jobs)
            bar.update(1)
            log.info("sweep job %s: %s in %.0f s", name,
                     "ok" if res.get("ok") else f"FAILED ({res.get('error', '')})",
                     res.get("wall_s", float("nan")))
    return {n: jobs[n] for n in names}


def calibrate_job(data: str, out: str, store: str, args: Sequence[str] = ()) -> dict:
    """One sweep job: ``solderpyro calibrate --data DATA --out OUT --store STORE --quiet ARGS``
    in a subprocess (its own logs go to ``OUT/log.txt``); returns the run's headline numbers
    (the FE check, the design's stop) from its record
    (:class:`~solderpyro.config.rundir.RunDir`)."""
    Path(out).mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "solderpyro.cli", "calibrate", "--data", data, "--out", out,
           "--store", store, "--quiet", *args]
    with open(Path(out) / "log.txt", "w") as logf:
        rc = subprocess.run(cmd, stdout=logf, stderr=subprocess.STDOUT).returncode
    if rc != 0:
        tail = (Path(out) / "log.txt").read_text().splitlines()[-3:]
        raise RuntimeError(f"calibrate exited {rc}: {' | '.join(tail)}")
    from solderpyro.config.rundir import RunDir

    info = RunDir.read(out).info
    chk = info.checks.fe_check
    return {"command": " ".join(cmd[2:]), "out": out,
            "design": {"reason": info.design.reason, "fe_runs": info.design.fe_runs},
            "fe_check_rms_sd": chk.get("rms_over_sigma"), "fe_check_ok": chk.get("ok")}
