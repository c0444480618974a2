"""One call per calibration mode: build the Pyro model, run NUTS, return a :class:`Posterior`.

- :func:`calibrate_direct`: the computer model inside the likelihood (no surrogate).
- :func:`calibrate_modular`: a fitted GP, hyperparameters fixed, code uncertainty propagated.
- :func:`calibrate_joint`: the seed's full joint over runs and observations (Eq. 5-8).

NUTS runs through :func:`~solderpyro.calibration.mcmc.run_nuts`, the one sampler: Stan's NUTS
in NumPy (:mod:`~solderpyro.calibration.nuts`) on an analytic log density and gradient where
one exists (direct and full joint: :mod:`~solderpyro.calibration.fastkoh`; modular PCA: the
reduced likelihood of :mod:`~solderpyro.calibration.reduced`), else on Pyro's potential of the
model with autograd; chains run in parallel processes; keywords such as ``chains``,
``warmup``, ``draws``, ``full_mass``, ``workers`` and ``warm`` are passed on to it.

Each returns draws in physical units: ``t`` ``(chain, draw, n_theta)`` labelled with the theta
box's names, ``sigma``, and for the joint mode ``beta`` (output units), ``sigma_c`` and ``corr``
(Eq. 4's theta on the unit cube); ``sigma_delta``/``corr_delta`` with a discrepancy.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from solderpyro.calibration.data import CalibrationData, check_tensor
from solderpyro.calibration.emulators import FunctionEmulator, GPEmulator
from solderpyro.calibration.koh import (
    SITE_CORR,
    SITE_SIGMA,
    SITE_SIGMA_C,
    SITE_T,
    JointInputs,
    ObsInputs,
    Priors,
    discrepancy_cov,
    joint_loglik,
    joint_model,
    observation_model,
    prepare_joint,
    prepare_observation,
)
from solderpyro.calibration.kronjoint import kron_joint
from solderpyro.calibration.mcmc import NutsOptions, NutsRun, Posterior, run_nuts
from solderpyro.params import Box
from solderpyro.surrogate import GPSurrogate


def _post(run: NutsRun, box: Box) -> Posterior:
    samples = run.samples
    out = {"t": box.from_unit(samples[SITE_T])}
    out.update({k: v for k, v in samples.items() if k != SITE_T})
    return Posterior(out, {"t": list(box.names)}, run.divergences, run.seconds, dict(samples),
                     warm=run.warm, stats=run.stats, diverging=run.diverging,
                     sample_stats=run.sample_stats)


def calibrate_direct(f: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
                     x_obs: torch.Tensor, y_obs: torch.Tensor, theta_box: Box,
                     priors: Priors | None = None, discrepancy: bool = False,
                     x_box: Box | None = None, **nuts: Any) -> tuple[Posterior, ObsInputs]:
    """Calibrate ``f(x (n, n_x), t (n_theta,)) -> (n,)`` directly against ``y_obs (n_obs,)``.

    Args:
        x_obs: ``(n_obs, n_x)``; theta_box: calibration parameters and their flat-prior box.
        nuts: passed to :func:`~solderpyro.calibration.mcmc.run_nuts` (without a discrepancy
            and with the default priors the gradient is analytic: one torch backward pass
            through ``f`` per gradient).

    Returns:
        the posterior and the model inputs (for :func:`predict_observation_model`).
    """
    check_tensor("x_obs", x_obs, 2)
    inp = prepare_observation(y_obs, FunctionEmulator(f, x_obs), theta_box, x_obs, x_box,
                              discrepancy)
    return _run_obs(inp, priors, nuts), inp


def calibrate_modular(gp: GPSurrogate, y_obs: torch.Tensor, theta_box: Box,
                      x_obs: torch.Tensor | None = None, priors: Priors | None = None,
                      discrepancy: bool = False, x_box: Box | None = None,
                      **nuts: Any) -> tuple[Posterior, ObsInputs]:
    """Calibrate through a fitted GP (hyperparameters fixed at their ML optimum).

    Args:
        gp: fitted on inputs ``(x, t)`` (scalar layout, give ``x_obs (n_obs, n_x)``) or on
            ``t`` alone with outputs matching ``y_obs`` (batched/pca layout, ``x_obs=None``).
        y_obs: ``(n_obs,)``; theta_box: the flat-prior box of t (physical units).

    NUTS adapts a dense mass matrix when there are several calibration parameters (the Anand
    constants are strongly correlated: 2.3x faster on the specimen) unless ``full_mass=False``.
    """
    inp = prepare_observation(y_obs, GPEmulator(gp, x_obs), theta_box, x_obs, x_box,
                              discrepancy)
    nuts.setdefault("full_mass", theta_box.dim > 1)  # measured 2.3x faster on the specimen
    return _run_obs(inp, priors, nuts), inp


def calibrate_emulator(emulator: Any, y_obs: torch.Tensor, theta_box: Box,
                       priors: Priors | None = None, **nuts: Any
                       ) -> tuple[Posterior, ObsInputs]:
    """Modular calibration through any emulator ``t (n_theta,) -> (mean (n_obs,), cov)`` (e.g.
    a :class:`~solderpyro.calibration.emulators.ObservedEmulator`); as
    :func:`calibrate_modular` otherwise."""
    inp = prepare_observation(y_obs, emulator, theta_box)
    nuts.setdefault("full_mass", theta_box.dim > 1)
    return _run_obs(inp, priors, nuts), inp


def _run_obs(inp: ObsInputs, priors: Priors | None, nuts: dict) -> Posterior:
    return _post(run_nuts(observation_model, (inp, priors or Priors()), NutsOptions(**nuts)),
                 inp.theta_box)


def calibrate_joint(data: CalibrationData, priors: Priors | None = None,
                    kernel: str = "gaussian", mean: str = "constant", ard: bool = False,
                    discrepancy: bool = False, nugget: float = 1e-6,
                    **nuts: Any) -> tuple[Posterior, JointInputs]:
    """The seed's full joint KOH calibration (t, sigma, beta, sigma_c, theta sampled together).

    NUTS adapts a dense mass matrix here unless ``full_mass=False`` is passed; the log density
    is analytic for the Gaussian kernel, a constant mean, no discrepancy and the default
    priors, else Pyro's potential with autograd (:func:`~.mcmc.run_nuts`).

    Returns:
        the posterior (beta drawn from its exact Gaussian conditional per draw, output units)
        and the model inputs (for :func:`predict_joint`).
    """
    pr = priors or Priors()
    inp = prepare_joint(data, kernel, mean, ard, discrepancy, nugget)
    nuts.setdefault("full_mass", True)  # sigma_c, theta and t are strongly correlated
    post = _post(run_nuts(joint_model, (inp, pr), NutsOptions(**nuts)), data.theta_box)
    post.samples["beta"] = _beta_draws(inp, post, pr, seed=int(nuts.get("seed", 0)))
    names = list(data.x_box.names) + list(data.theta_box.names)
    post.labels[SITE_CORR] = [f"theta_{n}" for n in names] if ard else ["theta"]
    post.labels["beta"] = ["beta"] if mean == "constant" else \
        ["beta_0"] + [f"beta_{n}" for n in names]
    return post, inp


def _beta_draws(inp: JointInputs, post: Posterior, pr: Priors, seed: int) -> torch.Tensor:
    """beta | rest ~ N(beta_hat, (F' S^-1 F)^-1) per draw, mapped to output units."""
    gen = torch.Generator().manual_seed(seed)
    raw = {k: v.reshape(-1, *v.shape[2:]) for k, v in post.raw.items()}
    n = raw[SITE_T].shape[0]
    kron = kron_joint(inp)  # a product design: beta's moments without the dense Cholesky
    out = []
    for i in range(n):
        with torch.no_grad():
            if kron is not None:
                x = torch.cat([raw[SITE_T][i], raw[SITE_SIGMA][i].reshape(1),
                               raw[SITE_SIGMA_C][i].reshape(1), raw[SITE_CORR][i]])
                bm, bv = kron.beta(x.double().numpy())
                bh = torch.tensor([bm], dtype=raw[SITE_T].dtype)
                bc = torch.tensor([[bv]], dtype=raw[SITE_T].dtype)
            else:
                k_delta = None
                if inp.discrepancy:
                    from pyro import condition
                    cond = condition(discrepancy_cov, data={k: raw[k][i] for k in
                                                       ("sigma_delta", "corr_delta")})
                    k_delta = cond(pr, inp.u_xobs, 1.0)
                _, bh, bc = joint_loglik(inp, raw[SITE_T][i], raw[SITE_SIGMA][i],
                                         raw[SITE_SIGMA_C][i], raw[SITE_CORR][i], k_delta)
            lc = torch.linalg.cholesky(bc)
            b = bh + lc @ torch.randn(bh.shape, generator=gen, dtype=bh.dtype)
        b = b * inp.y_scale
        b[0] = b[0] + inp.y_mean
        out.append(b)
    c, dr = post.raw[SITE_T].shape[:2]
    return torch.stack(out).reshape(c, dr, -1)
