"""Coverage of the FE-exact posterior over noise realizations of one hidden-effect case.

Usage: python benchmarks/coverage_exact.py [--effect stress_free_temperature] [--seeds 1-10]
       [--times seed|extended] [--n 128] [--rounds 4] [--profile 9]
       [--work runs/coverage_exact] [--out benchmarks/results/coverage_exact.json]

The same truth (solderpyro.diagnose.hidden.TRUTH and the effect's hidden value), full-field data
at the seed times (``--times extended``: at the seven extended times, the measurement that
separates a ridge of the seed times), noise 0.05 um with a different seed per dataset (seed 1
is the dataset of benchmarks/hidden_effects.py); the model is calibrated with
the effect switched on by the FE-exact step alone (solderpyro.pipeline.fe_exact.fe_exact: the
FE's best fit from a fixed start, the chi-square profile along the ridge, AMIS with the FE in the
likelihood; no surrogate). For an exact posterior each 95 % interval holds the truth in 95 % of
the datasets on average. Each dataset's result is appended to the JSON as soon as it is done
(a rerun skips finished seeds; FE runs are reused from the run store WORK/store).
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np
import torch

from solderpyro.calibration import Priors
from solderpyro.compute.executor import executor_from_options
from solderpyro.compute.runstore import RunStore
from solderpyro.config.compose import build, compose
from solderpyro.diagnose.hidden import TRUTH, make_dataset
from solderpyro.exact.coords import sampling_coords
from solderpyro.exact.posterior import profile_intervals
from solderpyro.fem.loading import EXTENDED_TIMES, SEED_TIMES
from solderpyro.io.measurements import read_measurements
from solderpyro.pipeline.fe_exact import ExactRun, fe_exact
from solderpyro.specimen import (
    SpecimenModel,
    StoreUse,
    calibration_box,
    observation_index,
    output_points,
    split_effects,
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--effect", default="stress_free_temperature")
    ap.add_argument("--seeds", default="1-10", help="noise seeds, e.g. 1-10 or 1,4,7")
    ap.add_argument("--times", default="seed", choices=("seed", "extended"),
                    help="observation times of the full-field data")
    ap.add_argument("--n", type=int, default=128, help="FE runs per AMIS round")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--profile", type=int, default=9)
    ap.add_argument("--profile-ci", action="store_true",
                    help="also the 95 %% profile-likelihood intervals through the FE "
                         "(solderpyro.exact.posterior.profile_intervals) and whether they hold "
                         "the truth")
    ap.add_argument("--work", default="runs/coverage_exact")
    ap.add_argument("--cluster", default=None, metavar="local:N",
                    help="run the FE batches (fits, AMIS rounds, profiles) on a Dask "
                         "LocalCluster of N workers (solderpyro.compute.executor)")
    ap.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                    help="run the FE batches on a running Dask cluster")
    ap.add_argument("--out", default="benchmarks/results/coverage_exact.json")
    a = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    torch.set_num_threads(1)
    if "-" in a.seeds:
        lo, hi = (int(v) for v in a.seeds.split("-"))
        seeds = list(range(lo, hi + 1))
    else:
        seeds = [int(v) for v in a.seeds.split(",")]
    out = Path(a.out)
    times = tuple(SEED_TIMES if a.times == "seed" else EXTENDED_TIMES)
    ov = [f"loading.output_times=[{','.join(str(t) for t in times)}]", f"effects=[{a.effect}]"]
    setup = build(compose(ov))
    fx, _, _ = split_effects(setup, times)
    space = calibration_box(setup, fx)
    coords = sampling_coords(space, setup.space.defaults)
    model = SpecimenModel(setup.problem, setup.space, times, True, dtype=setup.dtype,
                          effects=fx or ())
    model.use_store(StoreUse(RunStore(Path(a.work) / "store")))
    base = build(compose([]))
    with executor_from_options(a.cluster, a.scheduler):  # where the FE batches run
        _run_seeds(a, seeds, setup, space, coords, model, base, times, out)


def _run_seeds(a, seeds, setup, space, coords, model, base, times, out):
    """Each noise seed in turn: data, FE-exact posterior, profiles; recorded as done."""
    done = json.loads(out.read_text()) if out.exists() else {"cases": []}
    seen = {(c["effect"], c["seed"], c.get("times", "seed"), "profile_ci" in c)
            for c in done["cases"]}
    start = None
    for seed in seeds:
        if (a.effect, seed, a.times, a.profile_ci) in seen:
            continue
        t0 = time.perf_counter()
        d = Path(a.work) / a.effect / (f"seed{seed}" if a.times == "seed"
                                       else f"seed{seed}_{a.times}")
        d.mkdir(parents=True, exist_ok=True)
        data = d / "data.csv"
        if not data.exists():
            make_dataset(base, a.effect, data, True, times, seed=seed)
        meas = read_measurements(data, valid_points=output_points(setup.problem))
        truth = dict(TRUTH)
        truth.update(eval(meas.meta["hidden_values"]))  # noqa: S307 (our own file)
        model.set_observations(*observation_index(meas, model.times,
                                                  tuple(model.output_names)))
        y = torch.tensor(np.array(meas.value_um), dtype=torch.float64)

        def fun(rows: np.ndarray) -> np.ndarray:
            th = torch.as_tensor(np.asarray(rows, float), dtype=torch.float64)
            return model.observed_runs(th)[0].numpy()

        first = start is None
        if first:  # a truth-blind start: the middle of the box (a longer fit the first time)
            start = np.array([[(lo + hi) / 2 for lo, hi in zip(space.lower, space.upper,
                                                                  strict=True)]])
        ex, info = fe_exact(fun, coords, y, Priors(sigma_known=0.05), None, start, ExactRun(
            a.n, a.rounds, a.profile, seed, lm_iters=15 if first else 4))
        start = np.array([info["best_fit"]["x"]])  # the next dataset starts from this fit
        prof: dict = {}
        if a.profile_ci:
            pci = profile_intervals(fun, space, y.numpy(), 0.05, ex.samples,
                                    np.asarray(ex.result.extra["ssr"], float))
            prof = {"profile_ci": {p.parameter: [p.lower, p.upper] for p in pci},
                    "covered_profile_ci": {p.parameter: p.lower <= truth[p.parameter] <= p.upper
                                           for p in pci},
                    "profile_at_bound": {p.parameter: [p.at_lower_bound, p.at_upper_bound]
                                         for p in pci}}
        rows = {r["parameter"]: r for r in ex.rows}
        rec = {"effect": a.effect, "seed": seed, "times": a.times, "n_obs": len(y),
               "truth": truth,
               "intervals": {k: [rows[k]["q2.5"], rows[k]["median"], rows[k]["q97.5"]]
                             for k in truth},
               "covered": {k: rows[k]["q2.5"] <= v <= rows[k]["q97.5"]
                           for k, v in truth.items()},
               "ess": info["ess"], "khat": info["khat"], "reliable": info["reliable"],
               "fe_runs": info["fe_runs"], "best_chi2": info["best_fit"]["chi2"], **prof,
               "seconds": time.perf_counter() - t0}
        # re-read: another process (another effect or times) may have written meanwhile
        done = json.loads(out.read_text()) if out.exists() else {"cases": []}
        done["cases"] = [c for c in done["cases"]  # a rerun (e.g. with --profile-ci) replaces
                         if (c["effect"], c["seed"], c.get("times", "seed"))
                         != (a.effect, seed, a.times)]
        done["cases"].append(rec)
        cov: dict[str, list[bool]] = {}
        for c in done["cases"]:
            if (c["effect"], c.get("times", "seed")) == (a.effect, a.times) and c["reliable"]:
                for k, v in c["covered"].items():
                    cov.setdefault(k, []).append(v)
        done.setdefault("coverage_by_case", {})[f"{a.effect}/{a.times}"] = {
            k: float(np.mean(v)) for k, v in cov.items()}
        pc: dict[str, list[bool]] = {}
        for c in done["cases"]:
            if (c["effect"], c.get("times", "seed")) == (a.effect, a.times) \
                    and "covered_profile_ci" in c:
                for k, v in c["covered_profile_ci"].items():
                    pc.setdefault(k, []).append(v)
        if pc:
            done.setdefault("profile_ci_coverage_by_case", {})[f"{a.effect}/{a.times}"] = {
                k: float(np.mean(v)) for k, v in pc.items()}
        done.setdefault("commands", {})[f"{a.effect}/{a.times}"] = \
            "python benchmarks/coverage_exact.py " + " ".join(
            f"--{k} {v}" for k, v in vars(a).items())
        out.write_text(json.dumps(done, indent=2, default=float) + "\n")
        print(json.dumps(rec, default=float), flush=True)


if __name__ == "__main__":
    main()
