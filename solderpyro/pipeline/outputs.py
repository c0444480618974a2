"""Stage 7, the outputs: what a calibration leaves in its run directory.

``summary.csv``, ``draws.npz``, ``data.csv``, the run's record (what ``solderpyro diagnose``
needs to rebuild the model; :class:`~solderpyro.config.rundir.RunDir`), ``posterior.nc``, the
sampler's state, the figures and ``report.md``/``report.html``. Written after the surrogate
posterior, and again after the FE-exact step, so that nothing computed is lost if a later
step fails.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from solderpyro.calibration.mcmc import Posterior, WarmStart
from solderpyro.config.rundir import Draws, RunDir, RunInfo
from solderpyro.io.measurements import Measurements
from solderpyro.surrogate import LooResult


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
