"""Measure the diagnosis's discretization floor and write
solderpyro/diagnose/floor.json.

Two FE discretizations never agree exactly, so on enough values every candidate effect
"explains" some of the difference between the calibration's FE and the truth. This script
makes noise-free data of the reference case (docs/configuration.md) with a finer FE than
the calibration's (``mesh=fine``, temperature steps of 2 K, time steps of 150 s), fits the
calibration's FE to them exactly as ``solderpyro diagnose`` does (its base fit, then each
candidate's refit, :mod:`solderpyro.diagnose.refits`), and records per data layout (the full
field and the points A, B) the mean-square residual of the base fit and the mean square each
candidate's refit removes (:func:`solderpyro.diagnose.decide.floor_from_fits`).

    .venv/bin/python benchmarks/diagnosis_floor.py --store runs/floor/store [--cluster local:2]

Every FE run is kept in the run store; a rerun reads them back.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np

from solderpyro.compute.executor import executor_from_options
from solderpyro.compute.runstore import RunStore
from solderpyro.config.compose import build, compose
from solderpyro.diagnose.decide import FLOOR_FILE, floor_from_fits
from solderpyro.diagnose.hidden import TRUTH, make_dataset
from solderpyro.diagnose.refits import base_fit, layout, refit_candidates
from solderpyro.diagnose.screen import ladder_values
from solderpyro.effects import EFFECTS
from solderpyro.fem.loading import SEED_TIMES
from solderpyro.io.measurements import read_measurements
from solderpyro.specimen import SpecimenModels, output_points

FINE = ["mesh=fine", "solver.stepping.dT_max=2.0", "solver.stepping.dt_max=150"]
#: fit weights: chi2 = SS / SIGMA^2 (any value gives the same fits; small keeps the LM's
#: stopping tolerance, 0.5 in chi2, far below the sums of squares measured)
SIGMA = 0.01


def measure(kind: str, out: Path, store: RunStore) -> dict:
    field = kind == "field"
    data = out / f"clean_{kind}.csv"
    if not data.exists():
        make_dataset(build(compose(FINE)), None, data, field, SEED_TIMES, noise=1e-12, seed=0)
    setup = build(compose([]))
    meas = read_measurements(data, valid_points=output_points(setup.problem))
    cands = tuple(EFFECTS)
    lay = layout(setup, (), cands, meas)
    fe = SpecimenModels(setup, store)
    t0 = time.perf_counter()
    truth = np.array([TRUTH[n] for n in setup.space.names])
    lit = np.array([setup.anand[n] for n in setup.space.names])
    base = base_fit(lay, fe, meas, SIGMA, {"truth": truth, "literature constants": lit})
    starts = {}
    for eff in lay.fx_all.effects:  # as the diagnosis: a one-parameter effect from a rung
        x = base["x"].copy()
        if eff.n_params == 1:
            x[lay.cols(eff.name)] = ladder_values(eff)[0]
        starts[eff.name] = x
    refits = refit_candidates(lay, fe, meas, SIGMA, base["x"], base["chi2"], (), starts)
    n = len(meas.value_um)
    fl = floor_from_fits(base["chi2"] * SIGMA**2,
                         {r.name: r.chi2 * SIGMA**2 for r in refits if r.ok}, n,
                         f"python benchmarks/diagnosis_floor.py: noise-free {kind} data of the "
                         f"reference case from the FE with {' '.join(FINE)}, fitted by the "
                         "default FE")
    rec = fl.to_json()
    rec.pop("margin")
    rec.update({"n": n, "base_rms_um": float(np.sqrt(fl.baseline_ms_um2)),
                "base_x": dict(zip(setup.space.names, base["x"][:lay.n_cal].tolist(),
                                   strict=True)),
                "failed": [r.name for r in refits if not r.ok],
                "fe_runs": fe.computed, "seconds": round(time.perf_counter() - t0, 1)})
    logging.getLogger("solderpyro").info("floor %s: %s", kind, json.dumps(rec))
    return rec


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="runs/floor", help="data directory")
    ap.add_argument("--store", default="runs/floor/store", help="FE run store")
    ap.add_argument("--kinds", default="points,field")
    ap.add_argument("--cluster", default=None)
    ap.add_argument("--write", default=str(FLOOR_FILE), help="floor file to (over)write")
    a = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    path = Path(a.write)
    rec = json.loads(path.read_text()) if path.exists() else {}
    with executor_from_options(a.cluster, None):
        for kind in a.kinds.split(","):
            rec[kind] = measure(kind, out, RunStore(a.store))
            path.write_text(json.dumps(rec, indent=1) + "\n")
    print(json.dumps(rec, indent=1))


if __name__ == "__main__":
    main()
