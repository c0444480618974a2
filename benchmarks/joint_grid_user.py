"""The 400-run ball-drop full joint on its product design as a user calls it: default
``calibrate_joint`` (4 chains x 500 warm-up + 1,000 draws, beta drawn per draw), one thread.

Usage: python benchmarks/joint_grid_user.py   (prints wall time, R-hat, min bulk ESS, C's 95 %)
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_koh import C_TRUE, ball_grid_data  # noqa: E402

from solderpyro.calibration import Priors, calibrate_joint  # noqa: E402


def main() -> None:
    torch.set_num_threads(1)
    data = ball_grid_data()
    pr = Priors(sigma_max=1.0, sigma_c_max=10.0 * float(data.y_sim.std()))
    t0 = time.perf_counter()
    post, _ = calibrate_joint(data, pr, progress=False, workers=1)
    wall = time.perf_counter() - t0
    rows = post.summary()
    c = next(r for r in rows if r["parameter"] == "C")
    print(json.dumps({"wall_s": round(wall, 1), "sampler_s": round(post.seconds, 1),
                      "max_rhat": max(r["r_hat"] for r in rows),
                      "min_ess_bulk": min(r["ess_bulk"] for r in rows),
                      "C_95": [c["q2.5"], c["q97.5"]],
                      "truth_inside": bool(c["q2.5"] <= C_TRUE <= c["q97.5"])}))


if __name__ == "__main__":
    main()
