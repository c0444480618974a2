"""Which refinement removes the calibration FE's discretization error, and what does the
correction (``calibration.discretization=correct``) buy?

    python benchmarks/discretization_correction.py DATA.csv [--store DIR] [--at x1,x2,x3,x4]
           [--json benchmarks/results/discretization_correction.json]

DATA: a clean full-field dataset made by the finer FE (``mesh=fine``, 2 K / 150 s steps; e.g.
``make_dataset(build(compose(FINE)), None, PATH, True, SEED_TIMES, noise=0.05, seed=0)``).

1. At the truth (the data file's metadata), one FE run per discretization; printed: the chi2
   (at the data's sigma) of its difference to the data-making FE, and the run's wall time.
2. Levenberg-Marquardt fits (``fe_best_fit``, 12 iterations from the truth and the Liu 2008
   constants) of the calibration FE, plain and with the correction ``FE_refined - FE`` (x1.5,
   ``fe_check.refined``) taken at ``--at`` (default: the plain fit), and of the data-making
   FE; printed: each best fit, its chi2, and the truth's chi2 above it.

Both parts also go to the results file (overwritten), with the inputs.
"""

from __future__ import annotations

import argparse
import ast
import sys
import time
from pathlib import Path

import numpy as np

from solderpyro.config.compose import build, compose
from solderpyro.io.measurements import read_measurements
from solderpyro.pipeline.fe_check import discretization_error
from solderpyro.pipeline.fe_exact import fe_best_fit
from solderpyro.pipeline.problem import CalibrationProblem

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import Results, json_option  # noqa: E402

DATA_FE = ["mesh=fine", "solver.stepping.dT_max=2.0", "solver.stepping.dt_max=150"]
VARIANTS = {
    "default": [],
    "half the time steps": ["solver.stepping.dT_max=2.0", "solver.stepping.dt_max=150"],
    "solder rows 8": ["mesh.rows.solder.ny=8"],
    "copper and steel rows 16": ["mesh.rows.copper.ny=16", "mesh.rows.steel.ny=16"],
    "x 40": ["mesh.nx=40"], "x 45": ["mesh.nx=45"], "x 60": ["mesh.nx=60"],
    "x 60 and solder rows 8": ["mesh.nx=60", "mesh.rows.solder.ny=8"],
    "mesh=fine": ["mesh=fine"],
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data")
    ap.add_argument("--store", default="runs/store")
    ap.add_argument("--at", default=None, help="where the correction is taken (4 values)")
    json_option(ap, __file__)
    a = ap.parse_args()
    res = Results(a.json)
    meas = read_measurements(a.data)
    truth_d = ast.literal_eval(meas.meta["truth"])
    sig = float(np.median(meas.sigma_um))

    def model(ov: list[str]) -> CalibrationProblem:
        return CalibrationProblem.build(build(compose(ov)), meas, a.store, 64, False)

    sm, data_fe = model([]), model(DATA_FE)
    truth = np.array([truth_d[n] for n in sm.space.names])
    y = sm.y.numpy()
    c2 = lambda v: float(np.sum((v / sig) ** 2))  # noqa: E731
    F = data_fe.observed(truth[None])[0]
    print("1. at the truth, chi2 of the difference to the data-making FE:")
    at_truth = {}
    for name, ov in VARIANTS.items():
        m = model(ov)
        t0 = time.perf_counter()
        v = m.observed(truth[None])[0]
        dt = time.perf_counter() - t0
        at_truth[name] = {"chi2_to_data_fe": c2(v - F), "run_s": dt}
        print(f"   {name:28s} {c2(v - F):7.2f}   {dt:5.2f} s (0 s: read from the store)")
    v = sm.observed(truth[None])[0] + discretization_error(sm, truth)
    at_truth["refined x1.5"] = {"chi2_to_data_fe": c2(v - F)}
    print(f"   {'refined x1.5':28s} {c2(v - F):7.2f}")
    liu = np.array([sm.setup.anand[n] for n in sm.space.names])
    starts = np.stack([truth, liu])

    fits = {}

    def fit(name: str, fun) -> None:
        best = fe_best_fit(fun, starts, sm.space, y, sig, 12)
        ct = c2(y - fun(truth[None])[0])
        fits[name] = {"best_fit": np.asarray(best.x).tolist(), "best_chi2": float(best.chi2),
                      "truth_chi2": ct, "truth_above_best": ct - float(best.chi2)}
        print(f"   {name:34s} best {np.round(best.x, 4)} chi2 {best.chi2:8.2f}; truth "
              f"{ct:8.2f}, above the best {ct - best.chi2:5.2f}")

    print("2. Levenberg-Marquardt:")
    plain = fe_best_fit(sm.observed, starts, sm.space, y, sig, 12)
    at = np.array([float(x) for x in a.at.split(",")]) if a.at else plain.x
    delta = discretization_error(sm, at)
    fit("calibration FE", sm.observed)
    fit("calibration FE, corrected", lambda r: sm.observed(r) + delta)
    fit("data-making FE", data_fe.observed)
    res.write({"at_truth": at_truth, "correction_at": np.asarray(at).tolist(),
               "levenberg_marquardt": fits},
              data=Path(a.data), store=a.store, truth=truth.tolist(), sigma_um=sig)


if __name__ == "__main__":
    main()
