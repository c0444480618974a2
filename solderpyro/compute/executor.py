"""Where FE batches run: in this process (the default) or on a Dask cluster.

Every FE campaign of the package (the calibration's start design and acquisition batches, the
FE check, the FE-exact step and the profiles, ``diagnose``'s Jacobians and refits, the
sensitivity DOE) reaches the solver through :func:`solderpyro.compute.store.run_doe`, and
``run_doe`` hands its batches to the *current executor*:

* :class:`InProcess` (default): one batch after another on this machine, each split over
  one-thread forked copies of this process, one per core (:func:`solve_split`; Linux); Dask
  is never imported on this path.
* :class:`DaskExecutor`: one Dask task per FE batch on a ``dask.distributed`` cluster
  (``--cluster local:N`` starts a ``LocalCluster`` of N single-threaded workers;
  ``--scheduler tcp://HOST:PORT`` joins a running one, e.g. a ``dask_jobqueue.SLURMCluster``).
  Each task solves its batch and writes its runs to the run store itself (the store is the
  meeting point: a shared filesystem on a real cluster), so nothing a worker finished is lost
  when the client dies; the client also stores, as each task completes (``as_completed``),
  whatever a worker could not write. A worker killed mid-task: the scheduler reruns the task
  elsewhere. A batch whose workers died ``distributed.scheduler.allowed-failures + 1`` times
  comes back as failed members with that reason and is *not* stored, so a rerun tries again.

Work that is not a run record (``predict``'s solves with the solder's fields recorded) goes
through :meth:`InProcess.map` / :meth:`DaskExecutor.map`: a function of a batch's rows,
split over this machine's cores or one Dask task per batch; the caller keeps what comes back.

Choose the executor for a block of code with :func:`use_executor` (a context variable, so
threads and nested calls see the right one)::

    from solderpyro.compute.executor import DaskExecutor, use_executor
    with DaskExecutor.start("local:2") as ex, use_executor(ex):
        calibrate_specimen(...)            # every FE batch goes to the two workers

Results do not depend on the executor: the FE solves each member independently (members of
one batch agree with the same members solved alone to ~1e-15 um), and ``run_doe`` assembles
rows in their input order.

Imports run one way: this module turns a solved batch into run records itself
(:func:`solve_batch`) and builds on the run store (:mod:`solderpyro.compute.runstore`: the records,
and the store a worker writes); :mod:`solderpyro.compute.store`'s ``run_doe`` builds on this module.
"""

from __future__ import annotations

import contextlib
import contextvars
import hashlib
import logging
import math
import os
import re
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from solderpyro.compute.runstore import RunRecord, RunStore

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BatchOutcome:
    """What one FE batch gave back.

    Attributes:
        records: one :class:`~solderpyro.compute.runstore.RunRecord` per member, in row order.
        stored: whether the records are already in the store (written where they were solved).
        seconds: FE wall time of the batch where it ran, s (NaN when unknown).
        lost: the batch was never solved (its workers died): failed records that must not be
            stored, so that a rerun tries again.
    """

    records: list[RunRecord]
    stored: bool
    seconds: float = float("nan")
    lost: bool = False


def solve_batch(solver: Any, P: torch.Tensor, times: Sequence[float],
                names: Sequence[str]) -> list[RunRecord]:
    """Solve one batch ``P (b, 9 + n_eff)`` over ``times`` (s, sorted): one
    :class:`~solderpyro.compute.runstore.RunRecord` per member (``names``: the columns of ``P``).

    ``solver``: anything with ``.solve(P, times, progress=False)``, or a callable
    ``(P, times)``, returning a ``SolveResult``-like (``V (b, n_time, n_out)`` um, ``ok (b,)``,
    ``reasons``, ``times``, ``names``, optional ``n_steps``/``n_substeps``).
    """
    tt = [float(t) for t in times]
    return _batch_records(_solve(solver, P, tt), P, tt, names)


def _solve(solver: Any, p: torch.Tensor, times: list[float]) -> Any:
    if hasattr(solver, "solve"):
        return solver.solve(p, times, progress=False)
    return solver(p, times)


def _batch_records(res: Any, p: torch.Tensor, times: list[float],
                   names: Sequence[str]) -> list[RunRecord]:
    """One :class:`RunRecord` per member of a solver result ``res`` for params ``p`` ``(b, k)``
    named ``names`` ``(k,)``."""
    V = res.V.detach().cpu().to(torch.float64).numpy()  # (b, n_time, n_out)
    rtimes = tuple(float(t) for t in torch.as_tensor(res.times).tolist())
    if V.shape[:2] != (p.shape[0], len(times)) or not np.allclose(rtimes, times, rtol=0,
                                                                  atol=1e-9):
        raise ValueError(f"solver returned V of shape {V.shape} at times {rtimes}, expected "
                         f"({p.shape[0]}, {len(times)}, n_out) at {tuple(times)}")
    ok = torch.as_tensor(res.ok).cpu().tolist()
    reasons = list(getattr(res, "reasons", None) or [""] * len(ok))
    n_steps, n_sub = getattr(res, "n_steps", None), getattr(res, "n_substeps", None)
    out = []
    for i, row in enumerate(p.tolist()):
        why = str(reasons[i]) or ("" if ok[i] else "solver reported failure (no reason given)")
        out.append(RunRecord(dict(zip(names, row, strict=True)), bool(ok[i]), why,
                             tuple(times), tuple(str(n) for n in res.names), V[i],
                             None if n_steps is None else int(n_steps),
                             None if n_sub is None else int(n_sub), int(p.shape[0])))
    return out


#: solvers built on this (worker) process, by the hash of their pickled inputs
_SOLVERS: dict[str, Any] = {}


def _worker_solver(key: str, blob: bytes) -> Any:
    """The solver pickled as ``blob`` (``key``: its sha256), built once per worker process."""
    if key not in _SOLVERS:
        import cloudpickle

        _SOLVERS.clear()  # one campaign's solver at a time: bounded memory
        _SOLVERS[key] = cloudpickle.loads(blob)
    return _SOLVERS[key]


def _task(key: str, blob: bytes, P: torch.Tensor, times: list[float], names: list[str],
          store_root: str | None, cfg_hash: str) -> tuple[list[RunRecord], bool, float]:
    """One Dask task: solve a batch and store its runs where the worker can reach the store.
    Returns ``(records, stored, seconds)``."""
    torch.set_num_threads(1)  # one thread per worker: the cluster, not torch, spreads the work
    solver = _worker_solver(key, blob)
    # The task runs beside the worker's event-loop thread; at Python's 5 ms switch interval the
    # solver's Python steps kept handing the GIL to it: a 64-run batch took 15.8 s in a worker
    # against 11.4-12.0 s in a plain process, 13.2 s with 100 ms (the loop still runs whenever
    # the solver is in native code, which releases the GIL).
    switch = sys.getswitchinterval()
    sys.setswitchinterval(0.1)
    t0 = time.perf_counter()
    try:
        recs = solve_batch(solver, P, times, names)
    finally:
        sys.setswitchinterval(switch)
    dt = time.perf_counter() - t0
    stored = False
    if store_root is not None:
        try:
            store = RunStore(store_root)
            for r in recs:
                store.put(cfg_hash, r)
            stored = True
        except OSError as e:  # no shared filesystem here: the client stores them
            log.warning("worker could not write the run store %s (%s); the client will",
                        store_root, e)
    return recs, stored, dt


def _map_task(blob: bytes, P: torch.Tensor) -> Any:
    """One Dask task of :meth:`DaskExecutor.map`: the pickled function on ``P``, one thread."""
    import cloudpickle

    torch.set_num_threads(1)
    return cloudpickle.loads(blob)(P)


def _on_cpu(t: torch.Tensor) -> bool:
    return t.device.type == "cpu"


#: the fewest members a forked part of a batch gets (:func:`solve_split`): even a 2-run batch
#: split in two ran 1.25-1.37x faster than whole on two threads, a 4-run one 1.4x, 16-32 runs
#: 1.6-1.8x (``benchmarks/bench_fe.py --split``, the project's 2-core machine)
MIN_PART = 1


def local_cores() -> int:
    """Cores this process may run on (its CPU affinity where the OS tells it)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - macOS, Windows
        return os.cpu_count() or 1


def _can_fork() -> bool:
    import multiprocessing as mp

    return sys.platform.startswith("linux") and "fork" in mp.get_all_start_methods()


def _child_run(conn: Any, fn: Any, P: torch.Tensor) -> None:
    """A forked part of :func:`split_rows`: ``fn(P)`` on one thread, its result (or
    ``("error", message)``) sent back."""
    torch.set_num_threads(1)
    try:
        msg: Any = ("ok", fn(P))
    except BaseException as e:  # noqa: BLE001 - reported to the parent, which runs it
        msg = ("error", f"{type(e).__name__}: {e}")
    try:
        conn.send(msg)
    finally:
        conn.close()


def split_rows(fn: Any, P: torch.Tensor, processes: int, on_cpu: bool = True,
               what: str = "an FE batch") -> list[Any]:
    """``fn`` on the rows of ``P`` ``(b, k)`` split over ``processes`` processes of one thread
    each: this one and forked copies of it (Linux), at least :data:`MIN_PART` rows apiece.

    Returns ``[fn(P[part]) for part in parts]``, the parts in row order (contiguous). Runs
    ``fn(P)`` whole where a split is not possible or not worth it (fewer rows than two parts,
    ``on_cpu`` False: CUDA does not survive fork; no fork; a daemonic process). Nothing is lost
    when a forked part fails (it died, or raised): this process runs that part itself, and
    says so (``what`` names the work in the warning).
    """
    parts = min(int(processes), len(P) // MIN_PART)
    import multiprocessing as mp

    # a daemonic process (a Dask worker, a pool's) may not have children, and shares the cores
    # with its siblings already
    if parts < 2 or not on_cpu or not _can_fork() or mp.current_process().daemon:
        return [fn(P)]

    ctx = mp.get_context("fork")
    idx = list(torch.arange(len(P)).tensor_split(parts))
    kids = []
    for rows in idx[1:]:
        r, w = ctx.Pipe(duplex=False)
        proc = ctx.Process(target=_child_run, args=(w, fn, P[rows]), daemon=True)
        proc.start()
        w.close()
        kids.append((proc, r, rows))
    prev = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        out = [fn(P[idx[0]])]
    except BaseException:
        for proc, r, _ in kids:  # none is waited for: stop them (a full pipe would block one)
            proc.kill()
            proc.join()
            r.close()
        raise
    finally:
        torch.set_num_threads(prev)
    for proc, r, rows in kids:
        try:
            msg: Any = r.recv()
        except (EOFError, OSError) as e:
            msg = ("error", f"no result ({type(e).__name__}; exit code {proc.exitcode})")
        finally:
            r.close()
        proc.join()
        if msg[0] == "error":
            log.warning("a forked part of %s (%d rows) failed (%s); run here", what, len(rows),
                        msg[1])
            out.append(fn(P[rows]))
        else:
            out.append(msg[1])
    return out


def solve_split(solver: Any, P: torch.Tensor, times: Sequence[float], names: Sequence[str],
                processes: int) -> list[RunRecord]:
    """Solve one batch ``P (b, 9 + n_eff)`` split over ``processes`` processes of one thread
    each (:func:`split_rows`); records in row order, as :func:`solve_batch` gives them.

    Why: the FE's batched solve gains little from a second thread (10.4 against 9.1 runs/s at
    b = 64 on this 2-core machine, BENCHMARKS.md), so the in-process default left a core
    idle; split in two, batches of 2-64 runs ran 1.25-1.8x faster (``benchmarks/bench_fe.py
    --split``). A member's result does not depend on its batch (~1e-15 um).
    A CUDA solve is never forked (it fills its device anyway).
    """
    tkw = getattr(solver, "tkw", None)
    on_cpu = not isinstance(tkw, dict) or torch.device(tkw.get("device", "cpu")).type == "cpu"

    def part(p: torch.Tensor) -> list[RunRecord]:
        return solve_batch(solver, p, times, names)

    return [r for recs in split_rows(part, P, processes, on_cpu) for r in recs]


class InProcess:
    """Run FE batches one after another on this machine (the default executor).

    ``n_workers`` is 1 (one batch at a time); batches are the rows in order, ``batch_size``
    at a time; each batch is split over ``processes`` one-thread processes
    (:func:`solve_split`; default: every core this process may use).

    Args:
        processes: processes per batch (1: the whole batch in this process, on torch's
            threads); None: :func:`local_cores`.
    """

    n_workers = 1

    def __init__(self, processes: int | None = None) -> None:
        if processes is not None and (not isinstance(processes, int) or processes < 1):
            raise ValueError(f"InProcess processes must be a positive integer, got "
                             f"{processes!r}")
        self.processes = processes

    def partition(self, n: int, batch_size: int) -> list[list[int]]:
        """Split ``n`` rows into batches of ``batch_size`` (the last one shorter)."""
        return [list(range(j, min(n, j + batch_size))) for j in range(0, n, batch_size)]

    def run(self, solver: Any, batches: Sequence[torch.Tensor], times: Sequence[float],
            names: Sequence[str], store: RunStore, cfg_hash: str) -> Iterator[BatchOutcome]:
        """Solve each batch ``(b_i, 9 + n_eff)`` in turn and yield its outcome (not yet
        stored: :func:`~solderpyro.compute.store.run_doe` stores it)."""
        procs = self.processes or local_cores()
        for P in batches:
            t0 = time.perf_counter()
            recs = solve_split(solver, P, times, names, procs)
            yield BatchOutcome(recs, False, time.perf_counter() - t0)

    def map(self, fn: Any, batches: Sequence[torch.Tensor], what: str = "a batch"
            ) -> Iterator[tuple[int, list[Any]]]:
        """``fn`` on each batch ``(b_i, k)`` in turn, split over ``processes`` one-thread
        processes (:func:`split_rows`): yields ``(i, [fn(part) for part in its parts])`` as
        each batch ends (any work a caller hands out in batches, e.g. ``predict``'s recorded
        solves; ``what`` names it in warnings)."""
        procs = self.processes or local_cores()
        for i, P in enumerate(batches):
            yield i, split_rows(fn, P, procs, _on_cpu(P), what)

    def describe(self) -> str:
        """A short label of where the batches run (for progress bars and logs)."""
        return "in-process"


_LOCAL = re.compile(r"^local(?::(\d+))?$")


#: Dask settings of the workers a ``--cluster local:N`` starts, measured on the FE (a 64-run batch
#: on one thread; BENCHMARKS.md, "Scaling out on Dask"): glibc's memory trimming at 64 kB, which
#: Dask sets for its workers, made the solver's many medium-sized tensor allocations 12 % slower,
#: and the statistical profiler (a thread sampling the stack every 10 ms) took a few per cent more.
#: A cluster started elsewhere (``--scheduler``) keeps its own settings: docs/scaling.md says which
#: to use.
WORKER_CONFIG = {"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": 1 << 30,
                 "distributed.worker.profile.enabled": False}


def parse_cluster(spec: str) -> int:
    """Workers of a ``--cluster`` spec: ``local:N`` (N >= 1) or ``local`` (one per core)."""
    m = _LOCAL.match(spec.strip())
    if m is None:
        raise ValueError(f"--cluster must be 'local' or 'local:N' (N workers), got {spec!r}; "
                         f"to join a running cluster use --scheduler tcp://HOST:PORT")
    n = int(m.group(1)) if m.group(1) else (os.cpu_count() or 1)
    if n < 1:
        raise ValueError(f"--cluster local:N needs N >= 1 workers, got {n}")
    return n


class DaskExecutor:
    """Run FE batches as Dask tasks, one task per batch (see the module docstring).

    Args:
        client: a connected ``distributed.Client``.
        owns: close the client (and its cluster) in :meth:`close`.
        retries: extra attempts of a task that *raised* (not of one whose worker died: the
            scheduler's ``allowed-failures`` governs those).

    Build one with :meth:`start`, which also checks the address.
    """

    def __init__(self, client: Any, owns: bool = False, retries: int = 0) -> None:
        self.client = client
        self.owns = owns
        self.retries = retries

    @classmethod
    def start(cls, cluster: str | None = None, scheduler: str | None = None,
              timeout: float = 10.0) -> DaskExecutor:
        """Start a ``LocalCluster`` (``cluster='local:N'``: N single-threaded worker
        processes) or join a running scheduler (``scheduler='tcp://HOST:PORT'``).

        Raises:
            ValueError: neither or both given, or a malformed spec.
            ConnectionError: no scheduler answered at ``scheduler`` within ``timeout`` s.
        """
        if (cluster is None) == (scheduler is None):
            raise ValueError("give exactly one of --cluster local:N and --scheduler ADDRESS")
        import dask
        from distributed import Client, LocalCluster  # loads distributed's config defaults

        for name in ("distributed", "bokeh", "tornado"):  # no third-party INFO chatter
            logging.getLogger(name).setLevel(logging.WARNING)
        if cluster is not None:
            n = parse_cluster(cluster)
            env = dict(os.environ)
            try:
                with dask.config.set(WORKER_CONFIG):
                    lc = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                      dashboard_address=":0", silence_logs=logging.ERROR)
            finally:  # the nanny leaves its workers' settings (OMP_NUM_THREADS=1,
                os.environ.clear()  # PYTHONHASHSEED, ...) in this process's environment,
                os.environ.update(env)  # where later subprocesses would inherit them
            log.info("Dask LocalCluster: %d single-threaded workers (%s)", n,
                     lc.scheduler_address)
            return cls(Client(lc), owns=True)
        addr = str(scheduler)
        if not re.match(r"^[a-z]+://[^\s/]+:\d+$", addr):
            raise ValueError(f"--scheduler must look like tcp://HOST:PORT, got {addr!r}")
        try:
            client = Client(addr, timeout=f"{timeout}s")
        except (OSError, TimeoutError) as e:
            raise ConnectionError(f"--scheduler {addr}: no Dask scheduler answered within "
                                  f"{timeout:g} s ({type(e).__name__}: {e})") from e
        n = len(client.scheduler_info().get("workers", {}))
        log.info("Dask scheduler %s: %d workers", addr, n)
        return cls(client, owns=False)

    @property
    def n_workers(self) -> int:
        """Total worker threads of the cluster (at least 1)."""
        info = self.client.scheduler_info().get("workers", {})
        return max(1, sum(int(w.get("nthreads", 1)) for w in info.values()))

    def partition(self, n: int, batch_size: int) -> list[list[int]]:
        """Split ``n`` rows into batches of at most ``batch_size`` whose sizes differ by at
        most one, their number a multiple of the cluster's worker threads (while rows last),
        so that every worker gets the same share."""
        if n == 0:
            return []
        w = self.n_workers
        k = min(n, w * math.ceil(math.ceil(n / batch_size) / w))
        edges = [round(i * n / k) for i in range(k + 1)]
        return [list(range(a, b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]

    @staticmethod
    def _solver_blob(solver: Any) -> tuple[str, bytes]:
        """``(sha256, pickled solver)``. Sent with every task (a SpecimenSolver pickles as
        its inputs, ~16 kB) rather than scattered: scattered data dies with the workers that
        hold it, a task's own arguments are resent when it is rescheduled. Each worker builds
        the solver once (:func:`_worker_solver`)."""
        import cloudpickle

        blob = cloudpickle.dumps(solver)
        return hashlib.sha256(blob).hexdigest(), blob

    def run(self, solver: Any, batches: Sequence[torch.Tensor], times: Sequence[float],
            names: Sequence[str], store: RunStore, cfg_hash: str) -> Iterator[BatchOutcome]:
        """Submit one task per batch ``(b_i, 9 + n_eff)`` and yield outcomes as tasks
        complete (not in batch order)."""
        from distributed import as_completed
        from distributed.scheduler import KilledWorker

        if not batches:
            return
        key, blob = self._solver_blob(solver)
        root = str(Path(store.root).resolve())
        tt, nm = [float(t) for t in times], [str(n) for n in names]
        futs = {self.client.submit(_task, key, blob, P, tt, nm, root, cfg_hash, pure=False,
                                   retries=self.retries): i for i, P in enumerate(batches)}
        try:
            for fut in as_completed(list(futs)):
                i = futs[fut]
                try:
                    recs, stored, dt = fut.result()
                except KilledWorker as e:
                    yield BatchOutcome(_failed(batches[i], tt, names, solver,
                                                  f"FE batch lost: its worker died on every "
                                                  f"attempt ({e}); not stored, a rerun "
                                                  f"retries it"), False, lost=True)
                    continue
                yield BatchOutcome(recs, stored, dt)
        finally:
            for f in futs:
                f.release()

    def map(self, fn: Any, batches: Sequence[torch.Tensor], what: str = "a batch"
            ) -> Iterator[tuple[int, list[Any]]]:
        """One task per batch ``(b_i, k)`` running ``fn`` (cloudpickled, one thread per
        worker): yields ``(i, [fn(batch)])`` as tasks complete (not in batch order).

        Raises:
            RuntimeError: naming the batch whose workers died on every attempt (``what``
                names the work); what completed before was yielded.
        """
        import cloudpickle
        from distributed import as_completed
        from distributed.scheduler import KilledWorker

        if not batches:
            return
        blob = cloudpickle.dumps(fn)
        futs = {self.client.submit(_map_task, blob, P, pure=False, retries=self.retries): i
                for i, P in enumerate(batches)}
        try:
            for fut in as_completed(list(futs)):
                i = futs[fut]
                try:
                    yield i, [fut.result()]
                except KilledWorker as e:
                    raise RuntimeError(f"{what} {i}: its worker died on every attempt ({e}); "
                                       "a rerun tries it again") from None
        finally:
            for f in futs:
                f.release()

    def describe(self) -> str:
        """A short label of where the batches run: the scheduler and its worker threads."""
        return f"Dask ({self.client.scheduler.address}, {self.n_workers} worker threads)"

    def close(self) -> None:
        """Close the client, and the cluster when this executor started it."""
        cluster = getattr(self.client, "cluster", None) if self.owns else None
        self.client.close()
        if cluster is not None:
            cluster.close()

    def __enter__(self) -> DaskExecutor:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def _failed(P: torch.Tensor, times: list[float], names: Sequence[str], solver: Any,
            reason: str) -> list[RunRecord]:
    """Failed records (``ok=False``, NaN outputs) for every member of a lost batch."""
    outs = list(getattr(solver, "names", None) or ())
    V = np.full((len(times), len(outs)), np.nan)
    return [RunRecord(dict(zip(names, row, strict=True)), False, reason, tuple(times),
                      tuple(str(n) for n in outs), V) for row in P.tolist()]


Executor = InProcess | DaskExecutor

_CURRENT: contextvars.ContextVar[Executor | None] = contextvars.ContextVar(
    "solderpyro_executor", default=None)
_DEFAULT = InProcess()


def current_executor() -> Executor:
    """The executor FE batches go to now (:class:`InProcess` unless :func:`use_executor`)."""
    return _CURRENT.get() or _DEFAULT


@contextlib.contextmanager
def use_executor(executor: Executor | None) -> Iterator[Executor]:
    """Send every FE batch of the enclosed block to ``executor`` (None: in-process)."""
    tok = _CURRENT.set(executor)
    try:
        yield current_executor()
    finally:
        _CURRENT.reset(tok)


@contextlib.contextmanager
def executor_from_options(cluster: str | None, scheduler: str | None,
                          timeout: float = 10.0) -> Iterator[Executor]:
    """The CLI's seam: in-process when both are None, else a :class:`DaskExecutor` started
    (and closed afterwards) from ``--cluster`` / ``--scheduler``, current for the block."""
    if cluster is None and scheduler is None:
        with use_executor(None) as ex:
            yield ex
        return
    with DaskExecutor.start(cluster, scheduler, timeout) as dex, use_executor(dex) as ex:
        yield ex
