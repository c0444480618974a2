"""Does the data's own model put the truth outside? Profile chi-square at each true constant.

For field data with a known truth: the Levenberg-Marquardt best fit of a chosen FE (``--fine``: the
FE that made the data, ``mesh=fine`` with 2 K / 150 s steps, as benchmarks/design_hidden.py makes
it; default: the calibration's FE), and for each parameter the fit with that parameter held at its
true value. ``Delta = chi2_profile - chi2_best``; above 3.84 the truth lies outside the 95 %
profile-likelihood interval. If every Delta is below it, a calibration whose interval misses the
truth is wrong, not unlucky (BENCHMARKS.md, "Hidden effects: diagnose, recalibrate, cover the
truths").

Usage: python benchmarks/profile_at_truth.py DATA.csv --start x1,x2,... [--effect NAME]
       [--truth-extra V ...] [--params 0,1,...] [--fine] [--store DIR]
       [--json benchmarks/results/profile_at_truth.json]
(e.g. runs/hidden_effect_data/none.csv --start 13.44,11160,2.41,0.104 with and without --fine;
runs/hidden_effect_data/moire_rigid_motion.csv --effect moire_rigid_motion --fine --params 1,2,5
with the truth's and the posterior medians' Moire values appended)
Prints, and writes to the results file (overwritten), the best fit and each profile's Delta.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from solderpyro.config.compose import build, compose
from solderpyro.diagnose.hidden import TRUTH
from solderpyro.exact.fit import LMOptions, lm_fit
from solderpyro.io.measurements import read_measurements
from solderpyro.pipeline.problem import CalibrationProblem

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import Results, json_option  # noqa: E402

FINE = ["mesh=fine", "solver.stepping.dT_max=2.0", "solver.stepping.dt_max=150"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data")
    ap.add_argument("--start", required=True, help="comma-separated start row (physical)")
    ap.add_argument("--effect", default=None)
    ap.add_argument("--truth-extra", type=float, nargs="*", default=[])
    ap.add_argument("--params", default=None, help="indices to profile (default: all)")
    ap.add_argument("--fine", action="store_true", help="the data-making FE, not the default")
    ap.add_argument("--store", default="runs/store")
    json_option(ap, __file__)
    a = ap.parse_args()
    res = Results(a.json)
    meas = read_measurements(a.data)
    ov = (FINE if a.fine else []) + ([f"effects=[{a.effect}]"] if a.effect else [])
    sm = CalibrationProblem.build(build(compose(ov)), meas, a.store, 64, False)
    truth = np.array([TRUTH[k] for k in ("s0", "QR", "xi", "m")] + list(a.truth_extra))
    start = np.array([float(v) for v in a.start.split(",")])
    d = sm.space.dim
    if truth.size != d or start.size != d:
        raise SystemExit(f"--start and the truth (with --truth-extra) need {d} values "
                         f"({', '.join(sm.space.names)}), got {start.size} and {truth.size}")
    ks = [int(k) for k in a.params.split(",")] if a.params else list(range(d))
    # each profile from two starts: --start with the parameter at its truth, and the truth
    # itself (a profile is never above the truth's own chi-square: the truth is one of its
    # points; from --start alone the constrained fits could stop above it)
    starts = ([start] + [np.where(np.arange(d) == k, truth, start) for k in ks]
              + [truth for _ in ks])
    free = [np.arange(d)] + [np.delete(np.arange(d), k) for k in ks] * 2
    y, sig = np.array(meas.value_um), float(np.median(meas.sigma_um))
    t0 = time.perf_counter()
    fits = lm_fit(sm.observed, np.array(starts), sm.space.lower, sm.space.upper, y, sig,
                  free=free, options=LMOptions(iters=12, tol=0.05))
    c2t = float((((y - sm.observed(truth[None])[0]) / sig) ** 2).sum())
    best = min(min(f.chi2 for f in fits), c2t)
    print(f"{time.perf_counter() - t0:.0f} s; best fit chi2 {fits[0].chi2:.2f} at "
          f"{np.round(fits[0].x, 4)}; truth {c2t:.2f} (joint Delta {c2t - best:.2f})")
    profiles = {}
    for j, k in enumerate(ks):
        dl = min(fits[j + 1].chi2, fits[j + 1 + len(ks)].chi2, c2t) - best
        profiles[sm.space.names[k]] = float(dl)
        print(f"profile {sm.space.names[k]} at its truth: Delta {dl:.2f} "
              f"({'outside' if dl > 3.84 else 'inside'} the 95 % profile interval)")
    res.write({"best_fit": np.asarray(fits[0].x).tolist(), "best_fit_chi2": float(fits[0].chi2),
               "truth_chi2": c2t, "joint_delta": c2t - best,
               "profile_delta_at_truth": profiles,
               "all_inside_3_84": all(v <= 3.84 for v in profiles.values())},
              data=Path(a.data), start=start.tolist(), effect=a.effect, truth=truth.tolist(),
              fe="data-making (--fine)" if a.fine else "calibration (default)",
              store=a.store, sigma_um=sig)


if __name__ == "__main__":
    main()
