"""Why the coverage study's intervals miss: the modular likelihood's two terms at each truth.

Usage: python benchmarks/coverage_logdet.py
       [--results benchmarks/results/coverage_specimen.json]
       [--store runs/store] [--json benchmarks/results/coverage_logdet.json]

Rebuilds the default surrogate of benchmarks/coverage_specimen.py (50-run LHS, PCA, Matern 5/2 on
the flow-stress inputs) and the same 20 noisy datasets (same truths and noise draws), and prints
at each truth the modular log likelihood's -1/2 log|C(t) + sigma^2 I| (the code variance's
penalty) and -1/2 r^T (C + sigma^2 I)^-1 r (the misfit), with the surrogate's largest error there
(um), marking the datasets whose intervals missed the truth. The rows and their means over
the missed and the covered datasets go to the results file (overwritten).
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np
import torch

from solderpyro.compute.runstore import RunStore
from solderpyro.config.compose import build, compose
from solderpyro.design import lhs
from solderpyro.specimen import SpecimenModel, StoreUse
from solderpyro.surrogate import GPSurrogate
from solderpyro.surrogate.features import FlowStressInputs

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import Results, json_option  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--results", default="benchmarks/results/coverage_specimen.json")
    ap.add_argument("--store", default="runs/store")
    ap.add_argument("--noise", type=float, default=0.05)
    json_option(ap, __file__)
    a = ap.parse_args()
    out = Results(a.json)
    warnings.filterwarnings("ignore", category=UserWarning)
    res = json.load(open(a.results))
    setup = build(compose([]))
    sp, times = setup.space, setup.times
    model = SpecimenModel(setup.problem, sp, times, dtype=setup.dtype)
    model.use_store(StoreUse(RunStore(a.store)))
    theta = lhs(sp, res["runs"], 0)
    doe = model.runs(theta)
    y = doe.V.reshape(doe.V.shape[0], -1)
    gp = GPSurrogate(sp, output="pca", kernel="matern52", ard=True,
                     inputs=FlowStressInputs(sp, sp.defaults)).fit(theta[doe.ok], y[doe.ok])
    n = res["datasets"]
    truths = lhs(sp, n, 12345)
    tv = model.runs(truths)
    rng = np.random.default_rng(0)  # the coverage study's noise draws, in its order
    rows = []
    for i in range(n):
        f = tv.V[i].reshape(-1)
        yo = f + a.noise * torch.as_tensor(rng.standard_normal(f.shape[0]))
        with torch.no_grad():
            m, c = gp.mean_cov(truths[i][None])
        k = c + a.noise**2 * torch.eye(f.shape[0], dtype=c.dtype)
        r = yo - m
        miss = not all(res["per_dataset"][i]["covered"])
        row = {"dataset": i, "missed": miss, "half_logdet": -0.5 * torch.logdet(k).item(),
               "half_quad": -0.5 * (r @ torch.linalg.solve(k, r)).item(),
               "surrogate_max_error_um": (f - m).abs().max().item()}
        rows.append(row)
        print(f"dataset {i:2d} {'MISS' if miss else '    '} at the truth: -1/2 log det "
              f"{row['half_logdet']:6.1f}  -1/2 quad {row['half_quad']:6.1f}  surrogate max "
              f"error {row['surrogate_max_error_um']:.3f} um", flush=True)
    summary = {}
    for key, group in (("missed", True), ("covered", False)):
        g = [r for r in rows if r["missed"] == group]
        if g:
            summary[key] = {
                "datasets": len(g),
                "mean_half_logdet": float(np.mean([r["half_logdet"] for r in g])),
                "half_quad_range": [min(r["half_quad"] for r in g),
                                    max(r["half_quad"] for r in g)],
                "surrogate_max_error_um_range": [min(r["surrogate_max_error_um"] for r in g),
                                                 max(r["surrogate_max_error_um"] for r in g)]}
    print(json.dumps(summary, indent=1))
    out.write({"summary": summary, "per_dataset": rows}, results=Path(a.results),
              store=a.store, noise_um=a.noise, runs=res["runs"], datasets=n)


if __name__ == "__main__":
    main()
