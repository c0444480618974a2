"""Stage 7, the outputs: what a calibration leaves in its run directory.

``summary.csv``, ``draws.npz``, ``data.csv``, ``run.json`` (what ``solderpyro diagnose``
needs to rebuild the model), ``posterior.nc``, the sampler's state, the figures and
``report.md``/``report.html``. Written after the surrogate posterior, and again after the
FE-exact step, so that nothing computed is lost if a later step fails.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from solderpyro.calibration import Priors
from solderpyro.calibration.mcmc import Posterior
from solderpyro.io.measurements import Measurements
from solderpyro.params import Box
from solderpyro.specimen import WARM_FILE
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


def save_run(out: Path, meas: Measurements, space: Box, effects: tuple[str, ...],
             post: Posterior, bands: Any, y_obs: torch.Tensor, y_liu: torch.Tensor,
             priors: Priors, record: dict[str, Any],
             draws: tuple[np.ndarray, np.ndarray] | None = None) -> None:
    """Keep what a later ``solderpyro diagnose`` needs in the run directory.

    Writes ``data.csv`` (the measurements, exact round trip), ``draws.npz`` (flat posterior
    draws ``theta (n, dim)`` in physical units with ``names``, ``sigma (n,)`` in um, the
    predictive ``process (n_pred, n_obs)`` and ``observed (n_pred, n_obs)`` draws with their
    noise ``sigma_pred (n_pred,)``, ``y_obs`` and
    the Liu-constants model ``y_liu``, all in um) and ``run.json`` (settings, parameter box).
    ``draws``: ``(theta (n, dim), sigma (n,))`` to save instead of ``post``'s (the FE-exact
    posterior's resampled draws).
    """
    from solderpyro.io.measurements import write_measurements

    write_measurements(out / "data.csv", meas)
    theta, sigma = draws if draws is not None else (post.flat("t").numpy(),
                                                     post.flat("sigma").numpy())
    np.savez(out / "draws.npz", theta=theta, sigma=sigma,
             names=np.array(space.names), process=bands.draws.numpy(),
             observed=bands.obs_draws.numpy(), y_obs=y_obs.numpy(), y_liu=y_liu.numpy(),
             sigma_pred=(bands.sigma if bands.sigma is not None
                         else torch.full((bands.draws.shape[0],), float("nan"))).numpy())
    info = {**record, "parameters": list(space.names), "lower": list(space.lower),
            "upper": list(space.upper), "sigma_known": priors.sigma_known,
            "effects": list(effects),
            "times_s": [float(t) for t in meas.times()], "points": list(meas.points())}
    (out / "run.json").write_text(json.dumps(info, indent=2, default=str) + "\n")
    if post.warm is not None:  # a recalibration can start from here (--warm-from)
        post.warm.save(out / WARM_FILE)
