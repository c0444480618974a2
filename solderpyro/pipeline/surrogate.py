"""Stage 2, the surrogate: a GP of the observed outputs over the FE's parameter box."""

from __future__ import annotations

import logging

import torch

from solderpyro.pipeline.problem import SpecimenModel
from solderpyro.pipeline.settings import SurrogateSettings
from solderpyro.surrogate import GPSurrogate

log = logging.getLogger("solderpyro")


def fit_surrogate(sm: SpecimenModel, s: SurrogateSettings, X: torch.Tensor, Y: torch.Tensor
                  ) -> GPSurrogate:
    """Fit the surrogate to converged runs.

    Args:
        sm: the problem (its ``gp_box``, and Anand defaults for the flow-stress inputs).
        s: kernel, ARD, mean, output layout (``"pca"`` unless one value is observed), inputs.
        X: ``(n, n_fe)`` FE parameters, physical units; Y: ``(n, n_obs)`` observed outputs, um.

    Returns:
        the fitted :class:`~solderpyro.surrogate.GPSurrogate`.
    """
    from solderpyro.surrogate.features import input_map

    output = s.output if Y.shape[1] > 1 else "batched"
    feats = input_map(s.inputs, sm.gp_box, sm.setup.space.defaults, s.inputs_T_C,
                      s.inputs_rate)
    gp = GPSurrogate(sm.gp_box, output=output, kernel=s.kernel, ard=s.ard, mean=s.mean,
                     inputs=feats)
    return gp.fit(X, Y)
