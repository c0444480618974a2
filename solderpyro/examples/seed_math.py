"""The seed paper's mathematical example (Section 3, after Loeppky et al. 2006).

True process y = 1.5 + 3.5 exp(-1.7 x) on x = 0, 0.3, ..., 3, observed with N(0, 0.36) noise;
computer model y_c = 5 exp(-t x). Reproduces:

- the log-linear regression (Eq. 16-17) and its t, sigma;
- Table I / Figures 1-2: direct calibration of (t, sigma), flat priors;
- Table II / Figures 3-4: full-joint KOH calibration from 5 LHS runs of the code in (x, t),
  sampling t, sigma, beta, sigma_c and theta.

How to read the comparison with the seed: the noise draw differs from the seed's, so the
numbers differ draw to draw by about their posterior spread. What must agree is the structure:
the regression t is lower than the Bayesian t (log-transform bias), sigma absorbs the model
error, and the 5-run surrogate posterior of t is wider than the direct one (code uncertainty).
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.stats import qmc

from solderpyro.calibration import (
    CalibrationData,
    Posterior,
    Priors,
    calibrate_direct,
    calibrate_joint,
    predict_joint,
    predict_observation_model,
)
from solderpyro.calibration.data import InputAxes
from solderpyro.calibration.mcmc import format_summary, write_summary
from solderpyro.params import Box

log = logging.getLogger("solderpyro")
DT = torch.float64
X_OBS = torch.arange(11, dtype=DT)[:, None] * 0.3  # (11, 1)
NOISE_SD = 0.6  # variance 0.36
T_BOX = Box(("t",), (-1.0,), (3.0,))  #: flat prior on t, wide enough not to bind
X_BOX = Box(("x",), (0.0,), (3.0,))
LHS_T = Box(("t",), (-0.5,), (2.5,))  #: LHS box and t prior (Table II)
SIGMA_MAX = 5.0  #: flat prior on sigma over (0, 5)

SEED_REGRESSION = {"t": 0.5293, "sigma": 0.3270}
SEED_TABLE1 = {"t": (0.4781, 0.6557, 0.9147), "sigma": (0.4542, 0.6855, 1.1284)}
SEED_TABLE2 = {"t": (-0.0735, 0.2414, 0.5308), "sigma": (0.3739, 0.5594, 0.8616),
               "beta": (1.8070, 1.8070, 1.8088), "sigma_c": (1.9055, 1.9196, 1.9198),
               "theta": (0.3110, 0.4731, 0.6968)}


def true_process(x: torch.Tensor) -> torch.Tensor:
    """Seed Eq. 14: ``(n,)`` -> ``(n,)``."""
    return 1.5 + 3.5 * torch.exp(-1.7 * x)


def code(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Seed Eq. 15: ``x (n, 1)``, ``t (1,)`` -> ``(n,)``."""
    return 5.0 * torch.exp(-t[0] * x[:, 0])


def make_data(seed: int, true_fn=true_process) -> tuple[torch.Tensor, torch.Tensor]:
    """Observations: ``x (11, 1)``, ``y (11,)`` with N(0, 0.6^2) noise from ``seed``."""
    g = torch.Generator().manual_seed(seed)
    y = true_fn(X_OBS[:, 0]) + NOISE_SD * torch.randn(11, generator=g, dtype=DT)
    return X_OBS.clone(), y


def regression(x: torch.Tensor, y: torch.Tensor) -> tuple[float, float]:
    """Seed Eq. 16-17: least squares of w = log(y / 5) on x through the origin.

    Observations with y <= 0 (the log is undefined) are dropped with a warning.

    Returns:
        t = -beta and sigma (the regression's, on the log scale, n - 1 denominator).
    """
    keep = y > 0
    if not bool(keep.all()):
        warnings.warn(f"regression drops {int((~keep).sum())} observations with y <= 0",
                      stacklevel=2)
    f, w = x[keep, 0], torch.log(y[keep] / 5.0)
    beta = (f @ w) / (f @ f)
    s2 = ((f * beta - w).square().sum() / (f.shape[0] - 1)).item()
    return -beta.item(), s2**0.5


def lhs_runs(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``n`` LHS runs of the code over (x, t): ``x (n, 1)``, ``t (n, 1)``, ``y (n,)``."""
    u = torch.as_tensor(qmc.LatinHypercube(d=2, seed=seed).random(n), dtype=DT)
    xs, ts = X_BOX.from_unit(u[:, :1]), LHS_T.from_unit(u[:, 1:])
    ys = torch.stack([code(xs[i:i + 1], ts[i])[0] for i in range(n)])
    return xs, ts, ys


@dataclass
class SeedMathResult:
    """Everything :func:`run` computed (tables as summary rows)."""

    x: torch.Tensor
    y: torch.Tensor
    regression: tuple[float, float]
    direct: Posterior
    joint: Posterior
    table1: list[dict]
    table2: list[dict]


def run(out: str | Path, seed: int = 0, chains: int = 4, warmup: int = 500, draws: int = 1000,
        n_lhs: int = 5, progress: bool = True) -> SeedMathResult:
    """Run the whole example and write data, tables and figures into ``out``.

    Writes ``data.csv`` (x, y), ``regression.csv`` (t, sigma), ``table1.csv`` and ``table2.csv``
    (parameter, q2.5, median, q97.5), ``posterior_direct.nc``, ``posterior_joint.nc`` and
    ``fig1_direct.png`` ... ``fig4_joint_predictive.png``.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    x, y = make_data(seed)
    np.savetxt(out / "data.csv", np.c_[x[:, 0].numpy(), y.numpy()], delimiter=",",
               header="x,y", comments="", fmt="%.10g")
    t_reg, s_reg = regression(x, y)
    (out / "regression.csv").write_text(f"t,sigma\n{t_reg:.10g},{s_reg:.10g}\n")
    nuts: dict[str, Any] = dict(chains=chains, warmup=warmup, draws=draws, seed=seed,
                                progress=progress)
    log.info("Table I: direct calibration of t, sigma (%d chains x %d draws)", chains, draws)
    direct, d_inp = calibrate_direct(code, x, y, T_BOX, Priors(sigma_max=SIGMA_MAX), **nuts)
    table1 = [r for r in direct.summary() if r["parameter"] in SEED_TABLE1]
    write_summary(table1, out / "table1.csv", ("parameter", "q2.5", "median", "q97.5"))
    direct.save(out / "posterior_direct.nc")
    log.info("Table II: full-joint KOH from %d LHS runs", n_lhs)
    xs, ts, ys = lhs_runs(n_lhs, seed)
    data = CalibrationData.create(xs, ts, ys, x, y,
                                  InputAxes(["x"], ["t"], theta_box=LHS_T, x_box=X_BOX))
    joint, j_inp = calibrate_joint(data, Priors(sigma_max=SIGMA_MAX), **nuts)
    rows = {r["parameter"]: r for r in joint.summary()}
    # Eq. 4's theta is sampled on the unit cube; x and t both span 3, so on the seed's raw
    # inputs theta_raw = theta_unit / 3^2.
    rows["theta"] = {**rows["theta"], **{k: float(rows["theta"][k]) / 9.0
                                         for k in ("q2.5", "median", "mean", "q97.5")}}
    table2 = [rows[k] for k in SEED_TABLE2]
    write_summary(table2, out / "table2.csv", ("parameter", "q2.5", "median", "q97.5"))
    joint.save(out / "posterior_joint.nc")
    xg = torch.linspace(0, 3, 61, dtype=DT)[:, None]
    bands_d = predict_observation_model(direct, d_inp, xg, seed=seed)
    bands_j = predict_joint(joint, j_inp, xg, seed=seed)
    from solderpyro.examples import seed_math_plots as P

    P.fig1(out / "fig1_direct.png", x, y, xg, bands_d, t_reg, true_process)
    P.fig2(out / "fig2_direct_posterior.png", direct)
    P.fig3(out / "fig3_surrogate.png", xs, ts, ys, data, joint, j_inp, code)
    P.fig4(out / "fig4_joint_predictive.png", x, y, xg, bands_j, true_process)
    return SeedMathResult(x, y, (t_reg, s_reg), direct, joint, table1, table2)


def report(res: SeedMathResult) -> str:
    """The tables beside the seed's numbers, as text."""
    lines = [f"Regression (Eq. 16-17): t = {res.regression[0]:.4f}, sigma = "
             f"{res.regression[1]:.4f}   (seed: t = {SEED_REGRESSION['t']}, sigma = "
             f"{SEED_REGRESSION['sigma']})", ""]
    for title, rows, seed in (("Table I (direct)", res.table1, SEED_TABLE1),
                              ("Table II (full joint, 5 LHS runs)", res.table2, SEED_TABLE2)):
        lines.append(f"{title}:  ours 2.5% / median / 97.5%   |   seed")
        for r in rows:
            s = seed[str(r["parameter"])]
            lines.append(f"  {r['parameter']:<8} {float(r['q2.5']):8.4f} {float(r['median']):8.4f}"
                         f" {float(r['q97.5']):8.4f}   | {s[0]:8.4f} {s[1]:8.4f} {s[2]:8.4f}")
        lines.append("")
    lines.append("Sampler diagnostics (joint):")
    lines.append(format_summary(res.joint.summary()))
    lines.append(f"divergences per chain: direct {res.direct.divergences}, joint "
                 f"{res.joint.divergences}")
    lines.append("")
    lines.append("Reading: the noise draw differs from the seed's, so each number may move by "
                 "about its posterior spread. Compare the structure: the regression t lies below "
                 "the Bayesian medians (the log transform), sigma is well above the true 0.6 "
                 "when it absorbs the model error (5 exp(-t x) decays to 0, the truth to 1.5), "
                 "and the 5-run surrogate interval of t is wider than the direct one (code "
                 "uncertainty). The seed's near-constant beta and sigma_c intervals are not "
                 "reproduced: with 5 runs these are poorly identified and their posteriors are "
                 "wide here. theta is reported on the seed's raw inputs (unit-cube theta / 9).")
    return "\n".join(lines)
