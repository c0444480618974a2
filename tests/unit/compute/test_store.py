"""Run store and DOE runner: config hash, atomic records, crash safety, failed members."""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from solderpyro.compute.executor import InProcess
from solderpyro.compute.runstore import RunRecord, RunStore, config_hash, param_hash
from solderpyro.compute.store import DoeOptions, run_doe
from solderpyro.design import lhs
from solderpyro.fem.loading import SEED_TIMES, ThermalCycle, TimeStepping
from solderpyro.fem.mesh import MeshSpec
from solderpyro.fem.problem import AnandSolder, Problem
from solderpyro.fem.solver import SpecimenSolver
from solderpyro.params import ANAND_NAMES, LIU2008, ParameterSpace

REPO = Path(__file__).resolve().parents[3]

#: A coarse, cheap problem (about a second per FE solve): mesh=coarse rows, nx=8, long steps.
CHEAP_SRC = """
from solderpyro.fem.loading import TimeStepping
from solderpyro.fem.mesh import Layer, MeshSpec
from solderpyro.fem.problem import Problem

def cheap_problem():
    layers = (Layer("copper", "copper", -4.0, 0.0, 3, 0.25, "top"),
              Layer("solder", "solder", 0.0, 0.5, 2),
              Layer("steel", "steel", 0.5, 4.5, 3, 0.25, "bottom"))
    return Problem(layers=layers, mesh=MeshSpec(nx=8),
                   stepping=TimeStepping(dT_max=25.0, dwell_dt0=100.0, growth=2.0,
                                         dt_max=1800.0))
"""
_ns: dict = {}
exec(CHEAP_SRC, _ns)
cheap_problem = _ns["cheap_problem"]

#: Four stiff parameter sets (little creep: few Newton iterations), (4, 9).
THETA4 = [[20.0, 12000.0, 4.0, 0.4], [16.0, 11000.0, 2.0, 0.3],
          [18.0, 11500.0, 3.0, 0.35], [22.0, 12500.0, 2.5, 0.45]]


def _params(theta) -> torch.Tensor:
    return ParameterSpace.seed().full(torch.tensor(theta, dtype=torch.float64))


# ---------------------------------------------------------------- config hash

def test_config_hash_is_stable_within_and_across_processes():
    h = config_hash(Problem(), SEED_TIMES, False, torch.float64)
    assert h == config_hash(Problem(), SEED_TIMES, False, torch.float64)
    assert h == config_hash(Problem(), tuple(reversed(SEED_TIMES)), False, torch.float64)
    code = ("import torch; from solderpyro.fem.problem import Problem; "
            "from solderpyro.fem.loading import SEED_TIMES; from solderpyro.compute.runstore "
            "import config_hash; print(config_hash(Problem(), SEED_TIMES, False, torch.float64))")
    env = dict(os.environ, PYTHONHASHSEED="123")  # a different str-hash seed than ours
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=REPO, env=env, timeout=120, check=True)
    assert out.stdout.strip() == h
    assert len(h) == 16 and int(h, 16) >= 0


def test_config_hash_changes_with_every_input():
    base = Problem()
    h0 = config_hash(base, SEED_TIMES, False, torch.float64)
    mats = dict(base.materials)
    mats["steel"] = dataclasses.replace(mats["steel"], E=201e3)

    class StiffSolder(AnandSolder):  # same fields, another law (e.g. T-dependent modulus)
        def modulus(self, T_C):
            return 1.1 * self.E

    mats2 = dict(base.materials)
    sol = base.materials["solder"]
    mats2["solder"] = StiffSolder(E=sol.E, nu=sol.nu, alpha=sol.alpha)
    lay = list(base.layers)
    lay[1] = dataclasses.replace(lay[1], ny=5)
    variants = {
        "mesh": (dataclasses.replace(base, mesh=MeshSpec(nx=31)), SEED_TIMES, False,
                 torch.float64),
        "layers": (dataclasses.replace(base, layers=tuple(lay)), SEED_TIMES, False,
                   torch.float64),
        "cycle": (dataclasses.replace(base, cycle=ThermalCycle(
            base.cycle.times, (25.0, 75.0, 75.0, 100.0, 100.0, 125.0, 125.0, 20.0))),
            SEED_TIMES, False, torch.float64),
        "material": (dataclasses.replace(base, materials=mats), SEED_TIMES, False,
                     torch.float64),
        "law": (dataclasses.replace(base, materials=mats2), SEED_TIMES, False, torch.float64),
        "plane": (dataclasses.replace(base, plane="strain"), SEED_TIMES, False, torch.float64),
        "stepping": (dataclasses.replace(base, stepping=TimeStepping(dT_max=3.9)), SEED_TIMES,
                     False, torch.float64),
        "points": (dataclasses.replace(base, points={"A": (15.0, 4.5)}), SEED_TIMES, False,
                   torch.float64),
        "T_ref": (dataclasses.replace(base, T_ref_C=25.000000001), SEED_TIMES, False,
                  torch.float64),
        "times": (base, SEED_TIMES[:3], False, torch.float64),
        "field": (base, SEED_TIMES, True, torch.float64),
        "dtype": (base, SEED_TIMES, False, torch.float32),
    }
    hashes = {k: config_hash(*v) for k, v in variants.items()}
    for k, h in hashes.items():
        assert h != h0, f"config_hash ignores a change of {k}"
    assert len(set(hashes.values())) == len(hashes)


def test_param_hash_exact_and_meta_readable(tmp_path):
    p = _params(THETA4)
    assert param_hash(p[0]) == param_hash(p[0].tolist()) == param_hash(p[0].numpy())
    q = p[0].clone()
    q[0] = torch.nextafter(q[0], torch.tensor(np.inf, dtype=q.dtype))  # one ulp away
    assert param_hash(q) != param_hash(p[0])
    with pytest.raises(ValueError, match="9 Anand"):
        param_hash(p[0, :4])
    store = RunStore(tmp_path)
    h = store.register(Problem(), SEED_TIMES, False, torch.float64)
    meta = store.meta(h)
    assert meta is not None and meta["config_hash"] == h
    assert meta["inputs"]["times"] == list(SEED_TIMES)
    assert meta["inputs"]["problem"]["mesh"]["nx"] == Problem().mesh.nx


# ---------------------------------------------------------------- records

def _record(values, ok=True, V=None):
    V = np.arange(8.0).reshape(4, 2) / 3.0 if V is None else V
    return RunRecord(dict(zip(ANAND_NAMES, values, strict=True)), ok, "" if ok else "diverged",
                     SEED_TIMES, ("A", "B"), V, n_steps=75, n_substeps=2, batch_size=3)


def test_record_round_trip_is_exact(tmp_path):
    store = RunStore(tmp_path)
    vals = [v * (1 + 1e-13) for v in LIU2008.values()]
    V = np.random.default_rng(0).normal(size=(4, 2)) * 1e3
    V[1, 0] = np.nan  # a time the member did not reach
    path = store.put("cfg", _record(vals, ok=False, V=V))
    assert path.parent == tmp_path / "cfg" / "runs" and path.stem == param_hash(vals)
    assert not list(path.parent.glob("*.tmp"))  # no temp files left behind
    back = store.get("cfg", vals)
    assert back is not None
    assert back.values == vals  # bitwise
    np.testing.assert_array_equal(back.V, V)  # NaN in the same place, other values bitwise
    assert (back.ok, back.reason, back.times, back.names) == (False, "diverged", SEED_TIMES,
                                                              ("A", "B"))
    assert (back.n_steps, back.n_substeps, back.batch_size) == (75, 2, 3)
    assert back.created and back.version
    d = json.loads(path.read_text())  # plain JSON: V as float64 bytes, parameters by name
    assert d["V"]["dtype"] == "<f8" and d["V"]["shape"] == [4, 2]
    assert set(d["params"]) == set(ANAND_NAMES)
    # a record written before the base64 form (V as lists, NaN as null) still reads exactly
    d["V"] = [[None if np.isnan(x) else float(x) for x in row] for row in V.tolist()]
    path.write_text(json.dumps(d))
    old = store.get("cfg", vals)
    assert old is not None
    np.testing.assert_array_equal(old.V, V)
    assert store.get("cfg", [v * 1.01 for v in vals]) is None
    assert store.get("other", vals) is None


def test_partial_or_corrupt_files_are_skipped_with_a_warning(tmp_path, caplog):
    store = RunStore(tmp_path)
    good, bad, wrong = list(LIU2008.values()), [v * 1.1 for v in LIU2008.values()], \
        [v * 1.2 for v in LIU2008.values()]
    store.put("cfg", _record(good))
    p_bad = store.put("cfg", _record(bad))
    text = p_bad.read_text()
    p_bad.write_text(text[: len(text) // 2])  # a torn write, as a non-atomic writer would leave
    p_wrong = store.put("cfg", _record(wrong))
    d = json.loads(p_wrong.read_text())
    del d["V"]
    p_wrong.write_text(json.dumps(d))  # valid JSON, incomplete record
    (p_bad.parent / ".x.json.tmp").write_text("{")  # stale temp file of a killed writer
    with caplog.at_level(logging.WARNING, logger="solderpyro"):
        recs = store.records("cfg")
        assert store.get("cfg", bad) is None
    assert [r.values for r in recs] == [good]
    msgs = " ".join(r.getMessage() for r in caplog.records)
    assert p_bad.name in msgs and p_wrong.name in msgs and "skipping" in msgs


# ---------------------------------------------------------------- DOE runner

class FakeSolver:
    """Cheap stand-in: V = affine in the parameters; members with s0 > 30 MPa fail.

    The outputs are (b, 4, 2) at the seed times; ``calls`` records the batch sizes solved.
    """

    def __init__(self, fail_at: int | None = None) -> None:
        self.calls: list[int] = []
        self.fail_at = fail_at

    def __call__(self, p, times):
        if self.fail_at is not None and len(self.calls) == self.fail_at:
            raise RuntimeError("simulated crash")
        self.calls.append(p.shape[0])
        t = torch.tensor(times, dtype=torch.float64)
        V = p[:, None, :2] * t[None, :, None] * 1e-6  # (b, n_time, 2)
        ok = p[:, 0] <= 30.0
        V = torch.where(ok[:, None, None], V, torch.nan)
        reasons = ["" if o else "no convergence in the step to t=600 s" for o in ok.tolist()]
        return SimpleNamespace(times=t, names=["A", "B"], V=V, ok=ok, reasons=reasons,
                               n_steps=10, n_substeps=0)


def test_doe_stores_failed_members_and_never_recomputes_them(tmp_path, caplog):
    space = ParameterSpace(("s0", "QR"), (5.0, 7000.0), (40.0, 13000.0))
    theta = lhs(space, 10, seed=1)
    params = space.full(theta)
    params = torch.cat([params, params[:2]])  # duplicates are solved once
    n_fail = int((params[:, 0] > 30).sum())
    assert 0 < n_fail < len(params)
    store, solver = RunStore(tmp_path), FakeSolver()
    with caplog.at_level(logging.DEBUG, logger="solderpyro"):  # the summary line is DEBUG
        # one process: its calls are all
        res = run_doe(solver, store, "cfg", params, SEED_TIMES,
                      options=DoeOptions(4, False, InProcess(processes=1)))
    assert solver.calls == [4, 4, 2] and (res.n_reused, res.n_computed) == (0, 10)
    assert res.V.shape == (12, 4, 2) and res.n_failed == n_fail
    assert torch.isnan(res.V[~res.ok]).all() and torch.isfinite(res.V[res.ok]).all()
    assert all(("no convergence" in r) == (not o) for r, o in zip(res.reasons, res.ok.tolist(),
                                                                 strict=True))
    assert len(list((tmp_path / "cfg" / "runs").glob("*.json"))) == 10
    msgs = [r.getMessage() for r in caplog.records]
    assert any(f"{n_fail} failed" in m and str(tmp_path) in m for m in msgs)
    assert sum("failed (params" in m for m in msgs) == n_fail
    solver2 = FakeSolver()
    res2 = run_doe(solver2, store, "cfg", params, SEED_TIMES, options=DoeOptions(4, False))
    assert solver2.calls == [] and (res2.n_reused, res2.n_computed) == (12, 0)
    assert torch.equal(res2.ok, res.ok) and res2.reasons == res.reasons
    torch.testing.assert_close(res2.V, res.V, rtol=0, atol=0, equal_nan=True)


def test_doe_crash_keeps_finished_batches(tmp_path):
    params = _params([[10.0 + i, 9000.0 + 100 * i, 2.0, 0.2] for i in range(6)])
    store = RunStore(tmp_path)
    with pytest.raises(RuntimeError, match="simulated crash"):
        run_doe(FakeSolver(fail_at=2), store, "cfg", params, SEED_TIMES,
                options=DoeOptions(2, False, InProcess(processes=1)))
    assert len(store.records("cfg")) == 4
    solver = FakeSolver()
    res = run_doe(solver, store, "cfg", params, SEED_TIMES,
                  options=DoeOptions(2, False, InProcess(processes=1)))
    assert (res.n_reused, res.n_computed, solver.calls) == (4, 2, [2])


def test_lhs_is_stratified_in_unit_cube_and_inside_the_box():
    space = ParameterSpace(("s0", "A"), (5.0, 1e4), (25.0, 1e8), log_scale=(False, True))
    x = lhs(space, 16, seed=3)
    assert x.shape == (16, 2) and x.dtype == torch.float64
    assert (x >= torch.tensor(space.lower)).all() and (x <= torch.tensor(space.upper)).all()
    u = space.to_unit(x)  # (16, 2): one point per stratum, per column (log for A)
    for j in range(2):
        assert sorted(torch.floor(u[:, j] * 16).long().tolist()) == list(range(16))
    assert torch.equal(x, lhs(space, 16, seed=3))


# ---------------------------------------------------------------- kill -9 mid-DOE

DOE_SCRIPT = CHEAP_SRC + """
import sys, torch
from solderpyro.fem.loading import SEED_TIMES
from solderpyro.fem.solver import SpecimenSolver
from solderpyro.compute.runstore import RunStore
from solderpyro.compute.store import DoeOptions, run_doe

params = torch.tensor({params}, dtype=torch.float64)
problem = cheap_problem()
store = RunStore(sys.argv[1])
h = store.register(problem, SEED_TIMES, False, torch.float64)
run_doe(SpecimenSolver(problem, None, dtype=torch.float64), store, h, params, SEED_TIMES,
        options=DoeOptions(1, False))
"""


def test_kill_minus_9_mid_doe_loses_nothing_computed(tmp_path):
    params = _params(THETA4)  # (4, 9)
    root = tmp_path / "store"
    script = tmp_path / "doe.py"
    script.write_text(textwrap.dedent(DOE_SCRIPT.format(params=params.tolist())))
    problem = cheap_problem()
    store = RunStore(root)
    h = config_hash(problem, SEED_TIMES, False, torch.float64)
    runs = root / h / "runs"
    proc = subprocess.Popen([sys.executable, str(script), str(root)], cwd=REPO,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 120
        while not (runs.is_dir() and any(runs.glob("*.json"))):
            assert proc.poll() is None, proc.stderr.read().decode() if proc.stderr else ""
            assert time.monotonic() < deadline, "no run stored within 120 s"
            time.sleep(0.02)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode == -signal.SIGKILL
    n_stored = len(list(runs.glob("*.json")))
    assert 1 <= n_stored < 4, "the DOE finished before the kill: make each batch slower"
    assert store.meta(h) is not None
    solver = SpecimenSolver(problem, None, dtype=torch.float64)
    res = run_doe(solver, store, h, params, SEED_TIMES, options=DoeOptions(1, False))
    assert res.n_reused == n_stored >= 1 and res.n_computed == 4 - n_stored
    assert res.ok.all() and len(store.records(h)) == 4
    fresh = solver.solve(params, SEED_TIMES)  # all four, one batch, in this process
    assert fresh.ok.all()
    # batches of one against one of four: rounding only (a member's iterations do not depend
    # on its batch; ~1 ulp of max|V| measured), bounded by 1e-11 max|V|
    ref = fresh.V.to(torch.float64)
    torch.testing.assert_close(res.V, ref, rtol=0, atol=1e-11 * ref.abs().max().item())


def test_records_are_readable_by_the_other_users_of_a_shared_store(tmp_path):
    """A record gets the permissions open() would give it (0666 less the umask), not
    mkstemp's 0600: workers of a cluster may run as other users of a shared filesystem."""
    old = os.umask(0o022)
    try:
        p = RunStore(tmp_path).put("cfg", _record(list(LIU2008.values())))
    finally:
        os.umask(old)
    import solderpyro.compute.runstore as rs

    assert p.stat().st_mode & 0o777 == 0o666 & ~rs._UMASK


def test_fields_at_their_meaning_free_values_leave_the_hash_as_it_was():
    """Layer ends, x spans and repeated cycles are left out of config_hash at the values that
    mean what the classes did without them (runs stored before stay reusable): the reference
    case's hash is the one stores already hold, and each field, once set, changes it."""
    from solderpyro.compute.runstore import config_hash
    from solderpyro.config.compose import build, compose
    from solderpyro.fem.loading import ThermalCycle

    s = build(compose([]))
    h = config_hash(s.problem, s.times, False, torch.float64, ())
    assert h == "698db24ce5fc30f4"  # the reference case's hash in existing run stores
    lay = list(s.problem.layers)
    lay[1] = dataclasses.replace(lay[1], x1=15.0)
    p1 = dataclasses.replace(s.problem, layers=tuple(lay))
    cyc = s.problem.cycle
    two = ThermalCycle(cyc.times + tuple(t + cyc.end for t in cyc.times[1:]),
                       cyc.temps_C + cyc.temps_C[1:], (cyc.end, 2 * cyc.end))
    p2 = dataclasses.replace(s.problem, cycle=two)
    p3 = dataclasses.replace(s.problem, cycle=ThermalCycle(two.times, two.temps_C))
    hashes = {config_hash(p, s.times, False, torch.float64, ()) for p in (p1, p2, p3)}
    assert h not in hashes and len(hashes) == 3
