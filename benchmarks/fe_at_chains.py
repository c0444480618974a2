"""The FE's chi-square at draws of every chain of a finished run.

    python benchmarks/fe_at_chains.py RUN_DIR [--per-chain 3]
           [--json benchmarks/results/fe_at_chains.json]

Reads the run's posterior (posterior.nc), its setup (run.json: overrides, data, store) and
solves the FE (through the run store: no solve where it holds the row) at ``--per-chain``
draws spread through each chain; prints, per draw, the parameters and the FE's chi-square
(noise sd from the data's sigma_um, 0.05 um in the reference case). A chain whose draws the FE
misfits by thousands while the others fit sits in an island only the surrogate fits (the
kinematic-hardening field case: 6,778-23,445 against 2,163-2,175). The draws and each chain's
range of the FE's chi-square go to the results file (overwritten), with the run's inputs.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import Results, json_option  # noqa: E402


def main() -> None:
    import arviz as az

    from solderpyro.config.compose import build, compose
    from solderpyro.config.rundir import RunDir
    from solderpyro.io.measurements import read_measurements
    from solderpyro.pipeline.problem import CalibrationProblem

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", help="a finished 'solderpyro calibrate' run directory")
    ap.add_argument("--per-chain", type=int, default=3)
    json_option(ap, __file__)
    a = ap.parse_args()
    res = Results(a.json)
    run = Path(a.run)
    info = RunDir.read(run).info
    setup = build(compose(info.overrides))
    meas = read_measurements(info.data)
    sm = CalibrationProblem.build(setup, meas, info.store, 64, False)
    post = az.from_netcdf(str(run / "posterior.nc")).posterior
    names = list(sm.space.names)
    n_chain, n_draw = post.sizes["chain"], post.sizes["draw"]
    idx = np.linspace(0, n_draw - 1, a.per_chain).astype(int)
    rows, chain = [], []
    for c in range(n_chain):
        for i in idx:
            rows.append([float(post[n].values[c, i]) for n in names])
            chain.append(c + 1)
    V, ok = sm.fe(torch.tensor(rows, dtype=torch.float64))
    sd = np.nanmedian(meas.sigma_um) if np.isfinite(meas.sigma_um).any() else 0.05
    chi2 = (((V.numpy() - sm.y.numpy()[None]) / sd) ** 2).sum(1)
    out = [{"chain": c, **dict(zip(names, r, strict=True)), "fe_chi2": float(x)}
           for c, r, x in zip(chain, rows, chi2, strict=True)]
    for o in out:
        print(json.dumps(o))
    by_chain = {str(c + 1): [float(chi2[k]) for k in range(len(out)) if chain[k] == c + 1]
                for c in range(n_chain)}
    res.write({"noise_sd_um": float(sd), "n_obs": int(sm.y.numel()),
               "fe_chi2_range_by_chain": {c: [min(v), max(v)] for c, v in by_chain.items()},
               "draws": out},
              run=run.resolve(), per_chain=a.per_chain, data=str(info.data),
              store=str(info.store), overrides=list(info.overrides))


if __name__ == "__main__":
    main()
