"""The 400-run ball-drop full joint on its product design as a user calls it: default
``calibrate_joint`` (4 chains x 500 warm-up + 1,000 draws, beta drawn per draw), one thread.

Usage: python benchmarks/joint_grid_user.py [--json benchmarks/results/joint_grid_user.json]
Prints and writes (overwriting the results file) the wall time, R-hat, min bulk ESS and C's 95 %.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import Results, json_option  # noqa: E402
from bench_koh import C_TRUE, ball_grid_data  # noqa: E402

from solderpyro.calibration import Priors, calibrate_joint  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    json_option(ap, __file__)
    a = ap.parse_args()
    res = Results(a.json)
    torch.set_num_threads(1)
    data = ball_grid_data()
    pr = Priors(sigma_max=1.0, sigma_c_max=10.0 * float(data.y_sim.std()))
    t0 = time.perf_counter()
    post, _ = calibrate_joint(data, pr, progress=False, workers=1)
    wall = time.perf_counter() - t0
    rows = post.summary()
    c = next(r for r in rows if r["parameter"] == "C")
    out = {"calibrate_wall_s": round(wall, 1), "sampler_s": round(post.seconds, 1),
           "max_rhat": max(r["r_hat"] for r in rows),
           "min_ess_bulk": min(r["ess_bulk"] for r in rows),
           "C_95": [c["q2.5"], c["q97.5"]], "C_true": C_TRUE,
           "truth_inside": bool(c["q2.5"] <= C_TRUE <= c["q97.5"])}
    print(json.dumps(out))
    res.write(out, data="bench_koh.ball_grid_data() (400-run product design, 12 observations)",
              chains=4, warmup=500, draws=1000, threads=1)


if __name__ == "__main__":
    main()
