"""`solderpyro koh --propose q`: the next runs for a simulator solderpyro does not run, where
the posterior is, and never a pending one twice."""

import csv

import numpy as np
import torch

from solderpyro.calibration.tables import RunTables, koh_from_tables
from solderpyro.design.external import read_pending, still_pending

T_TRUE = 0.7


def sim(x, t):
    return np.sin(2 * x) + t * x + 0.3 * t**2


def _tables(tmp_path, ts):
    s = tmp_path / "sim.csv"
    with s.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["x", "t", "y"])
        for t in ts:
            for x in (0.0, 0.5, 1.0):
                w.writerow([x, t, sim(x, t)])
    o = tmp_path / "obs.csv"
    rng = np.random.default_rng(1)
    with o.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["x", "y"])
        for x in (0.2, 0.6, 0.9):
            w.writerow([x, sim(x, T_TRUE) + 0.01 * rng.standard_normal()])
    return s, o


def _append(sim_path, proposed):
    with proposed.open() as f:
        rows = list(csv.DictReader(f))
    with sim_path.open("a", newline="") as f:
        w = csv.writer(f)
        for r in rows:
            x, t = float(r["x"]), float(r["t"])
            w.writerow([x, r["t"], sim(x, t)])


def test_propose_writes_runs_in_the_posterior_and_never_a_pending_one_twice(tmp_path):
    s, o = _tables(tmp_path, np.linspace(0.0, 2.0, 6))
    out = tmp_path / "out"
    kw = dict(mode="modular", chains=1, warmup=150, draws=200, progress=False)
    post = koh_from_tables(RunTables(s, o, ["x"], ["t"], "y"), out, propose=2, **kw)
    lo, hi = np.quantile(post.flat("t").numpy(), [0.0, 1.0])
    with (out / "proposed.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2 * 3  # each proposed t at the 3 observed x
    t1 = sorted({float(r["t"]) for r in rows})
    assert len(t1) == 2 and all(lo <= t <= hi for t in t1)  # posterior draws
    # a posterior much narrower than the 0-2 prior box (sd 2 / sqrt(12) = 0.58): its sd, not
    # the range of 200 draws of one chain (a tail statistic: 0.78-1.08 over GP fits that
    # differ only along their likelihood's flat outputscale direction)
    assert post.flat("t").numpy().std() < 0.5 * 2.0 / np.sqrt(12.0)
    assert sorted({float(r["x"]) for r in rows}) == [0.2, 0.6, 0.9]
    # called again before the results are in: two new sets, the first two stay pending
    koh_from_tables(RunTables(s, o, ["x"], ["t"], "y"), out, propose=2, **kw)
    pend = read_pending(out / "pending.csv", ["t"])
    assert len(pend) == 4 and len(set(pend[:, 0].tolist())) == 4
    with (out / "proposed.csv").open() as f:
        t2 = {float(r["t"]) for r in csv.DictReader(f)}
    assert not (t2 & set(t1))
    # the results of the latest two are appended: only the first two are pending now
    _append(s, out / "proposed.csv")
    from solderpyro.calibration.tables import read_columns

    th = read_columns(s, ["t"], "SIM")
    left = still_pending(pend, th)
    assert sorted(left[:, 0].tolist()) == t1


def test_still_pending_matches_to_relative_precision():
    pend = torch.tensor([[1.0, 100.0], [2.0, 200.0]], dtype=torch.float64)
    runs = torch.tensor([[1.0 + 1e-9, 100.0], [5.0, 500.0]], dtype=torch.float64)
    torch.testing.assert_close(still_pending(pend, runs), pend[1:])
