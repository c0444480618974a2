"""Would a discretization-error term in the likelihood move the truth inside?

The calibration FE (default mesh and steps) against field data made by a finer FE: the
Levenberg-Marquardt best fit, and the truth's chi-square above it, with and without a
rank-one error term ``s^2 e e^T`` in the noise covariance, ``e`` the FE once refined (x1.5,
``pipeline.fe_check.refined``) minus the FE, taken at a reference point (``--at``: the
literature constants, or a comma-separated parameter row, e.g. the fit). The term is whitened
away exactly (``W = I - beta e e^T / |e|^2``), so LM fits ``W f`` to ``W y``.

Usage: python benchmarks/discretization_term.py DATA.csv [--effect NAME --truth-extra V]
       [--at liu|x1,x2,...] [--store DIR] [--json benchmarks/results/discretization_term.json]
(e.g. runs/hidden_effect_data/none.csv --at 13.6,12025,3.02,0.1127 and --at liu;
runs/hidden_effect_data/thermal_lag.csv --effect thermal_lag --truth-extra 105 --at
15.93,12020.8,3.446,0.10805,105.515)
Prints, and writes to the results file (overwritten), each amplitude sd's best fit and the
truth's chi-square above it.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

from solderpyro.config.compose import build, compose
from solderpyro.exact.fit import LMOptions, lm_fit
from solderpyro.io.measurements import read_measurements
from solderpyro.pipeline.fe_check import refined
from solderpyro.pipeline.problem import CalibrationProblem

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import Results, json_option  # noqa: E402

TRUTH = [12.92, 10586.0, 2.04, 0.1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data")
    ap.add_argument("--effect", default=None)
    ap.add_argument("--truth-extra", type=float, nargs="*", default=[])
    ap.add_argument("--at", default="liu")
    ap.add_argument("--store", default="runs/store")
    ap.add_argument("--sd", type=float, nargs="*", default=[0.0, 3.0, 30.0],
                    help="prior sd of the term's amplitude (0: no term)")
    json_option(ap, __file__)
    a = ap.parse_args()
    res = Results(a.json)
    meas = read_measurements(a.data)
    setup = build(compose([f"effects=[{a.effect}]"] if a.effect else []))
    sm = CalibrationProblem.build(setup, meas, a.store, 64, False)
    fine = CalibrationProblem.build(dataclasses.replace(setup, problem=refined(setup.problem)),
                               meas, a.store, 64, False)
    truth = np.array(TRUTH + list(a.truth_extra))
    y, sig = np.array(meas.value_um), float(np.median(meas.sigma_um))
    if a.at == "liu":
        e = (fine.literature() - sm.literature()).numpy()
        ref = truth
    else:
        ref = np.array([float(v) for v in a.at.split(",")])
        e = (fine.observed(ref[None]) - sm.observed(ref[None]))[0]
    print(f"|e|^2 / sigma^2 = {e @ e / sig**2:.3g} (pattern at {a.at})")
    rows = []
    for s in a.sd:
        beta = 1.0 - np.sqrt(sig**2 / (sig**2 + s**2 * float(e @ e)))

        def W(V: np.ndarray, beta: float = beta) -> np.ndarray:
            return V - beta * np.outer(np.atleast_2d(V) @ e, e).reshape(V.shape) / (e @ e)

        def f(X: np.ndarray, W=W) -> np.ndarray:
            return W(sm.observed(X))

        fits = lm_fit(f, np.array([truth, ref]), sm.space.lower, sm.space.upper, W(y), sig,
                      options=LMOptions(iters=10))
        b = min(fits, key=lambda t: t.chi2)
        c2t = float(np.sum((W(y) - f(truth[None])[0]) ** 2) / sig**2)
        print(f"amplitude sd {s:g}: best fit chi2 {b.chi2:.2f} at {np.round(b.x, 4)}; truth "
              f"{c2t:.2f}; Delta {c2t - b.chi2:.2f}")
        rows.append({"amplitude_sd": s, "best_fit": np.asarray(b.x).tolist(),
                     "best_chi2": float(b.chi2), "truth_chi2": c2t,
                     "truth_above_best": c2t - float(b.chi2)})
    res.write({"e2_over_sigma2": float(e @ e / sig**2), "by_amplitude_sd": rows},
              data=Path(a.data), at=a.at, effect=a.effect, truth=truth.tolist(),
              store=a.store, sigma_um=sig)


if __name__ == "__main__":
    main()
