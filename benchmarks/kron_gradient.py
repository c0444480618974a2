"""One gradient of the full-joint likelihood, dense against Kronecker, on product designs.

Per case: the median over ``--reps`` calls (after one warm call) of the dense Cholesky's
gradient (``joint_flat(..., structure="dense")``) and the Kronecker form's
(``structure="kronecker"``), one thread, at the same parameter points, and the largest
relative differences of the value and the gradient between the two. Cases: the ball drop on
its 20 x 20 product design with 12 observations (``bench_koh.ball_grid_data``: the
``joint_400_grid`` benchmark), and a smooth two-input code on m_t x m_x runs with 5
observations (the sizes that set ``kronjoint.MIN_RUNS``).

Usage: python benchmarks/kron_gradient.py [--reps 50] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402
from scipy.stats import qmc  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_koh import ball_grid_data  # noqa: E402

from solderpyro.calibration import CalibrationData, Priors  # noqa: E402
from solderpyro.calibration.data import InputAxes  # noqa: E402
from solderpyro.calibration.fastkoh import joint_flat  # noqa: E402
from solderpyro.calibration.koh import prepare_joint  # noqa: E402
from solderpyro.params import Box  # noqa: E402

DT = torch.float64


def smooth_product(mt: int, mx: int, n: int = 5, seed: int = 0) -> CalibrationData:
    """``mt`` parameter sets (1-D LHS) each at the same ``mx`` inputs (1-D LHS), ``n`` noisy
    observations at t = 0.4 of y = sin(3 x) exp(-t) + x t."""
    rng = np.random.default_rng(seed)
    t = qmc.LatinHypercube(d=1, seed=seed).random(mt)
    x = qmc.LatinHypercube(d=1, seed=seed + 1).random(mx)
    ts, xs = np.repeat(t, mx, 0), np.tile(x, (mt, 1))

    def f(xx: np.ndarray, tt: np.ndarray) -> np.ndarray:
        return np.sin(3.0 * xx[:, 0]) * np.exp(-tt[:, 0]) + xx[:, 0] * tt[:, 0]

    xo = rng.random((n, 1))
    yo = f(xo, np.full((n, 1), 0.4)) + 0.01 * rng.standard_normal(n)
    unit = Box(("u",), (0.0,), (1.0,))
    tb = Box(("t",), (0.0,), (1.0,))

    def tt_(a: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(a, dtype=DT)

    return CalibrationData.create(tt_(xs), tt_(ts), tt_(f(xs, ts)), tt_(xo), tt_(yo),
                                  InputAxes(["u"], ["t"], theta_box=tb, x_box=unit))


def time_case(data: CalibrationData, reps: int, seed: int = 1) -> dict:
    inp = prepare_joint(data)
    dense = joint_flat(inp, Priors(), structure="dense").loglik
    kron = joint_flat(inp, Priors(), structure="kronecker").loglik
    p = data.theta_box.dim
    rng = np.random.default_rng(seed)
    ys = inp.y_scale
    pts = [np.concatenate([rng.random(p), [(0.005 + 0.1 * rng.random()) * ys,
                                          (0.3 + 2 * rng.random()) * ys],
                           0.2 + 4.0 * rng.random(inp.n_corr)]) for _ in range(5)]
    rel_ll = rel_g = 0.0
    for x in pts:
        a, ga = dense(x)
        b, gb = kron(x)
        rel_ll = max(rel_ll, abs(a - b) / max(1.0, abs(a)))
        rel_g = max(rel_g, float(np.abs(ga - gb).max() / max(1.0, np.abs(ga).max())))

    def med(fn) -> float:
        fn(pts[0])
        ts = []
        for i in range(reps):
            t0 = time.perf_counter()
            fn(pts[i % len(pts)])
            ts.append(time.perf_counter() - t0)
        return float(np.median(ts)) * 1e3

    return {"runs": int(data.n_sim), "observations": int(data.n_obs), "dense_ms": med(dense),
            "kronecker_ms": med(kron), "max_rel_diff_value": rel_ll,
            "max_rel_diff_gradient": rel_g}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reps", type=int, default=50)
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    torch.set_num_threads(1)
    cases = {"ball_drop_20x20": ball_grid_data()}
    cases.update({f"smooth_{k}x{k}": smooth_product(k, k) for k in (10, 12, 15, 20)})
    out = {}
    for name, data in cases.items():
        out[name] = time_case(data, a.reps)
        print(json.dumps({name: out[name]}), flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
