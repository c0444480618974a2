"""NUTS in ridge coordinates against the sampler's own coordinates, on a finished run's
posterior (solderpyro.calibration.ridgemap).

    python benchmarks/ridge_coords.py RUN_DIR [--store STORE] [--json OUT.json]
        [--modes plain@0.8,ridge@0.9,ridge@0.95:150] [--seed S]

Rebuilds the run's final surrogate from its design runs (design.csv, through the run store:
no FE solve when the store holds them), takes 800 draws of its posterior (posterior.nc) as
the "previous round" a warm start would carry, and samples the same posterior twice, paired in
one process with the same starts and seeds (4 chains x (500 + 1500), dense metric, the
draws' covariance as the first metric, 2 worker processes):

- ``plain@A``: the sampler's own coordinates (flow-stress / logit), target acceptance A
  (run_nuts's default 0.8);
- ``ridge@A``: the :class:`RidgeMap` fitted to the 800 draws, target acceptance A (default
  0.9 = :data:`~solderpyro.calibration.mcmc.MAPPED_ACCEPT`, as :func:`run_nuts` does).

``--modes`` lists them (comma-separated; the first is the baseline of the ESS/s ratios);
``:W`` after the acceptance sets the warm-up iterations (default 500). ``--seed``: the
sampler's.

One torch/BLAS thread per chain process, as :func:`run_nuts` runs them.

Printed and written: wall s, gradients per iteration, divergences, min bulk ESS, min ESS/s and
its ratio (ridge / plain), the 2.5 / 50 / 97.5 % quantiles of each parameter from both, and
which coordinates the map bends (``curved``), and where the divergent draws sit (their mean
percentile in each parameter's marginal: near 0 or 1, a tail).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    import arviz as az
    from _runs import rebuild  # benchmarks/ is on sys.path when this script runs

    from solderpyro.calibration.koh import SITE_SIGMA, SITE_T
    from solderpyro.calibration.mcmc import MAPPED_ACCEPT
    from solderpyro.calibration.nuts import NutsSettings, sample_nuts
    from solderpyro.calibration.ridgemap import RidgeMap

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", help="a finished 'solderpyro calibrate' run directory")
    ap.add_argument("--store", default=None, help="its run store (default: run.json's)")
    ap.add_argument("--data", default=None,
                    help="its measurement CSV (default: run.json's; the demo's run names none)")
    ap.add_argument("--json", default=None)
    ap.add_argument("--modes", default=f"plain@0.8,ridge@{MAPPED_ACCEPT}",
                    help="coordinates@target acceptance[:warm-up], comma-separated; the "
                         "first is the baseline of the ratios")
    ap.add_argument("--seed", type=int, default=0, help="the sampler's seed")
    a = ap.parse_args()
    modes = [x.strip() for x in a.modes.split(",") if x.strip()]
    for md in modes:
        kind, _, rest = md.partition("@")
        acc, _, wu = rest.partition(":")
        try:
            ok = (kind in ("plain", "ridge") and 0.0 < float(acc) < 1.0
                  and (not wu or int(wu) >= 1))
        except ValueError:
            ok = False
        if not ok:
            ap.error(f"--modes: {md!r} is not plain@A or ridge@A[:W] with 0 < A < 1, W >= 1")
    torch.set_num_threads(1)  # as run_nuts does: one BLAS/torch thread per chain process
    from threadpoolctl import threadpool_limits
    threadpool_limits(1)
    rb = rebuild(Path(a.run), a.store, a.data)
    sm, fm, T, sig = rb.sm, rb.fm, rb.T, rb.sig
    u = sm.space.to_unit(torch.as_tensor(T)).numpy()
    sel = np.linspace(0, len(T) - 1, 800).round().astype(int)
    Q = np.stack([fm.to_unconstrained({SITE_T: torch.as_tensor(u[i]),
                                       SITE_SIGMA: torch.as_tensor(sig[i])}) for i in sel])
    m = RidgeMap(Q)
    starts = [0, 200, 400, 600]
    out: dict = {"run": str(a.run), "dim": fm.dim, "curved": m.curved, "modes": {}}
    for mode in modes:
        acc, _, wu = mode.split("@")[1].partition(":")
        ta, warmup = float(acc), int(wu or 500)
        if mode.startswith("plain"):
            f, W = fm.logp_and_grad, Q
        else:
            f, W = m.wrap(fm.logp_and_grad), m.inverse(Q)
        t0 = time.perf_counter()
        ns = NutsSettings(chains=4, warmup=warmup, draws=1500, seed=a.seed, target_accept=ta,
                          max_tree_depth=10, dense_mass=True, workers=2)
        res = sample_nuts(f, fm.dim, ns, W[starts], inv_metric=np.cov(W.T))
        wall = time.perf_counter() - t0
        D = res.draws if mode.startswith("plain") else m.forward(res.draws)[0]
        ess = float(np.min(az.ess(az.convert_to_dataset({"q": D}), method="bulk")["q"].values))
        flat = D.reshape(-1, fm.dim)
        samp = fm.to_samples(D)
        th = samp[SITE_T].reshape(-1, sm.space.dim).numpy()
        phys = sm.space.from_unit(torch.as_tensor(th)).numpy()
        div = np.asarray(res.diverging, bool).reshape(-1)
        # where the divergent draws sit: their mean percentile in each parameter's marginal
        # (0.5: spread like the posterior; near 0 or 1: in a tail)
        pct = (np.argsort(np.argsort(phys, 0), 0) + 0.5) / len(phys)
        out["modes"][mode] = {
            "wall_s": round(wall, 1),
            "warmup": warmup,
            "gradients_per_iteration": [round(n / (warmup + 1500), 1)
                                        for n in res.n_leapfrog],
            "divergences": res.divergences, "step_size": [round(x, 3) for x in res.step_size],
            "min_bulk_ess": round(ess), "min_ess_per_s": round(ess / wall, 1),
            "quantiles": {nm: np.quantile(phys[:, j], [0.025, 0.5, 0.975]).tolist()
                          for j, nm in enumerate(sm.space.names)},
            "draws": int(len(flat)),
            "divergent_percentile": ({nm: round(float(pct[div, j].mean()), 3)
                                      for j, nm in enumerate(sm.space.names)}
                                     if div.any() else {})}
        print(mode, json.dumps({k: v for k, v in out["modes"][mode].items()
                                if k != "quantiles"}), flush=True)
    p = out["modes"][modes[0]]
    out["ess_per_s_ratio"] = {k: round(r["min_ess_per_s"] / max(p["min_ess_per_s"], 1e-9), 2)
                              for k, r in out["modes"].items() if k != modes[0]}
    for nm in sm.space.names:
        print(f"{nm:>10}: " + "  ".join(f"{k} {np.round(r['quantiles'][nm], 5)}"
                                        for k, r in out["modes"].items()))
    print(f"curved coordinates {m.curved}; min ESS/s / {modes[0]}'s = {out['ess_per_s_ratio']}")
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
