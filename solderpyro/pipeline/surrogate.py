"""Stage 2, the surrogate: a GP of the observed outputs over the FE's parameter box."""

from __future__ import annotations

import logging
import math

import torch

from solderpyro.config.settings import SurrogateSettings
from solderpyro.pipeline.problem import CalibrationProblem
from solderpyro.surrogate import GPOptions, GPSurrogate

log = logging.getLogger("solderpyro")


def fit_surrogate(cp: CalibrationProblem, s: SurrogateSettings, X: torch.Tensor, Y: torch.Tensor,
                  noise_sd: float | None = None) -> GPSurrogate:
    """Fit the surrogate to converged runs.

    Args:
        cp: the problem (its ``gp_box``, and Anand defaults for the flow-stress inputs).
        s: kernel, ARD, mean, output layout (``"pca"`` unless one value is observed), inputs.
        X: ``(n, n_fe)`` FE parameters, physical units; Y: ``(n, n_obs)`` observed outputs, um.
        noise_sd: the noise sd (um) for the PCA truncation rule (``s.truncation``); default
            the one the data state (none: the variance-explained rule alone).

    Returns:
        the fitted :class:`~solderpyro.surrogate.GPSurrogate`.
    """
    from solderpyro.surrogate.features import input_map

    output = s.output if Y.shape[1] > 1 else "batched"
    feats = input_map(s.inputs, cp.gp_box, cp.setup.space.defaults, s.inputs_T_C,
                      s.inputs_rate)
    sd = noise_sd if noise_sd is not None else cp.priors.sigma_known
    use = bool(sd) and output == "pca"
    trunc = GPOptions(resid_chi2=s.truncation * math.sqrt(2 * Y.shape[1]),
                      noise_sd=sd) if use else GPOptions()
    gp = GPSurrogate(cp.gp_box, output=output, kernel=s.kernel, ard=s.ard, mean=s.mean,
                     options=trunc, inputs=feats)
    gp.fit(X, Y)
    log.info("surrogate: %s GP on %d runs, %d outputs, %d component(s)", output, len(X),
             Y.shape[1], gp.basis.shape[1])
    return gp
