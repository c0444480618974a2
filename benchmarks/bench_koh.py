"""NUTS efficiency of solderpyro's calibrations (Pyro and fast samplers) against NumPyro.

Usage: python benchmarks/bench_koh.py [--chains 4] [--warmup 500] [--draws 1000]
       [--out benchmarks/results_koh.json] [--no-numpyro] [--no-pyro]

Cases (identical data, priors and likelihood on both sides):
- direct: the seed's mathematical example, t and sigma (Table I's posterior);
- joint: the full-joint KOH posterior (beta integrated out analytically on both sides) with
  m = 50 LHS runs, n = 8 observations and 4 calibration parameters of
  y = t1 exp(-t2 x) + t3 sin(pi t4 x), x in [0, 1].
Effective samples per second = min over parameters of ArviZ's bulk ESS / wall time (warm-up,
sampling and JIT compilation included). All run their chains one after another on one CPU
thread. solderpyro runs each case twice, with ``sampler="pyro"`` (Pyro's NUTS, TorchScript
potential, autograd) and ``sampler="fast"`` (solderpyro.calibration.nuts on the analytic
densities of solderpyro.calibration.fastkoh); its joint adapts a dense mass matrix (its
default); NumPyro runs with both its default diagonal and a dense mass matrix, and the ratios
are taken against the faster.
NumPyro is the optional `bench` extra (pip install -e .[bench]).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import time
import warnings

os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=1")
os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")  # one BLAS thread (NumPy, torch) as one XLA one

import numpy as np  # noqa: E402
import torch  # noqa: E402
from scipy.stats import qmc  # noqa: E402

from solderpyro.calibration import CalibrationData, Priors, calibrate_direct, calibrate_joint  # noqa: E402,E501
from solderpyro.calibration.koh import prepare_joint  # noqa: E402
from solderpyro.calibration.mcmc import flatten_sites  # noqa: E402
from solderpyro.examples.seed_math import X_OBS, code, make_data  # noqa: E402
from solderpyro.params import Box  # noqa: E402

DT = torch.float64
T_BOX = Box(("t",), (0.0,), (2.0,))
J_BOX = Box(("t1", "t2", "t3", "t4"), (0.5, 0.5, 0.0, 0.5), (1.5, 3.0, 1.0, 2.0))
J_TRUE = torch.tensor([1.0, 1.5, 0.5, 1.2], dtype=DT)


def j_code(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """``x (n, 1)``, ``t (..., 4)`` -> ``(n,)`` (or broadcast)."""
    xx = x[:, 0]
    return t[..., 0] * torch.exp(-t[..., 1] * xx) + t[..., 2] * torch.sin(math.pi * t[..., 3] * xx)


def joint_data(m: int = 50, n: int = 8, seed: int = 0) -> CalibrationData:
    u = torch.as_tensor(qmc.LatinHypercube(d=5, seed=seed).random(m), dtype=DT)
    xs, ts = u[:, :1], J_BOX.from_unit(u[:, 1:])
    ys = torch.stack([j_code(xs[i:i + 1], ts[i])[0] for i in range(m)])
    xo = torch.linspace(0, 1, n, dtype=DT)[:, None]
    g = torch.Generator().manual_seed(seed)
    yo = j_code(xo, J_TRUE) + 0.05 * torch.randn(n, generator=g, dtype=DT)
    return CalibrationData.create(xs, ts, ys, xo, yo, ["x"], list(J_BOX.names),
                                  theta_box=J_BOX, x_box=Box(("x",), (0.0,), (1.0,)))


def ess_per_s(cols: dict[str, np.ndarray], seconds: float) -> tuple[float, float]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        import arviz as az
    ess = az.ess(az.from_dict(posterior=cols), method="bulk")
    mn = min(float(ess[k]) for k in cols)
    return mn, mn / seconds


# ----------------------------------------------------------------------------- NumPyro side
def numpyro_direct(x, y, sigma_max, chains, warmup, draws, seed):
    import jax.numpy as jnp
    import numpyro
    import numpyro.distributions as nd
    from jax import random

    xj, yj = jnp.asarray(x[:, 0].numpy()), jnp.asarray(y.numpy())
    lo, hi = T_BOX.lower[0], T_BOX.upper[0]

    def model():
        tu = numpyro.sample("t_unit", nd.Uniform(0.0, 1.0))
        sig = numpyro.sample("sigma", nd.Uniform(0.0, sigma_max))
        numpyro.sample("y", nd.Normal(5 * jnp.exp(-(lo + (hi - lo) * tu) * xj), sig), obs=yj)

    return _run_numpyro(model, chains, warmup, draws, seed, random)


def numpyro_joint(inp, pr: Priors, chains, warmup, draws, seed, dense=False):
    import jax.numpy as jnp
    import jax.scipy.linalg as jsl
    import numpyro
    import numpyro.distributions as nd
    from jax import random

    u_sim, u_xo = jnp.asarray(inp.u_sim.numpy()), jnp.asarray(inp.u_xobs.numpy())
    z, ys = jnp.asarray(inp.z.numpy()), inp.y_scale
    m, n = u_sim.shape[0], u_xo.shape[0]
    p = inp.data.theta_box.dim
    lo_c, hi_c = pr.corr_range

    def model():
        tu = numpyro.sample("t_unit", nd.Uniform(jnp.zeros(p), 1.0).to_event(1))
        sig = numpyro.sample("sigma", nd.Uniform(0.0, pr.sigma_max))
        sc = numpyro.sample("sigma_c", nd.Uniform(0.0, pr.sigma_c_max))
        corr = numpyro.sample("corr", nd.Uniform(jnp.full(1, lo_c), hi_c).to_event(1))
        u = jnp.concatenate([u_sim, jnp.concatenate([u_xo, jnp.broadcast_to(tu, (n, p))], 1)])
        d2 = ((u[:, None, :] - u[None, :, :]) ** 2).sum(-1)
        cov = (sc / ys) ** 2 * (jnp.exp(-corr[0] * d2) + inp.nugget * jnp.eye(m + n))
        cov = cov + jnp.diag(jnp.concatenate([jnp.zeros(m), jnp.full(n, (sig / ys) ** 2)]))
        chol = jnp.linalg.cholesky(cov)
        h = jnp.ones((m + n, 1))
        a = jsl.solve_triangular(chol, h, lower=True)
        b = jsl.solve_triangular(chol, z[:, None], lower=True)
        g = a.T @ a
        beta = jnp.linalg.solve(g, a.T @ b)
        r = b - a @ beta
        ll = -jnp.log(jnp.diag(chol)).sum() - 0.5 * jnp.log(g[0, 0]) - 0.5 * (r**2).sum()
        numpyro.factor("y", ll)

    return _run_numpyro(model, chains, warmup, draws, seed, random, dense)


def _run_numpyro(model, chains, warmup, draws, seed, random, dense=False):
    from numpyro.infer import MCMC, NUTS

    t0 = time.perf_counter()
    mc = MCMC(NUTS(model, dense_mass=dense), num_warmup=warmup, num_samples=draws,
              num_chains=chains, chain_method="sequential", progress_bar=False)
    mc.run(random.PRNGKey(seed))
    sec = time.perf_counter() - t0
    return flatten_sites(mc.get_samples(group_by_chain=True)), sec


def raw_cols(post) -> dict[str, np.ndarray]:
    """The sampler's own sites of a solderpyro posterior, named as on the NumPyro side."""
    return flatten_sites(post.raw)


def _row(post) -> dict:
    mn, eps = ess_per_s(raw_cols(post), post.seconds)
    return dict(min_ess=mn, ess_per_s=eps, seconds=post.seconds,
                divergences=sum(post.divergences))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--chains", type=int, default=4)
    ap.add_argument("--warmup", type=int, default=500)
    ap.add_argument("--draws", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-numpyro", action="store_true")
    ap.add_argument("--no-pyro", action="store_true", help="skip the (slow) Pyro sampler")
    ap.add_argument("--out", default="benchmarks/results_koh.json")
    a = ap.parse_args()
    nuts = dict(chains=a.chains, warmup=a.warmup, draws=a.draws, seed=a.seed, progress=False)
    res: dict = {"machine": platform.processor() or platform.machine(),
                 "chains": a.chains, "warmup": a.warmup, "draws": a.draws}
    x, y = make_data(0)
    pr_d = Priors(sigma_max=5.0)
    data = joint_data()
    pr_j = Priors(sigma_max=1.0, sigma_c_max=10.0 * float(data.y_sim.std()))
    for sampler in ("fast",) + (() if a.no_pyro else ("pyro",)):
        post, _ = calibrate_direct(code, x, y, T_BOX, pr_d, sampler=sampler, **nuts)
        res[f"direct_{sampler}"] = _row(post)
        post, _ = calibrate_joint(data, pr_j, sampler=sampler, **nuts)
        res[f"joint_{sampler}"] = _row(post)
        q = {r["parameter"]: (r["q2.5"], r["q97.5"]) for r in post.summary()}
        res[f"joint_{sampler}_truth_in_95"] = {k: bool(q[k][0] <= float(v) <= q[k][1])
                                               for k, v in zip(J_BOX.names, J_TRUE,
                                                               strict=True)}
    if not a.no_numpyro:
        cols, sec = numpyro_direct(X_OBS, y, 5.0, a.chains, a.warmup, a.draws, a.seed)
        res["direct_numpyro"] = dict(zip(("min_ess", "ess_per_s"), ess_per_s(cols, sec),
                                         strict=True), seconds=sec)
        for dense in (False, True):
            cols, sec = numpyro_joint(prepare_joint(data), pr_j, a.chains, a.warmup, a.draws,
                                      a.seed, dense)
            res[f"joint_numpyro_{'dense' if dense else 'diag'}"] = dict(
                zip(("min_ess", "ess_per_s"), ess_per_s(cols, sec), strict=True), seconds=sec)
        res["joint_numpyro"] = max(res["joint_numpyro_diag"], res["joint_numpyro_dense"],
                                   key=lambda r: r["ess_per_s"])
        for case in ("direct", "joint"):
            for sampler in ("fast", "pyro"):
                if f"{case}_{sampler}" in res:
                    res[f"{case}_ratio_{sampler}_over_numpyro"] = (
                        res[f"{case}_{sampler}"]["ess_per_s"] / res[f"{case}_numpyro"]["ess_per_s"])
    print(json.dumps(res, indent=2))
    with open(a.out, "w") as f:
        json.dump(res, f, indent=2)


if __name__ == "__main__":
    torch.set_num_threads(1)
    main()
