"""Coverage of the specimen calibration's 95 % intervals over synthetic datasets.

Usage: python benchmarks/coverage_specimen.py [--datasets 20] [--runs 50] [--chains 2]
       [--warmup 300] [--draws 500] [--output batched|pca] [--kernel gaussian|matern52]
       [--inputs raw|flow_stress]
       [--var-explained 0.999]
       [--workflow [--budget N] [--start N] [--exact auto|on|off] --work runs/coverage]
       [--only i,j,...]
       [--store runs/store] [--out benchmarks/results/coverage_specimen.json]
       [--cluster local:2 | --scheduler tcp://HOST:PORT]

Truths are drawn from the prior (uniform on the seed box), so for an exact posterior the
coverage of a 95 % interval is 95 % on average. Each dataset: the FE at the truth at the seed
times, plus N(0, 0.05^2) um noise (8 values), calibrated with the same 50-run LHS surrogate
(one DOE from the run store, one GP fit) through the modular KOH posterior with NUTS, with
the noise known to ~10 % (``Priors(sigma_known=...)``, as when the data state ``sigma_um``).
With ``--workflow`` each dataset instead runs the whole ``solderpyro calibrate``
(solderpyro.pipeline.calibrate_specimen: its own adaptive design of up to ``--budget`` FE runs
from the shared run store, then NUTS, and the FE-exact step per ``--exact``).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from solderpyro.calibration import Priors, calibrate_modular
from solderpyro.compute.executor import executor_from_options
from solderpyro.compute.runstore import RunStore
from solderpyro.compute.sweep import sweep
from solderpyro.config.compose import build, compose
from solderpyro.design import lhs
from solderpyro.specimen import SpecimenModel, StoreUse
from solderpyro.surrogate import GPOptions, GPSurrogate
from solderpyro.surrogate.features import input_map


def _workflow(setup, tv, y, i, a):
    """The whole ``calibrate_specimen`` (its own adaptive design from the shared store,
    surrogate, NUTS, the FE-exact step per ``--exact``) on dataset ``i`` written as a
    measurement file; its 95 % intervals."""
    import csv
    from pathlib import Path

    from solderpyro.config.settings import (
        DesignSettings,
        ExactSettings,
        SamplerSettings,
        SurrogateSettings,
    )
    from solderpyro.io.measurements import from_arrays
    from solderpyro.pipeline import CalibrationSettings, calibrate_specimen

    times, names = tv.times, list(tv.names)
    pts = [setup.problem.points[n] for n in names]
    meas = from_arrays(np.asarray(times), names, np.array(pts),
                       y.reshape(len(times), len(names)).numpy(),
                       temperature_C=[setup.problem.cycle(t) for t in times],
                       sigma_um=a.noise)
    out = Path(a.work) / f"ds{i:02d}"
    dflt = DesignSettings()
    start = a.start if a.start is not None else dflt.start
    s = CalibrationSettings(
        design=DesignSettings(start=start, budget=a.budget),
        surrogate=SurrogateSettings(**setup.surrogate),
        sampler=SamplerSettings(chains=a.chains, warmup=a.warmup, draws=a.draws),
        exact=ExactSettings(mode=a.exact), seed=0, store=a.store, progress=False)
    if not (out / "summary.csv").exists():  # a rerun reuses finished datasets
        calibrate_specimen(setup, meas, out, s)
    with open(out / "summary.csv", newline="") as fh:
        rows = {r["parameter"]: r for r in csv.DictReader(fh)}
    names_t = setup.space.names
    return (np.array([float(rows[n]["q2.5"]) for n in names_t]),
            np.array([float(rows[n]["q97.5"]) for n in names_t]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--datasets", type=int, default=20)
    ap.add_argument("--runs", type=int, default=50,
                    help="LHS runs of the one shared surrogate (without --workflow)")
    ap.add_argument("--chains", type=int, default=2)
    ap.add_argument("--warmup", type=int, default=300)
    ap.add_argument("--draws", type=int, default=500)
    ap.add_argument("--noise", type=float, default=0.05)
    ap.add_argument("--output", default="pca", choices=("batched", "pca"),
                    help="surrogate layout: one GP per output, or GPs on principal components "
                         "(their errors are correlated across outputs, as the FE's are)")
    ap.add_argument("--kernel", default=None, choices=("gaussian", "matern52"),
                    help="GP correlation (default: the config's surrogate.kernel)")
    ap.add_argument("--inputs", default=None, choices=("raw", "flow_stress"),
                    help="GP inputs (default: the config's surrogate.inputs)")
    ap.add_argument("--var-explained", type=float, default=0.999,
                    help="PCA: share of the standardized output variance the kept PCs explain")
    ap.add_argument("--workflow", action="store_true",
                    help="run the whole calibration (solderpyro.pipeline.calibrate_specimen: "
                         "an adaptive design per dataset) instead of the one shared surrogate")
    ap.add_argument("--budget", type=int, default=None,
                    help="--workflow: most FE runs of each adaptive design (default: "
                         "calibrate's)")
    ap.add_argument("--start", type=int, default=None,
                    help="--workflow: Latin-hypercube runs before the first round (default: "
                         "calibrate's)")
    ap.add_argument("--exact", default="auto", choices=("auto", "on", "off"),
                    help="--workflow: the FE-exact step (calibrate --exact)")
    ap.add_argument("--work", default="runs/coverage", help="run directories (--workflow)")
    ap.add_argument("--only", default="", help="comma-separated dataset indices to run "
                    "(default: all; the truths and noise draws do not depend on it)")
    ap.add_argument("--store", default="runs/store")
    ap.add_argument("--out", default="benchmarks/results/coverage_specimen.json")
    ap.add_argument("--cluster", default=None, metavar="local:N",
                    help="run the datasets in parallel on a Dask LocalCluster")
    ap.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                    help="run the datasets on a running Dask cluster")
    a = ap.parse_args()
    setup = build(compose([]))
    sp, times = setup.space, setup.times
    model = SpecimenModel(setup.problem, sp, times, dtype=setup.dtype)
    model.use_store(StoreUse(RunStore(a.store), progress=True))
    theta = lhs(sp, a.runs, 0)
    doe = model.runs(theta)
    y_sim = doe.V.reshape(doe.V.shape[0], -1)  # (n_runs, n_time * n_out)
    kernel = a.kernel or setup.surrogate["kernel"]
    inputs = a.inputs or setup.surrogate["inputs"]
    setup.surrogate.update(kernel=kernel, output=a.output, inputs=inputs)  # for --workflow
    feats = input_map(inputs, sp, sp.defaults, setup.surrogate["inputs_T_C"],
                      setup.surrogate["inputs_rate"])
    gp = GPSurrogate(sp, output=a.output, kernel=kernel, ard=True, inputs=feats,
                     options=GPOptions(var_explained=a.var_explained)).fit(
        theta[doe.ok], y_sim[doe.ok])
    truths = lhs(sp, a.datasets, 12345)  # prior draws, stratified
    tv = model.runs(truths)
    rng = np.random.default_rng(0)
    ys = [tv.V[i].reshape(-1) + a.noise * torch.as_tensor(rng.standard_normal(y_sim.shape[1]))
          for i in range(a.datasets)]  # drawn in order: the noise does not depend on --only
    only = {int(v) for v in a.only.split(",") if v.strip()} or set(range(a.datasets))

    def job(name: str) -> dict:
        """One dataset: its 95 % intervals and whether they hold the truth."""
        i = int(name)
        if a.workflow:
            lo, hi = _workflow(setup, tv, ys[i], i, a)
        else:
            pr = Priors(sigma_known=a.noise)  # the data state their noise, as the demo's do
            post, _ = calibrate_modular(gp, ys[i], sp, priors=pr, chains=a.chains,
                                        warmup=a.warmup, draws=a.draws, seed=i,
                                        progress=False, init="sir")  # as calibrate_specimen
            t = post.flat("t").numpy()
            lo, hi = np.quantile(t, 0.025, axis=0), np.quantile(t, 0.975, axis=0)
        hit = (lo <= truths[i].numpy()) & (truths[i].numpy() <= hi)
        return {"truth": truths[i].tolist(), "lo": np.asarray(lo).tolist(),
                "hi": np.asarray(hi).tolist(), "covered": hit.tolist()}

    t0 = time.perf_counter()
    # one sweep job per dataset (solderpyro.compute.sweep), each kept in OUT.sweep.json as it ends:
    # in turn, or in parallel with --cluster
    with executor_from_options(a.cluster, a.scheduler) as ex:
        done = sweep([str(i) for i in sorted(only)], job, a.out + ".sweep.json", ex)
    bad = {k: v.get("error") for k, v in done.items() if not v.get("ok")}
    if bad:
        raise SystemExit(f"datasets failed: {bad}")
    rows = [done[str(i)] for i in sorted(only)]
    hits = np.array([r["covered"] for r in rows], dtype=bool)
    for i, r in zip(sorted(only), rows, strict=True):
        print(f"dataset {i + 1}/{a.datasets}: covered "
              f"{dict(zip(sp.names, r['covered'], strict=True))}; truth "
              f"{np.round(r['truth'], 3).tolist()} lo {np.round(r['lo'], 3).tolist()} "
              f"hi {np.round(r['hi'], 3).tolist()}", flush=True)
    res = {"datasets": a.datasets, "runs": a.runs, "noise_um": a.noise, "output": a.output,
           "kernel": kernel, "inputs": inputs,
           "workflow": a.workflow,
           **({"budget": a.budget, "start": a.start, "exact": a.exact} if a.workflow else {}),
           "n_pc": int(gp.basis.shape[1]),
           "coverage": dict(zip(sp.names, hits.mean(0).tolist(), strict=True)),
           "only": sorted(only),
           "loo_rmse_rel": gp.loo().rmse_rel, "seconds_sampling": time.perf_counter() - t0,
           "per_dataset": rows}
    print(json.dumps(res, indent=2))
    with open(a.out, "w") as f:
        json.dump(res, f, indent=2)


if __name__ == "__main__":
    main()
