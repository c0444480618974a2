"""The FE-exact posterior of one dataset: the reference a surrogate posterior is judged by.

    python benchmarks/exact_posterior.py DATA --effects modulus_temperature \
        --start 11.21,11070,2.003,0.1088,0.01758 --store STORE [--json OUT.json]
        [--compare RUN_DIR ...]

Full-field data at the seed times; the calibration's FE (default mesh and time step) with the
named effects switched on; :func:`solderpyro.pipeline.fe_exact.fe_exact` from ``--start``
(the calibrated parameters in the box's order, physical units): a few Levenberg-Marquardt
iterations, the chi-square profile along the ridge, ``--rounds`` AMIS rounds of ``--n`` FE
runs with the FE itself in the likelihood (noise sd known, 0.05 um). Prints and writes the
2.5 / 50 / 97.5 % quantiles, the weights' ESS and Pareto k-hat, and, for each ``--compare``
run directory, the largest quantile error per parameter divided by the FE-exact interval's
width (the accuracy measure of BENCHMARKS.md, "The adaptive design against fixed Latin
hypercubes").
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

from solderpyro.calibration import Priors
from solderpyro.compute.runstore import RunStore
from solderpyro.config.compose import build, compose
from solderpyro.exact.coords import sampling_coords
from solderpyro.fem.loading import SEED_TIMES
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

QS = ("q2.5", "median", "q97.5")


def exact_reference(data: str | Path, effects: list[str], start: np.ndarray, store: str | Path,
                    n: int = 128, rounds: int = 5, seed: int = 1, lm_iters: int = 6,
                    noise: float = 0.05) -> tuple[dict[str, list[float]], dict[str, Any]]:
    """The FE-exact posterior of full-field data at the seed times under the calibration's FE.

    Args:
        data: the measurement CSV. effects: registry names switched on. start: ``(1, dim)``
            physical start of the fit, in the calibration box's order. store: run store.
        n, rounds: AMIS runs per round and rounds; seed: its seed; lm_iters: the fit's
            Levenberg-Marquardt iterations; noise: the known noise sd, um.
    Returns:
        ``({parameter: [q2.5, median, q97.5]}, fe_exact's info)``.
    """
    times = tuple(SEED_TIMES)
    setup = build(compose([f"effects=[{','.join(effects)}]"] if effects else []))
    fx, _, _ = split_effects(setup, times)
    space = calibration_box(setup, fx)
    if start.shape[1] != space.dim:
        raise ValueError(f"start has {start.shape[1]} values; the box {space.names} needs "
                         f"{space.dim}")
    coords = sampling_coords(space, setup.space.defaults)
    model = SpecimenModel(setup.problem, setup.space, times, True, dtype=setup.dtype,
                          effects=fx or ())
    model.use_store(StoreUse(RunStore(store)))
    meas = read_measurements(data, valid_points=output_points(setup.problem))
    model.set_observations(*observation_index(meas, model.times, tuple(model.output_names)))
    y = torch.tensor(np.array(meas.value_um), dtype=torch.float64)

    def fun(rows: np.ndarray) -> np.ndarray:
        th = torch.as_tensor(np.asarray(rows, float), dtype=torch.float64)
        return model.observed_runs(th)[0].numpy()

    ex, info = fe_exact(fun, coords, y, Priors(sigma_known=noise), None, start,
                        ExactRun(n, rounds, 9, seed, lm_iters=lm_iters))
    return {r["parameter"]: [float(r[q]) for q in QS] for r in ex.rows}, info


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data")
    ap.add_argument("--effects", default="", help="comma-separated registry names")
    ap.add_argument("--start", required=True, help="comma-separated start, box order")
    ap.add_argument("--store", required=True)
    ap.add_argument("--n", type=int, default=128, help="FE runs per AMIS round")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--compare", nargs="*", default=[], help="run directories to judge")
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    torch.set_num_threads(1)
    start = np.array([[float(v) for v in a.start.split(",")]])
    try:
        ref, info = exact_reference(a.data, [e for e in a.effects.split(",") if e], start,
                                    a.store, a.n, a.rounds, a.seed)
    except ValueError as e:
        raise SystemExit(f"--start: {e}") from None
    out = {"command": "python benchmarks/exact_posterior.py " + " ".join(sys.argv[1:]),
           "quantiles": ref, "ess": info["ess"], "khat": info["khat"],
           "reliable": info["reliable"], "fe_runs": info["fe_runs"], "compare": {}}
    for k, v in ref.items():
        print(f"{k:8s} " + "  ".join(f"{x:.6g}" for x in v))
    print(f"ESS {info['ess']:.0f}, k-hat {info['khat']:.2f}, reliable {info['reliable']}, "
          f"{info['fe_runs']} FE runs")
    for run in a.compare:
        with (Path(run) / "summary.csv").open() as f:
            got = {r["parameter"]: [float(r[q]) for q in QS] for r in csv.DictReader(f)}
        err = {k: max(abs(g - e) for g, e in zip(got[k], v, strict=True)) / (v[2] - v[0])
               for k, v in ref.items() if k in got and k != "sigma"}
        out["compare"][run] = err
        print(f"{run}: largest quantile error / FE-exact width "
              + ", ".join(f"{k} {e:.3f}" for k, e in err.items())
              + f"; max {max(err.values()):.3f}")
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1, default=float) + "\n")


if __name__ == "__main__":
    main()
