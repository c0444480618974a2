"""NUTS efficiency of solderpyro's calibrations against NumPyro, same posterior side by side.

Usage: python benchmarks/bench_koh.py [--cases direct,joint,field_modular,joint_400,joint_400_grid]
       [--chains 4] [--warmup 500] [--draws 1000] [--seed 0]
       [--numpyro-mass both|diag|dense] [--workers 1] [--no-numpyro]
       [--out benchmarks/results/bench_koh.json]

Cases (identical data, priors, site transforms and likelihood on both sides):
- direct: the seed's mathematical example, t and sigma (Table I's posterior);
- joint: the full-joint KOH posterior (seed Eq. 5-8, beta integrated out analytically on both
  sides) with m = 50 LHS runs, n = 8 observations and 4 calibration parameters of
  y = t1 exp(-t2 x) + t3 sin(pi t4 x), x in [0, 1];
- field_modular: a full-field modular calibration of the specimen (s0, QR, xi, m on the seed
  box): the FE's V at the 4 seed times, A, B and the 558 grid points (2,240 observed values)
  at Liu's constants plus N(0, 0.05^2) um noise, through a PCA GP (Matern 5/2, ARD,
  FlowStressInputs) fitted on a 50-run LHS through the FE; sigma ~ LogNormal(log 0.05, 0.1)
  (Priors(sigma_known=0.05)), likelihood y ~ N(mean(t), F F^T + diag(d + sigma^2)). NumPyro
  side: the GP's predictive mean and low-rank covariance at t ported to JAX (checked against
  torch's ``GPSurrogate.mean_lowrank`` to 1e-10 before timing) and
  ``numpyro.distributions.LowRankMultivariateNormal`` on all 2,240 values;
- joint_400: the full-joint KOH posterior with 400 simulator runs and 12 observations of a
  ball-drop simulator (as SEPIA's ball-drop example): fall time from height h (x, 5-100 m)
  under gravity and quadratic drag dv/dt = g - C v^2 (C, the calibration parameter,
  0.05-0.5 1/m), closed form t = acosh(exp(C h)) / sqrt(g C); runs: a 400-point LHS over
  (h, C); observations: 12 heights, C = 0.2, noise sd 1 % of each fall time, no discrepancy.
  The runs are no product design, so solderpyro's gradient is the dense 412 x 412 Cholesky.
- joint_400_grid: the same model and observations with the runs as SEPIA's ball drop makes
  them: 20 drag coefficients (a 1-D Latin hypercube) each read at the same 20 heights (a 1-D
  Latin hypercube), 400 runs. solderpyro's likelihood is then the Kronecker form
  (calibration.kronjoint, found from the design, nothing passed); NumPyro's is the dense one.

Every case uses the same chains, warm-up and draws (the command line's). Effective samples per
second = min over the sampler's own sites (unit-cube t, sigma, sigma_c, corr) of ArviZ's bulk
ESS / wall time (warm-up, sampling and JIT compilation included). Both sides run their chains
one after another on one CPU thread (torch threads 1 and, where run_nuts has it, ``workers=1``:
``--workers``; XLA: one host device, no multi-threaded Eigen, one intra-op thread). solderpyro
runs with the mass matrix its calibration functions choose (dense for the joint and for
several modular parameters, diagonal for direct); NumPyro runs with its default diagonal and
with a dense mass matrix (``--numpyro-mass``), and the ratio is taken against the faster. The
2.5/50/97.5 % quantiles of every site are compared between the two sides: they agree when
|q_a - q_b| < 4 sqrt(mcse_a^2 + mcse_b^2) (ArviZ's quantile MCSE); ``agree`` is the median
check, ``agree_tails`` all three; ``converged`` (R-hat < 1.01 on both sides) says whether
the MCSEs, hence the check, can be trusted. The speed ratio is recorded only for a converged
pair: both sides' largest R-hat at most 1.01 and smallest bulk ESS at least 100 per chain
(:func:`speed_ratio`); otherwise the case records ``null`` and says "not converged: no ratio".
NumPyro is the optional `bench` extra (pip install -e .[bench]).
"""

from __future__ import annotations

import argparse
import inspect
import json
import math
import os
import platform
import time
import warnings
from collections.abc import Callable
from typing import Any

os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=1 "
                      "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")
os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")  # one BLAS thread (NumPy, torch) as one XLA one

import numpy as np  # noqa: E402
import torch  # noqa: E402
from scipy.stats import qmc  # noqa: E402

from solderpyro.calibration import (  # noqa: E402
    CalibrationData,
    Priors,
    calibrate_direct,
    calibrate_joint,
    calibrate_modular,
)
from solderpyro.calibration.data import InputAxes  # noqa: E402
from solderpyro.calibration.koh import prepare_joint  # noqa: E402
from solderpyro.calibration.kronjoint import kron_joint  # noqa: E402
from solderpyro.calibration.mcmc import NutsOptions, flatten_sites  # noqa: E402
from solderpyro.examples.seed_math import X_OBS, code, make_data  # noqa: E402
from solderpyro.params import Box  # noqa: E402

DT = torch.float64
CASES = ("direct", "joint", "field_modular", "joint_400", "joint_400_grid")
QS = (0.025, 0.5, 0.975)
T_BOX = Box(("t",), (0.0,), (2.0,))
J_BOX = Box(("t1", "t2", "t3", "t4"), (0.5, 0.5, 0.0, 0.5), (1.5, 3.0, 1.0, 2.0))
J_TRUE = torch.tensor([1.0, 1.5, 0.5, 1.2], dtype=DT)
G = 9.81  # m/s^2
H_BOX = Box(("h",), (5.0,), (100.0,))  # drop height, m
C_BOX = Box(("C",), (0.05,), (0.5,))  # quadratic drag coefficient, 1/m
C_TRUE = 0.2
FIELD_SIGMA = 0.05  # um


# ----------------------------------------------------------------------------- data
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
    return CalibrationData.create(xs, ts, ys, xo, yo, InputAxes(
        ["x"], list(J_BOX.names), theta_box=J_BOX, x_box=Box(("x",), (0.0,), (1.0,))))


def fall_time(h: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """Time (s) to fall ``h`` m from rest under dv/dt = g - c v^2 (any broadcastable shapes).

    Distance ln(cosh(sqrt(g c) t)) / c = h, so t = acosh(exp(c h)) / sqrt(g c), with
    acosh(e^a) = a + log(1 + sqrt(1 - e^{-2a})) (no overflow).
    """
    a = c * h
    return (a + torch.log1p(torch.sqrt(-torch.expm1(-2.0 * a)))) / torch.sqrt(G * c)


def _check_fall_time() -> None:
    """The closed form against an ODE solve of the same drag law (once, milliseconds)."""
    from scipy.integrate import solve_ivp

    for h, c in ((5.0, 0.05), (100.0, 0.5), (40.0, 0.2)):
        ev = lambda _t, s, h=h: s[0] - h  # noqa: E731
        ev.terminal = True  # type: ignore[attr-defined]
        sol = solve_ivp(lambda _t, s, c=c: [s[1], G - c * s[1] ** 2], (0.0, 100.0), [0.0, 0.0],
                        events=ev, rtol=1e-11, atol=1e-11)
        t_ode = float(sol.t_events[0][0])
        t_cf = float(fall_time(torch.tensor(h, dtype=DT), torch.tensor(c, dtype=DT)))
        assert abs(t_ode - t_cf) < 1e-6 * t_cf, (h, c, t_ode, t_cf)


def ball_code(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """``x (n, 1)`` heights, ``t (..., 1)`` drag coefficient -> ``(n,)`` fall times."""
    return fall_time(x[:, 0], t[..., 0])


def _ball(xs: torch.Tensor, ts: torch.Tensor, n: int, seed: int) -> CalibrationData:
    """Runs at heights ``xs (m, 1)`` and drag coefficients ``ts (m, 1)``, and ``n``
    observations at evenly spaced heights, C = 0.2, noise sd 1 % of each fall time."""
    _check_fall_time()
    ys = fall_time(xs[:, 0], ts[:, 0])
    xo = torch.linspace(H_BOX.lower[0], H_BOX.upper[0], n, dtype=DT)[:, None]
    g = torch.Generator().manual_seed(seed)
    t_true = fall_time(xo[:, 0], torch.tensor(C_TRUE, dtype=DT))
    yo = t_true * (1.0 + 0.01 * torch.randn(n, generator=g, dtype=DT))
    return CalibrationData.create(xs, ts, ys, xo, yo,
                                  InputAxes(["h"], ["C"], theta_box=C_BOX, x_box=H_BOX))


def ball_data(m: int = 400, n: int = 12, seed: int = 0) -> CalibrationData:
    """The ball drop on a 2-D Latin hypercube over (h, C): no product structure."""
    u = torch.as_tensor(qmc.LatinHypercube(d=2, seed=seed).random(m), dtype=DT)
    return _ball(H_BOX.from_unit(u[:, :1]), C_BOX.from_unit(u[:, 1:]), n, seed)


def ball_grid_data(m_c: int = 20, m_h: int = 20, n: int = 12, seed: int = 0) -> CalibrationData:
    """ball_data's model and observations on a product design: ``m_c`` drag coefficients, each
    run read at the same ``m_h`` heights (both 1-D Latin hypercubes), ``m_c m_h`` runs."""
    uc = torch.as_tensor(qmc.LatinHypercube(d=1, seed=seed).random(m_c), dtype=DT)
    uh = torch.as_tensor(qmc.LatinHypercube(d=1, seed=seed + 1).random(m_h), dtype=DT)
    return _ball(H_BOX.from_unit(uh).repeat(m_c, 1),
                 C_BOX.from_unit(uc).repeat_interleave(m_h, 0), n, seed)


def field_setup(seed: int = 0, n_runs: int = 50) -> dict[str, Any]:
    """FE runs (50-run LHS + Liu's constants), the fitted PCA GP and the noisy observations."""
    from solderpyro import ParameterSpace, SpecimenModel
    from solderpyro.design import lhs
    from solderpyro.params import LIU2008
    from solderpyro.surrogate import GPSurrogate
    from solderpyro.surrogate.features import FlowStressInputs

    space = ParameterSpace.seed()
    box = Box(space.names, space.lower, space.upper, space.log_scale, space.units)
    truth = torch.tensor([[LIU2008[k] for k in box.names]], dtype=DT)
    theta = lhs(box, n_runs, seed)
    t0 = time.perf_counter()
    V = SpecimenModel(space=space, field=True)(torch.cat([theta, truth]))  # (n+1, 4, 560)
    fe_s = time.perf_counter() - t0
    y = V.reshape(V.shape[0], -1)
    ok = torch.isfinite(y[:n_runs]).all(-1)
    assert torch.isfinite(y[-1]).all(), "the FE run at the true constants failed"
    t0 = time.perf_counter()
    feats = FlowStressInputs(box, space.defaults)
    gp = GPSurrogate(box, output="pca", kernel="matern52", ard=True, inputs=feats)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gp.fit(theta[ok], y[:n_runs][ok])
    fit_s = time.perf_counter() - t0
    g = torch.Generator().manual_seed(seed)
    y_obs = y[-1] + FIELD_SIGMA * torch.randn(y.shape[1], generator=g, dtype=DT)
    loo = gp.loo()
    return dict(gp=gp, box=box, feats=feats, y_obs=y_obs, truth=truth[0],
                info=dict(n_obs=int(y.shape[1]), n_runs=int(ok.sum()), n_pc=int(gp.basis.shape[1]),
                          fe_seconds=fe_s, gp_fit_seconds=fit_s, loo_rmse_rel=loo.rmse_rel,
                          loo_coverage95=loo.coverage95))


# ----------------------------------------------------------------------------- diagnostics
def _az() -> Any:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        import arviz as az
    return az


def ess_per_s(cols: dict[str, np.ndarray], seconds: float) -> tuple[float, float]:
    az = _az()
    ess = az.ess(az.from_dict(posterior=cols), method="bulk")
    mn = min(float(ess[k]) for k in cols)
    return mn, mn / seconds


def max_rhat(cols: dict[str, np.ndarray]) -> float:
    """Largest rank-normalized R-hat over the sites (the quantile check needs < 1.01)."""
    az = _az()
    rh = az.rhat(az.from_dict(posterior=cols))
    return max(float(rh[k]) for k in cols)


def quantiles(cols: dict[str, np.ndarray]) -> dict[str, dict[str, list[float]]]:
    """Per site: the 2.5/50/97.5 % quantiles and their MCSE (ArviZ)."""
    az = _az()
    idata = az.from_dict(posterior=cols)
    mc = [az.mcse(idata, method="quantile", prob=p) for p in QS]
    return {k: dict(q=[float(v) for v in np.quantile(a.reshape(-1), QS)],
                    mcse=[float(m[k]) for m in mc]) for k, a in cols.items()}


def compare(qa: dict, qb: dict) -> dict[str, Any]:
    """Sites of both sides: quantiles, |difference| / combined MCSE, agreement (< 4)."""
    out: dict[str, Any] = {}
    for k in qa:
        if k not in qb:
            continue
        z = [abs(a - b) / max(math.hypot(ma, mb), 1e-300) for a, b, ma, mb in
             zip(qa[k]["q"], qb[k]["q"], qa[k]["mcse"], qb[k]["mcse"], strict=True)]
        out[k] = dict(solderpyro=qa[k]["q"], numpyro=qb[k]["q"], mcse_solderpyro=qa[k]["mcse"],
                      mcse_numpyro=qb[k]["mcse"], z=z, agree=bool(z[1] < 4.0),
                      agree_tails=bool(max(z) < 4.0))
    return out


# ----------------------------------------------------------------------------- NumPyro side
def numpyro_direct(x, y, sigma_max, chains, warmup, draws, seed, dense=False):
    import jax.numpy as jnp
    import numpyro
    import numpyro.distributions as nd

    xj, yj = jnp.asarray(x[:, 0].numpy()), jnp.asarray(y.numpy())
    lo, hi = T_BOX.lower[0], T_BOX.upper[0]

    def model():
        tu = numpyro.sample("t_unit", nd.Uniform(jnp.zeros(1), 1.0).to_event(1))
        sig = numpyro.sample("sigma", nd.Uniform(0.0, sigma_max))
        numpyro.sample("y", nd.Normal(5 * jnp.exp(-(lo + (hi - lo) * tu[0]) * xj), sig), obs=yj)

    return _run_numpyro(model, chains, warmup, draws, seed, dense)


def numpyro_joint(inp, pr: Priors, chains, warmup, draws, seed, dense=False):
    """Gaussian kernel, one shared correlation parameter, constant mean, no discrepancy."""
    import jax.numpy as jnp
    import jax.scipy.linalg as jsl
    import numpyro
    import numpyro.distributions as nd

    assert inp.kernel == "gaussian" and inp.mean == "constant" and not inp.ard
    assert not inp.discrepancy and pr.sigma_max is not None and pr.sigma_known is None
    u_sim, u_xo = jnp.asarray(inp.u_sim.numpy()), jnp.asarray(inp.u_xobs.numpy())
    z, ys = jnp.asarray(inp.z.numpy()), inp.y_scale
    m, n = u_sim.shape[0], u_xo.shape[0]
    p = inp.data.theta_box.dim
    lo_c, hi_c = pr.corr_range
    sc_max = pr.sigma_c_max or 10 * inp.y_scale

    def model():
        tu = numpyro.sample("t_unit", nd.Uniform(jnp.zeros(p), 1.0).to_event(1))
        sig = numpyro.sample("sigma", nd.Uniform(0.0, pr.sigma_max))
        sc = numpyro.sample("sigma_c", nd.Uniform(0.0, sc_max))
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

    return _run_numpyro(model, chains, warmup, draws, seed, dense)


def jax_lowrank(gp, feats) -> Callable:
    """``t (d,)`` physical -> ``(mean (n_y,), F (n_y, k), d (n_y,))``: GPSurrogate.mean_lowrank
    of a fitted PCA GP (Matern 5/2, constant mean, FlowStressInputs on a linear box) in JAX."""
    import jax.numpy as jnp
    import jax.scipy.linalg as jsl

    f, scaling = gp.factors(), gp.input_scaling
    assert gp.output == "pca" and gp.kernel == "matern52" and f.mean_weights is None
    assert not any(gp.box.log_scale) and scaling is not None
    # w = lengthscale^-2 as torch forms it (GPyTorch keeps the hyperparameters in float32)
    c = {k: jnp.asarray(v.detach().numpy(), dtype=jnp.float64) for k, v in dict(
        u=f.u, chol=f.chol, alpha=f.alpha, os=f.outputscale, w=f.lengthscale.pow(-2),
        c=f.mean_const, basis=gp.basis, mu=gp.std.mean, scale=gp.std.scale,
        resid=gp.resid_var, in_lo=scaling[0], in_span=scaling[1]).items()}
    lo, hi = jnp.asarray(gp.box.lower), jnp.asarray(gp.box.upper)
    i_s0, i_qr, i_xi, i_m = (feats.idx[k] for k in ("s0", "QR", "xi", "m"))
    log_a, log_sh, n_exp = math.log(feats.fixed["A"]), math.log(feats.fixed["s_hat"]), \
        feats.fixed["n"]
    log_rate, t_ref = math.log(feats.rate_ref), feats.T_ref_K
    sv = c["basis"] * c["scale"][:, None]  # (n_y, k)
    d = c["resid"] * c["scale"] ** 2

    def log_asinh_exp(w):
        wp, wn = jnp.maximum(w, 0.0), jnp.minimum(w, 0.0)
        pos = jnp.log(wp + jnp.log1p(jnp.sqrt(1.0 + jnp.exp(-2.0 * wp))))
        neg = jnp.where(wn < -30.0, wn, jnp.log(jnp.arcsinh(jnp.exp(jnp.maximum(wn, -30.0)))))
        return jnp.where(w >= 0, pos, neg)

    def unit(x):
        z = log_rate - log_a + x[i_qr] / t_ref
        common = log_asinh_exp(x[i_m] * z) - jnp.log(x[i_xi])
        f = (x - lo) / (hi - lo)
        f = f.at[i_s0].set(jnp.log(x[i_s0]) + common)
        f = f.at[i_qr].set(log_sh + n_exp * z + common)
        return (f - c["in_lo"]) / c["in_span"]

    def lowrank(x):
        u = unit(x)  # (d,)
        r2 = ((u - c["u"]) ** 2 * c["w"][:, None, :]).sum(-1)  # (k, n)
        s5r = math.sqrt(5.0) * jnp.sqrt(jnp.maximum(r2, 1e-30))
        ks = c["os"][:, None] * (1.0 + s5r + s5r**2 / 3.0) * jnp.exp(-s5r)  # (k, n)
        mc = c["c"] + (ks * c["alpha"]).sum(-1)  # (k,)
        v = jsl.solve_triangular(c["chol"], ks[..., None], lower=True)[..., 0]  # (k, n)
        var = jnp.maximum(c["os"] - (v**2).sum(-1), 0.0)  # (k,)
        mean = c["mu"] + c["scale"] * (c["basis"] @ mc)
        return mean, sv * jnp.sqrt(var), d

    return lowrank


def check_jax_lowrank(gp, lowrank, box: Box, n: int = 5, tol: float = 1e-10) -> float:
    """Max abs difference of the JAX port from torch's mean_lowrank at ``n`` LHS points."""
    import jax
    import jax.numpy as jnp

    from solderpyro.design import lhs

    f = jax.jit(lowrank)
    worst = 0.0
    for t in lhs(box, n, 123):
        with torch.no_grad():
            ref = gp.mean_lowrank(t)
        got = f(jnp.asarray(t.numpy()))
        for a, b in zip(ref, got, strict=True):
            worst = max(worst, float(np.abs(a.numpy() - np.asarray(b)).max()))
    assert worst < tol, f"JAX port of mean_lowrank differs from torch by {worst:.3g}"
    return worst


def numpyro_field(gp, feats, y_obs, box: Box, chains, warmup, draws, seed, dense=False,
                  init_params=None):
    import jax.numpy as jnp
    import numpyro
    import numpyro.distributions as nd

    lowrank = jax_lowrank(gp, feats)
    yj = jnp.asarray(y_obs.numpy())
    lo, hi = jnp.asarray(box.lower), jnp.asarray(box.upper)
    p = box.dim

    def model():
        tu = numpyro.sample("t_unit", nd.Uniform(jnp.zeros(p), 1.0).to_event(1))
        sig = numpyro.sample("sigma", nd.LogNormal(math.log(FIELD_SIGMA), 0.1))
        mean, f, d = lowrank(lo + (hi - lo) * tu)
        numpyro.sample("y", nd.LowRankMultivariateNormal(mean, f, d + sig**2), obs=yj)

    return _run_numpyro(model, chains, warmup, draws, seed, dense, init_params)


def sir_starts(gp, y_obs, box: Box, pr, chains: int, seed: int) -> dict[str, np.ndarray]:
    """The specimen calibration's chain starts (``init="sir"``: likelihood-resampled prior
    draws, the same points solderpyro's run_nuts computes for this seed) on NumPyro's
    unconstrained scale: logit of t_unit, log of sigma, ``(chains, ...)``."""
    from solderpyro.calibration.emulators import GPEmulator
    from solderpyro.calibration.koh import observation_model, prepare_observation
    from solderpyro.calibration.mcmc import sir_inits

    inp = prepare_observation(y_obs, GPEmulator(gp), box)
    pts = sir_inits(observation_model, (inp, pr), chains, 256, seed)
    tu = np.stack([p["t_unit"].numpy() for p in pts])
    return {"t_unit": np.log(tu) - np.log1p(-tu),
            "sigma": np.log(np.array([float(p["sigma"]) for p in pts]))}


def _run_numpyro(model, chains, warmup, draws, seed, dense=False, init_params=None):
    from jax import random
    from numpyro.infer import MCMC, NUTS

    t0 = time.perf_counter()
    mc = MCMC(NUTS(model, dense_mass=dense), num_warmup=warmup, num_samples=draws,
              num_chains=chains, chain_method="sequential", progress_bar=False)
    if init_params is not None:
        import jax.numpy as jnp

        init_params = {k: jnp.asarray(v) for k, v in init_params.items()}
    mc.run(random.PRNGKey(seed), init_params=init_params)
    sec = time.perf_counter() - t0
    div = int(np.asarray(mc.get_extra_fields()["diverging"]).sum())
    return flatten_sites(mc.get_samples(group_by_chain=True)), sec, div


# ----------------------------------------------------------------------------- cases
#: a side's chains count as converged at R-hat <= this (rank-normalized, largest over sites)
MAX_RHAT = 1.01
#: and at least this bulk ESS per chain (smallest over sites): 4 chains need 400
MIN_ESS_PER_CHAIN = 100


def converged(row: dict, chains: int) -> bool:
    """Whether one side's run (a :func:`_row`: ``max_rhat``, ``min_ess``) converged: largest
    R-hat <= :data:`MAX_RHAT` and smallest bulk ESS >= :data:`MIN_ESS_PER_CHAIN` x chains."""
    return bool(row["max_rhat"] <= MAX_RHAT and row["min_ess"] >= MIN_ESS_PER_CHAIN * chains)


def speed_ratio(ours: dict, theirs: dict, chains: int) -> tuple[float | None, str]:
    """solderpyro's ESS per second over NumPyro's, only when both sides converged.

    Args:
        ours, theirs: :func:`_row` of each side (``ess_per_s``, ``max_rhat``, ``min_ess``).
        chains: chains per side.
    Returns:
        ``(ratio, text)``: the ratio and e.g. ``"4.40x"``, or ``(None, "not converged: no ratio
        (...)")`` naming each side's R-hat and ESS.
    """
    if converged(ours, chains) and converged(theirs, chains):
        r = ours["ess_per_s"] / theirs["ess_per_s"]
        return r, f"{r:.2f}x"
    return None, ("not converged: no ratio (R-hat {:.4g} ours, {:.4g} NumPyro's; min bulk ESS "
                  "{:.0f} ours, {:.0f} NumPyro's; needed R-hat <= {} and ESS >= {})").format(
        ours["max_rhat"], theirs["max_rhat"], ours["min_ess"], theirs["min_ess"], MAX_RHAT,
        MIN_ESS_PER_CHAIN * chains)


def _row(cols: dict[str, np.ndarray], seconds: float, divergences: int) -> dict:
    mn, eps = ess_per_s(cols, seconds)
    return dict(min_ess=mn, ess_per_s=eps, seconds=seconds, divergences=divergences,
                max_rhat=max_rhat(cols))


def _solderpyro(calibrate: Callable, *args: Any, **kw: Any) -> tuple[dict, float, int]:
    post, _ = calibrate(*args, **kw)
    return flatten_sites(post.raw), post.seconds, sum(post.divergences)


def build_case(case: str, a: argparse.Namespace, nuts: dict) -> dict[str, Any]:
    """``solderpyro()`` and ``numpyro(dense)`` runners (each -> cols, seconds, divergences),
    the true values of the unit-cube t sites (``truth``) and case information."""
    npk = dict(chains=a.chains, warmup=a.warmup, draws=a.draws, seed=a.seed)
    if case == "direct":
        x, y = make_data(0)
        pr = Priors(sigma_max=5.0)
        return dict(solderpyro=lambda: _solderpyro(calibrate_direct, code, x, y, T_BOX, pr,
                                                   **nuts),
                    numpyro=lambda dense: numpyro_direct(X_OBS, y, 5.0, dense=dense, **npk),
                    truth={}, info=dict(n_obs=int(y.shape[0])))
    if case in ("joint", "joint_400", "joint_400_grid"):
        if case == "joint":
            data, box, truth = joint_data(), J_BOX, J_TRUE
        else:
            data = ball_data() if case == "joint_400" else ball_grid_data()
            box, truth = C_BOX, torch.tensor([C_TRUE], dtype=DT)
        pr = Priors(sigma_max=1.0, sigma_c_max=10.0 * float(data.y_sim.std()))
        inp = prepare_joint(data)
        kron = kron_joint(inp) is not None
        tu = box.to_unit(truth)
        return dict(solderpyro=lambda: _solderpyro(calibrate_joint, data, pr, **nuts),
                    numpyro=lambda dense: numpyro_joint(inp, pr, dense=dense, **npk),
                    truth={f"t_unit[{i}]": float(v) for i, v in enumerate(tu)},
                    info=dict(n_sim=data.n_sim, n_obs=data.n_obs,
                              parameters=list(box.names),
                              solderpyro_likelihood="kronecker" if kron else "dense"))
    if case == "field_modular":
        fs = field_setup(a.seed)
        gp, box, feats, y_obs = fs["gp"], fs["box"], fs["feats"], fs["y_obs"]
        err = None if a.no_numpyro else check_jax_lowrank(gp, jax_lowrank(gp, feats), box)
        pr = Priors(sigma_known=FIELD_SIGMA)
        tu = box.to_unit(fs["truth"])
        starts = None
        if a.init == "sir":  # both sides start where the specimen calibration starts
            starts = sir_starts(gp, y_obs, box, pr, a.chains, a.seed)
        return dict(solderpyro=lambda: _solderpyro(calibrate_modular, gp, y_obs, box,
                                                   priors=pr, init=a.init, **nuts),
                    numpyro=lambda dense: numpyro_field(gp, feats, y_obs, box, dense=dense,
                                                        init_params=starts, **npk),
                    truth={f"t_unit[{i}]": float(v) for i, v in enumerate(tu)},
                    info=dict(fs["info"], jax_port_max_abs_err=err,
                              parameters=list(box.names)))
    raise ValueError(f"unknown case {case!r}; choose from {CASES}")


def run_case(case: str, a: argparse.Namespace, nuts: dict) -> dict[str, Any]:
    c = build_case(case, a, nuts)
    res: dict[str, Any] = {f"{case}_info": c["info"]}
    cols, sec, div = c["solderpyro"]()
    res[f"{case}_solderpyro"] = _row(cols, sec, div)
    q_s = quantiles(cols)
    res[f"{case}_solderpyro_quantiles"] = q_s
    if c["truth"]:
        res[f"{case}_solderpyro_truth_in_95"] = {
            k: bool(q_s[k]["q"][0] <= v <= q_s[k]["q"][2]) for k, v in c["truth"].items()}
    print(json.dumps({f"{case}_solderpyro": res[f"{case}_solderpyro"]}), flush=True)
    if a.no_numpyro:
        return res
    masses = {"both": (False, True), "diag": (False,), "dense": (True,)}[a.numpyro_mass]
    best = None  # the faster NumPyro run, a converged one where there is one
    for dense in masses:
        tag = "dense" if dense else "diag"
        cols_n, sec_n, div_n = c["numpyro"](dense)
        row = _row(cols_n, sec_n, div_n)
        res[f"{case}_numpyro_{tag}"] = row
        cmp = compare(q_s, quantiles(cols_n))
        res[f"{case}_quantiles_vs_numpyro_{tag}"] = cmp
        res[f"{case}_agree_numpyro_{tag}"] = all(v["agree"] for v in cmp.values())
        res[f"{case}_agree_tails_numpyro_{tag}"] = all(v["agree_tails"] for v in cmp.values())
        print(json.dumps({f"{case}_numpyro_{tag}": row,
                          "agree": res[f"{case}_agree_numpyro_{tag}"]}), flush=True)
        key = (converged(row, a.chains), row["ess_per_s"])
        if best is None or key > (converged(best[1], a.chains), best[1]["ess_per_s"]):
            best = (tag, row)
    assert best is not None
    ours = res[f"{case}_solderpyro"]
    res[f"{case}_numpyro"] = dict(best[1], mass=best[0])
    ratio, text = speed_ratio(ours, best[1], a.chains)
    res[f"{case}_ratio_solderpyro_over_numpyro"] = ratio
    res[f"{case}_ratio"] = text
    res[f"{case}_agree"] = res[f"{case}_agree_numpyro_{best[0]}"]
    # MCSEs (hence the agreement check) mean something only for converged chains
    res[f"{case}_converged"] = converged(ours, a.chains) and converged(best[1], a.chains)
    print(f"{case}: solderpyro over NumPyro in ESS per second: {text}", flush=True)
    return res


def sampler_label() -> str:
    """Which NUTS solderpyro's calibrations use by default (read, never passed)."""
    p = inspect.signature(NutsOptions).parameters.get("sampler")
    return f"run_nuts default sampler={p.default!r}" if p is not None else "run_nuts (one sampler)"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", default=",".join(CASES),
                    help=f"comma-separated subset of {', '.join(CASES)}")
    ap.add_argument("--chains", type=int, default=4)
    ap.add_argument("--warmup", type=int, default=500)
    ap.add_argument("--draws", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--init", default="uniform", choices=("uniform", "sir"),
                    help="field_modular: chain starts on both sides (sir: the specimen "
                    "calibration's likelihood-resampled prior draws, identical on both sides)")
    ap.add_argument("--numpyro-mass", choices=("both", "diag", "dense"), default="both",
                    help="NumPyro's mass matrix (both: run each, compare with the faster)")
    ap.add_argument("--workers", type=int, default=1,
                    help="solderpyro's chain processes where run_nuts has workers= (default 1: "
                         "one thread, as NumPyro's sequential chains)")
    ap.add_argument("--no-numpyro", action="store_true")
    ap.add_argument("--out", default="benchmarks/results/bench_koh.json")
    a = ap.parse_args()
    cases = [c.strip() for c in a.cases.split(",") if c.strip()]
    bad = [c for c in cases if c not in CASES]
    if bad:
        ap.error(f"unknown case(s) {bad}; choose from {', '.join(CASES)}")
    nuts: dict[str, Any] = dict(chains=a.chains, warmup=a.warmup, draws=a.draws, seed=a.seed)
    params = inspect.signature(NutsOptions).parameters
    if "progress" in params:
        nuts["progress"] = False
    if "workers" in params:  # chains in forked processes: one here, as NumPyro's one thread
        nuts["workers"] = a.workers
    res: dict[str, Any] = {"machine": platform.processor() or platform.machine(),
                           "chains": a.chains, "warmup": a.warmup, "draws": a.draws,
                           "seed": a.seed, "cases": cases, "solderpyro_sampler": sampler_label(),
                           "solderpyro_workers": nuts.get("workers", 1),
                           "torch": torch.__version__, "torch_threads": torch.get_num_threads(),
                           "xla_flags": os.environ.get("XLA_FLAGS", "")}
    if not a.no_numpyro:
        import jax
        import numpyro

        res.update(numpyro=numpyro.__version__, jax=jax.__version__)
    for case in cases:
        res.update(run_case(case, a, nuts))
        with open(a.out, "w") as f:  # after every case: a long run keeps what it measured
            json.dump(res, f, indent=2)
    summary = {c: {k: res.get(f"{c}_{k}") for k in ("ratio", "agree", "converged")}
               for c in cases}
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    torch.set_num_threads(1)
    main()
