"""Stage 7, the outputs: what a calibration leaves in its run directory.

``summary.csv``, ``draws.npz``, ``data.csv``, the run's record (what ``solderpyro diagnose``
needs to rebuild the model; :class:`~solderpyro.config.rundir.RunDir`), ``posterior.nc``, the
sampler's state, the figures and ``report.md``/``report.html``. Written after the surrogate
posterior, and again after the FE-exact step, so that nothing computed is lost if a later
step fails.

``posterior.nc``'s ``log_likelihood`` group holds, per kept draw, the leave-one-out predictive
log density ``log p(y_i | y_-i, theta)`` of each observation under the sampled likelihood
``y ~ N(mu(theta), C(theta))`` (:func:`log_likelihoods`): the KOH likelihood is one
correlated normal (the surrogate's code covariance couples the observations), so its pointwise
terms are the non-factorized ones of Buerkner, Gabry & Vehtari (2021, "Efficient leave-one-out
cross-validation for Bayesian non-factorized normal and Student-t models", Comput. Stat. 36),
with which ArviZ's PSIS-LOO (``az.loo``) estimates the exact LOO of the correlated model:

    log p(y_i | y_-i) = -log(2 pi) / 2 + log(gbar_ii) / 2 - g_i^2 / (2 gbar_ii),
    g = C^-1 (y - mu),  gbar_ii = [C^-1]_ii.

For a PCA surrogate ``C = F F^T + diag(d + sigma^2)`` (``F (n_obs, k)``) and ``C^-1`` comes from
Woodbury in O(n_obs k^2) per draw (a full field of 2,240 values and 20 components: 13 ms per
draw on one shared core, 1,000 draws in ~13 s; the dense route took 10.9 s per draw), so every
kept draw is used for fields too; a dense ``C`` (no PCA) costs one Cholesky factor per draw,
as the predictive's own draws (an eigendecomposition each) already do.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from solderpyro.calibration.koh import (
    SITE_CORR_D,
    SITE_SIGMA,
    SITE_SIGMA_D,
    SITE_T,
    emulator_lowrank,
    observation_covariance,
)
from solderpyro.calibration.mcmc import Posterior, WarmStart
from solderpyro.config.rundir import Draws, RunDir, RunInfo
from solderpyro.io.measurements import Measurements
from solderpyro.surrogate import LooResult, gaussian

_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)


@dataclass
class SpecimenCalibration:
    """What :func:`~solderpyro.pipeline.calibrate_specimen` produced (files are in ``out``).

    Attributes:
        out: the run directory. posterior: the surrogate posterior (NUTS). summary: the
            reported rows (the FE-exact posterior's when that ran and is reliable). loo: the
            surrogate's leave-one-out check. n_runs_ok, n_runs_failed: FE runs of the design.
        design: the adaptive design's record (why it stopped, its rounds).
    """

    out: Path
    posterior: Posterior
    summary: list[dict]
    loo: LooResult
    n_runs_ok: int
    n_runs_failed: int
    design: dict[str, Any] | None = None


def posterior_draws(post: Posterior, bands: Any, names: Sequence[str], y_obs: torch.Tensor,
                    y_liu: torch.Tensor,
                    draws: tuple[np.ndarray, np.ndarray] | None = None) -> Draws:
    """``draws.npz`` of a run (:class:`~solderpyro.config.rundir.Draws`): flat posterior draws
    ``theta (n, dim)`` in physical units with ``names``, ``sigma (n,)`` in um, the predictive
    ``process (n_pred, n_obs)`` and ``observed (n_pred, n_obs)`` draws with their noise
    ``sigma_pred (n_pred,)``, ``y_obs (n_obs,)`` and the Liu-constants model ``y_liu
    (n_obs,)``, all in um.

    Args:
        post: the surrogate posterior (NUTS). bands: its predictive
            (:func:`~solderpyro.calibration.predictive.predict_observation_model`).
        names: the parameter box's names (``dim``).
        draws: ``(theta (n, dim), sigma (n,))`` to save instead of ``post``'s (the FE-exact
            posterior's resampled draws, or the FE's best fit's).
    """
    theta, sigma = draws if draws is not None else (post.flat("t").numpy(),
                                                     post.flat("sigma").numpy())
    sig_pred = (bands.sigma if bands.sigma is not None
                else torch.full((bands.draws.shape[0],), float("nan")))
    return Draws(theta=np.asarray(theta), sigma=np.asarray(sigma), names=list(names),
                 process=bands.draws.numpy(), observed=bands.obs_draws.numpy(),
                 y_obs=y_obs.numpy(), y_liu=y_liu.numpy(), sigma_pred=sig_pred.numpy())


def save_run(out: Path, meas: Measurements, info: RunInfo, draws: Draws,
             warm: WarmStart | None = None) -> RunDir:
    """Keep what a later ``solderpyro diagnose`` needs in the run directory ``out``:
    ``data.csv`` (the measurements, exact round trip), ``draws.npz`` (``draws``) and the
    run's record ``info`` (:class:`~solderpyro.config.rundir.RunDir`), and the sampler's state
    ``warm`` where there is one (a recalibration can start from it, ``--warm-from``).

    Returns:
        the written :class:`~solderpyro.config.rundir.RunDir`.
    """
    run = RunDir(out, info).write(meas, draws)
    if warm is not None:
        warm.save(run.warm_path)
    return run


def mvn_loo_log_likelihood(y: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor
                           ) -> torch.Tensor:
    """Leave-one-out predictive log densities ``log p(y_i | y_-i)`` of ``y ~ N(mean, cov)``
    (see the module docstring), from ``C^-1`` through a Cholesky factor.

    Args:
        y: ``(n,)`` observations. mean: ``(..., n)``. cov: ``(..., n, n)`` positive definite
            (same units squared).
    Returns:
        ``(..., n)`` nats.
    """
    return mvn_log_likelihoods(y, mean, cov)[0]


def mvn_log_likelihoods(y: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`mvn_loo_log_likelihood` and the joint log density ``log N(y; mean, cov)`` from the
    same Cholesky factor.

    Returns:
        ``(loo (..., n), joint (...))`` nats.
    """
    chol = torch.linalg.cholesky(cov)
    prec = torch.cholesky_inverse(chol)
    r = y - mean
    g = (prec @ r.unsqueeze(-1))[..., 0]
    logdet = 2.0 * torch.log(chol.diagonal(dim1=-2, dim2=-1)).sum(-1)
    return (_loo_terms(g, prec.diagonal(dim1=-2, dim2=-1)),
            _joint(r, g, logdet))


def lowrank_loo_log_likelihood(y: torch.Tensor, mean: torch.Tensor, factor: torch.Tensor,
                               diag: torch.Tensor) -> torch.Tensor:
    """:func:`mvn_loo_log_likelihood` for ``cov = F F^T + diag(d)`` by Woodbury, never forming
    the ``(n, n)`` matrix: ``C^-1 = D^-1 - D^-1 F (I + F^T D^-1 F)^-1 F^T D^-1``.

    Args:
        y: ``(n,)``. mean: ``(..., n)``. factor: ``F (..., n, k)``. diag: ``d (..., n)``,
            positive.
    Returns:
        ``(..., n)`` nats.
    """
    return lowrank_log_likelihoods(y, mean, factor, diag)[0]


def lowrank_log_likelihoods(y: torch.Tensor, mean: torch.Tensor, factor: torch.Tensor,
                            diag: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`lowrank_loo_log_likelihood` and the joint log density, its log-determinant by
    the matrix determinant lemma ``log|C| = sum log d + log|I + F^T D^-1 F|``.

    Returns:
        ``(loo (..., n), joint (...))`` nats.
    """
    dinv = 1.0 / diag
    a = dinv.unsqueeze(-1) * factor  # D^-1 F (..., n, k)
    k = factor.shape[-1]
    inner = torch.eye(k, dtype=factor.dtype, device=factor.device) \
        + factor.transpose(-1, -2) @ a  # (..., k, k)
    lk = torch.linalg.cholesky(inner)
    b = torch.linalg.solve_triangular(lk, a.transpose(-1, -2), upper=False)  # (..., k, n)
    r = y - mean
    g = dinv * r - (b.transpose(-1, -2) @ (b @ r.unsqueeze(-1)))[..., 0]
    logdet = torch.log(diag).sum(-1) + 2.0 * torch.log(lk.diagonal(dim1=-2, dim2=-1)).sum(-1)
    return _loo_terms(g, dinv - b.square().sum(-2)), _joint(r, g, logdet)


def _joint(r: torch.Tensor, g: torch.Tensor, logdet: torch.Tensor) -> torch.Tensor:
    """``log N(r; 0, C)`` from ``g = C^-1 r`` and ``log|C|``."""
    return -_HALF_LOG_2PI * r.shape[-1] - 0.5 * logdet - 0.5 * (r * g).sum(-1)


def _loo_terms(g: torch.Tensor, prec_diag: torch.Tensor) -> torch.Tensor:
    return -_HALF_LOG_2PI + 0.5 * torch.log(prec_diag) - 0.5 * g.square() / prec_diag


def log_likelihoods(post: Posterior, inp: Any, index: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """The leave-one-out and the joint log-likelihood of the data ``inp.y_obs`` at the
    posterior draws ``index`` (flat indices into ``(chain, draw)``), under the likelihood the
    sampler saw (:func:`~solderpyro.calibration.koh.observation_model`: the emulator's mean and
    code covariance, low-rank for a PCA surrogate, plus ``sigma^2 I`` and the discrepancy's
    covariance where it is modelled), from one factorization per draw.

    Args:
        post: the surrogate posterior (its ``raw`` unit-cube sites). inp: its
            :class:`~solderpyro.calibration.koh.ObsInputs`. index: ``(k,)``.
    Returns:
        ``(loo (k, n_obs), joint (k,))`` nats.
    """
    y = inp.y_obs
    loo, joint = [], []
    with torch.no_grad():
        for i in torch.as_tensor(index).tolist():
            t = inp.theta_box.from_unit(_raw_draw(post, SITE_T, i))
            sigma = _raw_draw(post, SITE_SIGMA, i)
            lr = None if inp.discrepancy else emulator_lowrank(inp.emulator, t)
            if lr is not None:
                a, b = lowrank_log_likelihoods(y, lr[0], lr[1], lr[2] + sigma.square())
            else:
                mean, cov = inp.emulator(t)
                kd = None
                if inp.discrepancy:
                    kd = _raw_draw(post, SITE_SIGMA_D, i).square() * gaussian(
                        inp.u_x, inp.u_x, _raw_draw(post, SITE_CORR_D, i))
                a, b = mvn_log_likelihoods(y, mean, observation_covariance(inp, cov, sigma, kd))
            loo.append(a)
            joint.append(b)
    return torch.stack(loo), torch.stack(joint)


def _raw_draw(post: Posterior, site: str, i: int) -> torch.Tensor:
    v = post.raw[site]
    return v.reshape(-1, *v.shape[2:])[i]


def observation_coords(meas: Measurements, n_obs: int) -> dict[str, np.ndarray]:
    """Coordinates of ``posterior.nc``'s ``obs`` dimension: ``label`` (``"A@1800s"``: point and
    time), ``time_s`` (s), ``point`` (``"A"``, ``"B"``, a field point's label), ``x_mm`` and
    ``y_mm`` (the point's position, specimen frame), each ``(n_obs,)``, in the measurements'
    row order (the order of the calibrated data).

    Raises:
        ValueError: the measurements do not have ``n_obs`` rows.
    """
    if len(meas) != n_obs:
        raise ValueError(f"observation_coords: the measurements have {len(meas)} rows, the "
                         f"calibrated data {n_obs} values")
    pt = np.asarray(meas.point, dtype=str)
    lab = np.array([f"{p}@{t:g}s" for p, t in zip(pt, meas.time_s, strict=True)])
    return {"label": lab, "time_s": np.asarray(meas.time_s, float), "point": pt,
            "x_mm": np.asarray(meas.x_mm, float), "y_mm": np.asarray(meas.y_mm, float)}
