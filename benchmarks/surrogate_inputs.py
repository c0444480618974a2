"""Surrogate accuracy on held-out FE runs: the GP's inputs and kernel (docs/calibration.md).

Usage: python benchmarks/surrogate_inputs.py [--runs 50,100] [--test 120]
       [--store runs/store] [--out benchmarks/results/surrogate_inputs.json]

The 8 point outputs (V_A, V_B at the four seed times) of the reference case, an LHS of n runs
over the seed box (seed 0, as the calibration's DOE) and a separate LHS of held-out runs (seed
999). For each kernel (the seed's Gaussian, Matern 5/2) and input map (the raw box, or
FlowStressInputs: log flow stresses at 125 degC and 1e-5 1/s) it reports the held-out RMSE (um),
the share of held-out outputs inside the 95 % predictive interval, the sd of the standardized
errors (1 when the code variance is honest) and the mean log predictive density per run.
FE runs come from (and go to) the run store.
"""

from __future__ import annotations

import argparse
import json
import math
import warnings

import torch

from solderpyro.compute.runstore import RunStore
from solderpyro.config.compose import build, compose
from solderpyro.design import lhs
from solderpyro.specimen import SpecimenModel, StoreUse
from solderpyro.surrogate import GPSurrogate
from solderpyro.surrogate.features import FlowStressInputs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", default="50,100")
    ap.add_argument("--test", type=int, default=120)
    ap.add_argument("--store", default="runs/store")
    ap.add_argument("--out", default="benchmarks/results/surrogate_inputs.json")
    a = ap.parse_args()
    warnings.filterwarnings("ignore", category=UserWarning)
    setup = build(compose([]))
    sp, times = setup.space, setup.times
    model = SpecimenModel(setup.problem, sp, times, dtype=setup.dtype)
    model.use_store(StoreUse(RunStore(a.store)))

    def runs(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
        th = lhs(sp, n, seed)
        d = model.runs(th)
        return th[d.ok], d.V.reshape(d.V.shape[0], -1)[d.ok]

    xt, yt = runs(a.test, 999)
    rows = []
    for n in (int(v) for v in a.runs.split(",")):
        x, y = runs(n, 0)
        for kernel in ("gaussian", "matern52"):
            for inputs in ("raw", "flow_stress"):
                f = FlowStressInputs(sp, sp.defaults) if inputs == "flow_stress" else None
                gp = GPSurrogate(sp, output="pca", kernel=kernel, ard=True, inputs=f).fit(x, y)
                with torch.no_grad():
                    m, v = gp.predict(xt)
                z = (yt - m) / v.sqrt()
                lpd = (-0.5 * z**2 - 0.5 * torch.log(2 * math.pi * v)).sum(1).mean().item()
                r = {"runs": n, "kernel": kernel, "inputs": inputs,
                     "rmse_um": (yt - m).square().mean().sqrt().item(),
                     "max_abs_err_um": (yt - m).abs().max().item(),
                     "coverage95": (z.abs() < 1.96).double().mean().item(),
                     "z_sd": z.std().item(), "lpd_per_run": lpd,
                     "loo_rmse_rel": gp.loo().rmse_rel}
                rows.append(r)
                print(json.dumps(r), flush=True)
    res = {"test_runs": int(xt.shape[0]), "outputs": "V_A, V_B at the seed times",
           "reference": {"T_C": 125.0, "rate_per_s": 1e-5}, "rows": rows}
    with open(a.out, "w") as fh:
        json.dump(res, fh, indent=2)


if __name__ == "__main__":
    main()
