"""`koh --propose`: one run per distinct observed x (replicates share it), and the closed-form
greedy choice equals BoTorch's fantasy-model criterion."""

import csv

import numpy as np
import torch

from solderpyro.design.external import distinct_x, propose_external
from solderpyro.params import Box
from solderpyro.surrogate import GPSurrogate


def _sim(x1, x2, t):
    return np.sin(2 * x1) + x2 * t + 0.3 * t**2


def _gp_and_obs(reps=3):
    """A scalar GP over (x1, x2, t) from 24 LHS runs; 4 distinct observed x, each ``reps``
    times."""
    from scipy.stats import qmc

    u = qmc.LatinHypercube(d=3, seed=1).random(24)
    X = torch.tensor(u * [1.0, 1.0, 2.0], dtype=torch.float64)
    y = torch.tensor(_sim(*X.T.numpy()), dtype=torch.float64)[:, None]
    box = Box(("x1", "x2", "t"), (0.0, 0.0, 0.0), (1.0, 1.0, 2.0))
    gp = GPSurrogate(box).fit(X, y)
    xu = torch.tensor([[0.2, 0.1], [0.6, 0.9], [0.9, 0.4], [0.4, 0.5]], dtype=torch.float64)
    return gp, xu.repeat_interleave(reps, 0), xu


def test_distinct_x_counts_replicates():
    _, x_obs, xu = _gp_and_obs(reps=3)
    got, counts = distinct_x(x_obs)
    assert got.shape == (4, 2) and counts.tolist() == [3, 3, 3, 3]
    assert {tuple(r) for r in got.tolist()} == {tuple(r) for r in xu.tolist()}
    one, n = distinct_x(torch.zeros(5, 0))
    assert one.shape == (1, 0) and n.tolist() == [5]


def test_closed_form_choice_equals_botorch_fantasies():
    """The first pick maximizes BoTorch's qNegIntegratedPosteriorVariance over the candidates
    (runs at the distinct x, integration over every observation, replicates included)."""
    from solderpyro.design.acquisition import integrated_code_variance
    from solderpyro.design.model import botorch_model, observed_weights

    gp, x_obs, xu = _gp_and_obs(reps=2)
    draws = 0.5 + torch.rand(40, 1, generator=torch.Generator().manual_seed(0),
                             dtype=torch.float64)
    pending = draws[3:4]
    picked = propose_external(gp, x_obs, draws, 0.1, 2, pending=pending, n_mc=40,
                              n_candidates=40)

    def pairs(th, x):
        return torch.cat([x[None].expand(len(th), -1, -1),
                          th[:, None, :].expand(-1, len(x), -1)], -1)

    mc = gp.box.to_unit(pairs(draws, x_obs).reshape(-1, 3))
    cands = gp.box.to_unit(pairs(draws, xu))  # (40, 4, 3)
    pend = gp.box.to_unit(pairs(pending, xu).reshape(-1, 3))
    acq = integrated_code_variance(botorch_model(gp), mc, observed_weights(gp, 0.1),
                                   X_pending=pend)
    with torch.no_grad():
        vals = acq(cands)
    vals[3] = -float("inf")  # the pending set is never offered
    best = int(vals.argmax())
    assert torch.equal(picked[0], draws[best])
    # second pick: the first joins the pending runs
    acq2 = integrated_code_variance(botorch_model(gp), mc, observed_weights(gp, 0.1),
                                    X_pending=torch.cat([pend, cands[best]]))
    with torch.no_grad():
        vals2 = acq2(cands)
    vals2[[3, best]] = -float("inf")
    assert torch.equal(picked[1], draws[int(vals2.argmax())])


def test_proposed_csv_has_one_row_per_run(tmp_path):
    """Replicated observations (3 per x): proposed.csv holds each set once per distinct x."""
    from solderpyro.calibration.tables import RunTables, koh_from_tables

    rng = np.random.default_rng(0)
    xs = [(0.1, 0.2), (0.5, 0.8), (0.9, 0.3)]
    with (tmp_path / "sim.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["x1", "x2", "t", "y"])
        for x1, x2, t in rng.uniform([0, 0, 0], [1, 1, 2], (20, 3)):
            w.writerow([x1, x2, t, _sim(x1, x2, t)])
    with (tmp_path / "obs.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["x1", "x2", "y"])
        for x1, x2 in xs:
            for _ in range(3):
                w.writerow([x1, x2, _sim(x1, x2, 0.7) + 0.02 * rng.standard_normal()])
    out = tmp_path / "out"
    koh_from_tables(RunTables(tmp_path / "sim.csv", tmp_path / "obs.csv", ["x1", "x2"], ["t"],
                              "y"), out, mode="modular", propose=3, chains=1, warmup=100,
                    draws=100, progress=False)
    with (out / "proposed.csv").open() as f:
        rows = list(csv.reader(f))[1:]
    assert len(rows) == 3 * len(xs)
    assert len({tuple(r[1:]) for r in rows}) == len(rows)  # no run asked for twice
    assert len({r[3] for r in rows}) == 3
