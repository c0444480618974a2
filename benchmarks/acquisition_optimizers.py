"""How to choose the q runs of a design round: BoTorch's continuous optimize_acqf, its discrete
optimizer over posterior draws, and the closed-form greedy choice (docs/design.md).

Usage: python benchmarks/acquisition_optimizers.py [--q 6]
       [--out benchmarks/results/acquisition_optimizers.json]

A 4-parameter PCA surrogate (24 LHS runs of a smooth 15-output toy, the test suite's), data at
the box's centre, 64 "posterior draws" in the box's middle fifth; the likelihood-aware
acquisition (qIntegratedLogLikVariance). Reports each optimizer's acquisition value at its
q-batch (higher is better) and its wall time, measured in this process one after the other.
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

import torch

from solderpyro.design import lhs
from solderpyro.design.acquisition import (
    AcquisitionPoints,
    greedy_draws,
    loglik_terms,
    propose,
    qIntegratedLogLikVariance,
)
from solderpyro.design.model import botorch_model
from solderpyro.params import ParameterSpace
from solderpyro.surrogate import GPSurrogate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--q", type=int, default=6)
    ap.add_argument("--out", default="benchmarks/results/acquisition_optimizers.json")
    a = ap.parse_args()
    torch.manual_seed(0)
    box = ParameterSpace.seed()
    x = lhs(box, 24, 1)
    u = box.to_unit(x)
    y = torch.stack([torch.sin(3 * u[:, 0]) + u[:, 1] * u[:, 2] + 0.2 * k * u[:, 3]
                     for k in range(15)], 1)
    gp = GPSurrogate(box, output="pca", kernel="matern52", ard=True).fit(x, y)
    m = botorch_model(gp)
    g = torch.Generator().manual_seed(0)
    mc = 0.4 + 0.2 * torch.rand(64, 4, generator=g, dtype=torch.float64)
    yo = gp.predict(box.from_unit(torch.full((1, 4), 0.5, dtype=torch.float64)))[0][0]
    gr, M = loglik_terms(gp, box.from_unit(mc), yo, 0.05)
    acq = qIntegratedLogLikVariance(m, mc, gr, M)
    res = {}
    t = time.perf_counter()
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        _, v = propose(acq, 4, a.q, "optimize", seed=0)
    res["optimize_acqf"] = {"value": v, "seconds": time.perf_counter() - t,
                            "warnings": len(w)}
    t = time.perf_counter()
    _, v = propose(acq, 4, a.q, "draws", candidates=mc)
    res["optimize_acqf_discrete"] = {"value": v, "seconds": time.perf_counter() - t}
    t = time.perf_counter()
    pts = AcquisitionPoints(box.from_unit(mc), box.from_unit(mc))
    _, v = greedy_draws(gp, "loglik", pts, a.q, 0.05, yo)
    res["greedy_draws"] = {"value": v, "seconds": time.perf_counter() - t}
    out = {"command": f"python benchmarks/acquisition_optimizers.py --q {a.q}", "q": a.q,
           "results": res}
    Path(a.out).write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
