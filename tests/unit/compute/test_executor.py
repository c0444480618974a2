"""The executor seam: FE batches on a Dask LocalCluster give the in-process numbers, survive a
worker killed mid-campaign, and give up on a batch that kills every worker it meets."""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import cloudpickle
import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # test_store beside this file
from test_store import cheap_problem  # noqa: E402

from solderpyro.compute.executor import (
    DaskExecutor,
    InProcess,
    current_executor,
    executor_from_options,
    parse_cluster,
    use_executor,
)
from solderpyro.compute.runstore import RunStore, param_hash
from solderpyro.compute.store import DoeOptions, run_doe
from solderpyro.fem.loading import SEED_TIMES
from solderpyro.fem.solver import SpecimenSolver
from solderpyro.params import ANAND_NAMES, ParameterSpace

# the stand-in solvers below travel to the workers by value (the workers cannot import tests)
cloudpickle.register_pickle_by_value(sys.modules[__name__])

# keep_environment: Dask's nanny writes its workers' settings into os.environ
pytestmark = [pytest.mark.timeout(300), pytest.mark.usefixtures("keep_environment")]


def _params(n: int) -> torch.Tensor:
    """``(n, 9)`` stiff parameter sets (few Newton iterations), all distinct."""
    th = [[16.0 + 0.5 * i, 11000.0 + 100 * i, 2.0 + 0.2 * i, 0.3 + 0.01 * i] for i in range(n)]
    return ParameterSpace.seed().full(torch.tensor(th, dtype=torch.float64))


@pytest.fixture(scope="module")
def cluster():
    """Two single-threaded local workers, as ``--cluster local:2`` starts them."""
    pytest.importorskip("distributed")
    with DaskExecutor.start("local:2") as ex:
        yield ex


def test_partitions_cover_every_row_once():
    assert InProcess().partition(10, 4) == [[0, 1, 2, 3], [4, 5, 6, 7], [8, 9]]
    assert InProcess().partition(0, 4) == []

    class TwoWorkers(DaskExecutor):  # the partition rule alone, no cluster
        n_workers = 2  # type: ignore[assignment]

    ex = TwoWorkers(client=None)
    for n, b in [(1, 64), (5, 64), (30, 64), (130, 64), (7, 2)]:
        parts = ex.partition(n, b)
        assert sorted(i for p in parts for i in p) == list(range(n))
        assert max(map(len, parts)) <= b and len(parts) >= min(n, 2)
        assert len(parts) % 2 == 0 or len(parts) == n  # the same share for both workers
        assert max(map(len, parts)) - min(map(len, parts)) <= 1  # equal batches


def test_bad_cluster_options_fail_fast_and_name_the_option():
    with pytest.raises(ValueError, match="--cluster"):
        parse_cluster("locale:2")
    with pytest.raises(ValueError, match="N >= 1"):
        parse_cluster("local:0")
    with pytest.raises(ValueError, match="--scheduler must look like"):
        DaskExecutor.start(scheduler="not-an-address")
    t0 = time.monotonic()
    with pytest.raises(ConnectionError, match="--scheduler tcp://127.0.0.1:9"):
        DaskExecutor.start(scheduler="tcp://127.0.0.1:9", timeout=2.0)  # nothing listens
    assert time.monotonic() - t0 < 30


def test_default_executor_is_in_process_without_dask_import(tmp_path):
    """The default path never imports Dask (checked in a fresh interpreter)."""
    import subprocess

    code = ("import sys, torch\n"
            "from solderpyro.compute.runstore import RunStore\n"
            "from solderpyro.compute.store import DoeOptions, run_doe\n"
            "from solderpyro.compute.executor import current_executor\n"
            "from types import SimpleNamespace\n"
            "def solver(p, t):\n"
            "    tt = torch.tensor(t, dtype=torch.float64)\n"
            "    return SimpleNamespace(times=tt, names=['A'], V=p[:, None, :1] * tt[None, :,"
            " None], ok=torch.ones(len(p), dtype=torch.bool), reasons=[''] * len(p))\n"
            f"r = run_doe(solver, RunStore({str(tmp_path)!r}), 'c', torch.rand(3, 9) + 1,"
            " [1.0, 2.0], options=DoeOptions(progress=False))\n"
            "assert r.n_computed == 3 and current_executor().describe() == 'in-process'\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in"
            " ('dask', 'distributed')))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=True)
    assert out.stdout.strip() == "[]"


def test_two_workers_give_the_in_process_numbers(tmp_path, cluster):
    problem = cheap_problem()
    solver = SpecimenSolver(problem, None, dtype=torch.float64)
    P = _params(6)
    ref_store, dask_store = RunStore(tmp_path / "ref"), RunStore(tmp_path / "dask")
    h = ref_store.register(problem, SEED_TIMES, False, torch.float64)
    assert dask_store.register(problem, SEED_TIMES, False, torch.float64) == h
    ref = run_doe(solver, ref_store, h, P, SEED_TIMES, options=DoeOptions(64, False))
    with use_executor(cluster):
        assert current_executor() is cluster
        got = run_doe(solver, dask_store, h, P, SEED_TIMES, options=DoeOptions(64, False))
    assert current_executor().describe() == "in-process"
    assert bool(ref.ok.all()) and torch.equal(got.ok, ref.ok)
    # the workers solve other batches of the same runs: rounding only (a member's iterations
    # do not depend on its batch; <= 2e-14 of max|V| measured over a 30-run design), bounded
    # by 1e-12 max|V|
    torch.testing.assert_close(got.V, ref.V, rtol=0, atol=1e-12 * ref.V.abs().max().item())
    files = sorted(p.name for p in (tmp_path / "dask" / h / "runs").glob("*.json"))
    assert files == sorted(f"{param_hash(r)}.json" for r in P)  # each run stored once
    again = run_doe(solver, dask_store, h, P, SEED_TIMES,
                    options=DoeOptions(progress=False, executor=cluster))
    assert (again.n_reused, again.n_computed) == (6, 0)


def test_worker_killed_mid_campaign_completes_with_every_run_stored_once(tmp_path, cluster):
    problem = cheap_problem()
    solver = SpecimenSolver(problem, None, dtype=torch.float64)
    P = _params(8)
    store = RunStore(tmp_path)
    h = store.register(problem, SEED_TIMES, False, torch.float64)
    runs = tmp_path / h / "runs"
    pids = list(cluster.client.run(os.getpid).values())
    killed: list[int] = []

    def killer() -> None:  # kill -9 one worker as soon as the first run is stored
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not (runs.is_dir() and any(runs.glob("*.json"))):
            time.sleep(0.01)
        os.kill(pids[0], signal.SIGKILL)
        killed.append(pids[0])

    th = threading.Thread(target=killer)
    th.start()
    res = run_doe(solver, store, h, P, SEED_TIMES, options=DoeOptions(1, False, cluster))
    th.join()
    assert killed, "no worker was killed"
    assert bool(res.ok.all()) and res.n_computed == 8
    files = sorted(p.name for p in runs.glob("*.json"))
    assert files == sorted(f"{param_hash(r)}.json" for r in P)
    ref = run_doe(solver, RunStore(tmp_path / "ref"), h, P, SEED_TIMES,
                  options=DoeOptions(progress=False, executor=InProcess()))
    torch.testing.assert_close(res.V, ref.V, rtol=0, atol=1e-12 * ref.V.abs().max().item())
    cluster.client.wait_for_workers(2, timeout=60)  # the nanny restarted the dead worker


class KillerSolver:
    """Kills the worker process that runs it, every time (a batch that crashes its host)."""

    names = ["A", "B"]

    def __call__(self, p, times):
        os.kill(os.getpid(), signal.SIGKILL)


class AffineSolver:
    """V = affine in the parameters at ``times``: ``(b, n_time, 2)``, all converged."""

    names = ["A", "B"]

    def __call__(self, p, times):
        t = torch.tensor(times, dtype=torch.float64)
        V = p[:, None, :2] * t[None, :, None] * 1e-6
        return SimpleNamespace(times=t, names=self.names, V=V,
                               ok=torch.ones(len(p), dtype=torch.bool), reasons=[""] * len(p))


def test_a_batch_that_kills_every_worker_is_failed_not_hung(tmp_path):
    pytest.importorskip("distributed")
    import dask

    store = RunStore(tmp_path)
    with dask.config.set({"distributed.scheduler.allowed-failures": 1}):
        with DaskExecutor.start("local:1") as ex:
            t0 = time.monotonic()
            res = run_doe(KillerSolver(), store, "cfg", _params(2), SEED_TIMES,
                          options=DoeOptions(progress=False, executor=ex))
            assert time.monotonic() - t0 < 120
            assert not bool(res.ok.any())
            assert all("worker died" in r and "not stored" in r for r in res.reasons)
            assert not (tmp_path / "cfg" / "runs").exists()  # a rerun will try again
            # and the cluster still works
            ok = run_doe(AffineSolver(), store, "cfg", _params(2), SEED_TIMES,
                         options=DoeOptions(progress=False, executor=ex))
            assert bool(ok.ok.all()) and ok.n_computed == 2


def test_starting_a_local_cluster_leaves_this_process_environment_alone():
    """Dask's nanny writes its workers' settings (OMP_NUM_THREADS=1, PYTHONHASHSEED, ...) into
    the client's os.environ; a later subprocess of the client must not inherit them."""
    pytest.importorskip("distributed")
    before = dict(os.environ)
    with DaskExecutor.start("local:1"):
        assert dict(os.environ) == before
    assert dict(os.environ) == before


def test_executor_from_options_is_in_process_by_default():
    with executor_from_options(None, None) as ex:
        assert isinstance(ex, InProcess) and current_executor() is ex


def test_store_written_by_two_processes_at_once_stays_consistent(tmp_path):
    """Two writer processes put overlapping runs at the same time: every file is a whole,
    readable record of the parameters its name says, one per parameter set."""
    import subprocess

    code = ("import sys, numpy as np\n"
            "from solderpyro.compute.runstore import RunStore, RunRecord\n"
            "from solderpyro.params import ANAND_NAMES\n"
            "lo, hi = int(sys.argv[2]), int(sys.argv[3])\n"
            "s = RunStore(sys.argv[1])\n"
            "for i in range(lo, hi):\n"
            "    vals = [1.0 + i] + [2.0] * 8\n"
            "    V = np.full((4, 560), float(i))\n"
            "    s.put('cfg', RunRecord(dict(zip(ANAND_NAMES, vals)), True, '',"
            " (1., 2., 3., 4.), tuple(f'g{k}' for k in range(560)), V))\n")
    procs = [subprocess.Popen([sys.executable, "-c", code, str(tmp_path), str(lo), str(hi)])
             for lo, hi in [(0, 300), (150, 450)]]  # runs 150-299 written by both
    for p in procs:
        assert p.wait(timeout=300) == 0
    store = RunStore(tmp_path)
    recs = store.records("cfg")
    files = list((tmp_path / "cfg" / "runs").glob("*"))
    assert len(files) == len(recs) == 450  # no temp files left, no duplicates
    for r in recs:
        assert r.V.shape == (4, 560) and np.all(r.V == r.values[0] - 1.0)
    assert Path(store.path("cfg", [1.0] + [2.0] * 8)).exists()


CLIENT_SCRIPT = """
import sys, torch
from solderpyro.compute.executor import DaskExecutor
from solderpyro.fem.loading import SEED_TIMES
from solderpyro.fem.solver import SpecimenSolver
from solderpyro.compute.runstore import RunStore
from solderpyro.compute.store import DoeOptions, run_doe
sys.path.insert(0, sys.argv[2])
from test_executor import _params, cheap_problem

problem = cheap_problem()
store = RunStore(sys.argv[1])
h = store.register(problem, SEED_TIMES, False, torch.float64)
with DaskExecutor.start("local:2") as ex:
    run_doe(SpecimenSolver(problem, None, dtype=torch.float64), store, h, _params(8),
            SEED_TIMES, options=DoeOptions(1, False, ex))
"""


def test_client_killed_mid_campaign_then_rerun_reuses_every_stored_run(tmp_path):
    """kill -9 of the client (and with it its local cluster) mid-campaign: the runs the
    workers finished are in the store, whole, and the rerun solves only the others."""
    import subprocess

    pytest.importorskip("distributed")
    problem = cheap_problem()
    store = RunStore(tmp_path / "store")
    h = store.register(problem, SEED_TIMES, False, torch.float64)
    runs = tmp_path / "store" / h / "runs"
    proc = subprocess.Popen([sys.executable, "-c", CLIENT_SCRIPT, str(tmp_path / "store"),
                             str(Path(__file__).parent)], start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 180
        while not (runs.is_dir() and len(list(runs.glob("*.json"))) >= 2):
            assert proc.poll() is None, proc.stderr.read().decode() if proc.stderr else ""
            assert time.monotonic() < deadline, "no run stored within 180 s"
            time.sleep(0.02)
        os.killpg(proc.pid, signal.SIGKILL)  # the client and the workers it started
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    time.sleep(0.5)
    kept = {p.name for p in runs.glob("*.json")}
    assert 2 <= len(kept) < 8
    res = run_doe(SpecimenSolver(problem, None, dtype=torch.float64), store, h, _params(8),
                  SEED_TIMES, options=DoeOptions(4, False, InProcess()))
    assert (res.n_reused, res.n_computed) == (len(kept), 8 - len(kept))
    assert bool(res.ok.all())
    assert {p.name for p in runs.glob("*.json")} == {f"{param_hash(r)}.json"
                                                     for r in _params(8)}


def test_a_batch_split_over_forked_processes_gives_the_whole_batchs_runs(monkeypatch, caplog):
    """solve_split (the in-process default): 16 runs split over two one-thread processes come
    back in row order with the runs of the whole batch solved at once (to 1e-12 of max|V|: a
    member's iterations do not depend on its batch, so the parts differ from the whole by
    rounding, ~1 ulp of max|V|), and a forked part that dies is solved in this process, with
    a warning, nothing lost."""
    import solderpyro.compute.executor as exe

    if not exe._can_fork():
        pytest.skip("no fork on this platform")
    solver = SpecimenSolver(cheap_problem())
    P = _params(16)
    names = list(ANAND_NAMES)
    whole = exe.solve_batch(solver, P, SEED_TIMES, names)
    tol = 1e-12 * max(float(abs(r.V).max()) for r in whole)
    split = exe.solve_split(solver, P, SEED_TIMES, names, 2)
    assert [r.params for r in split] == [r.params for r in whole]
    for a, b in zip(whole, split, strict=True):
        assert a.ok and b.ok
        np.testing.assert_allclose(b.V, a.V, rtol=0, atol=tol)
    # one run, or one process: solved here, whole
    assert exe.solve_split(solver, P[:1], SEED_TIMES, names, 2)[0].ok
    assert len(exe.solve_split(solver, P[:3], SEED_TIMES, names, 1)) == 3

    # in a daemonic process (a Dask worker's kind), which may not fork: whole, in place
    import multiprocessing as mp

    ctx = mp.get_context("fork")
    r, w = ctx.Pipe(duplex=False)

    def in_daemon() -> None:
        torch.set_num_threads(1)  # a forked child must not enter the parent's OpenMP pool
        w.send([float(abs(a.V - b.V).max()) for a, b in zip(
            whole, exe.solve_split(solver, P[:4], SEED_TIMES, names, 2), strict=False)])

    proc = ctx.Process(target=in_daemon, daemon=True)
    proc.start()
    got = r.recv()
    proc.join()
    assert proc.exitcode == 0 and len(got) == 4 and max(got) <= tol

    def dies(conn, *args):
        os._exit(3)

    monkeypatch.setattr(exe, "_child_run", dies)
    with caplog.at_level("WARNING", logger="solderpyro.compute.executor"):
        again = exe.solve_split(solver, P, SEED_TIMES, names, 2)
    assert "failed" in caplog.text and "run here" in caplog.text
    for a, b in zip(whole, again, strict=True):
        np.testing.assert_allclose(b.V, a.V, rtol=0, atol=tol)


class _ParentFails:
    """Solves slowly in a forked part, raises in the process that made it."""

    def __init__(self) -> None:
        self.pid = os.getpid()

    def __call__(self, p, times):
        if os.getpid() == self.pid:
            raise RuntimeError("simulated crash in the parent's part")
        time.sleep(30)
        raise RuntimeError("never reached: the part is stopped")


def test_a_split_batch_whose_own_part_raises_stops_its_forked_parts():
    """solve_split: an error in this process's part propagates at once and leaves no forked
    part running (a part blocked on a full pipe would otherwise outlive the error)."""
    import multiprocessing as mp

    import solderpyro.compute.executor as exe

    if not exe._can_fork():
        pytest.skip("no fork on this platform")
    before = {p.pid for p in mp.active_children()}  # e.g. a Dask cluster's workers
    t0 = time.perf_counter()
    with pytest.raises(RuntimeError, match="simulated crash"):
        exe.solve_split(_ParentFails(), _params(4), SEED_TIMES, list(ANAND_NAMES), 2)
    assert time.perf_counter() - t0 < 20
    assert not {p.pid for p in mp.active_children()} - before
