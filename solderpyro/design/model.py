"""The fitted GPyTorch surrogate as a BoTorch :class:`~botorch.models.model.Model`.

BoTorch's acquisition functions (and ``optimize_acqf``) work in the box's unit cube
``X (..., d)``; the surrogate's GPs see ``GPSurrogate._unit`` of the physical inputs (the unit
cube, or a physics-informed map such as the log flow stresses). :class:`SurrogateInputs`
carries that map as a BoTorch input transform, so the model's ``posterior``, ``fantasize`` and
``condition_on_observations`` are BoTorch's own, with the surrogate's fitted hyperparameters.

The model's ``k`` outputs are the surrogate's GP coefficients: the ``k`` principal components
of a ``"pca"`` surrogate (standardized units), or the ``n_y`` outputs of a ``"batched"`` one.
:func:`observed_weights` gives the per-coefficient weights that turn their variances into the
noise-weighted code variance at the observed outputs,
``sum_i var(eta_i(theta)) / sigma^2 = sum_k a_k var(z_k(theta)) + const``.
"""

from __future__ import annotations

import copy

import torch
from botorch.models import SingleTaskGP
from botorch.models.transforms.input import InputTransform

from solderpyro.surrogate import GPSurrogate


class SurrogateInputs(InputTransform, torch.nn.Module):
    """BoTorch input transform: unit cube ``X (..., d)`` -> the surrogate's GP inputs.

    ``X`` is :meth:`Box.to_unit` of the physical parameters (log-scale coordinates in their
    logarithm); the transform applies :meth:`Box.from_unit` and the surrogate's own input map
    (differentiable, so ``optimize_acqf`` gets gradients through it).
    """

    def __init__(self, gp: GPSurrogate) -> None:
        super().__init__()
        self.transform_on_train = True
        self.transform_on_eval = True
        self.transform_on_fantasize = True
        self._gp = gp

    def transform(self, X: torch.Tensor) -> torch.Tensor:
        """``X (..., d)`` in the unit cube -> ``(..., d')`` GP inputs."""
        return self._gp._unit(self._gp.box.from_unit(X))

    def equals(self, other: InputTransform) -> bool:
        return isinstance(other, SurrogateInputs) and other._gp is self._gp


def botorch_model(gp: GPSurrogate) -> SingleTaskGP:
    """The fitted surrogate ``gp`` as a BoTorch ``SingleTaskGP`` with ``k`` outputs.

    Hyperparameters (kernel, lengthscales, output scales, means, nuggets) are copies of the
    fitted ones and stay fixed; the training data are the surrogate's runs. The model's
    posterior at ``X (..., q, d)`` (unit cube) equals the surrogate's GP coefficients'
    predictive distribution (``GPSurrogate._coef``) to rounding.

    Args:
        gp: a fitted :class:`GPSurrogate` (any output layout).

    Returns:
        ``SingleTaskGP`` over the unit cube of ``gp.box`` with ``num_outputs = k``
        (``gp.basis.shape[1]``); inputs ``(..., q, d)``, outputs ``(..., q, k)`` in the
        standardized coefficient units of the surrogate.
    """
    gp._need_fit()
    src = gp.model
    assert src is not None
    X = gp.box.to_unit(gp._x_train).to(gp._z)  # (n, d)
    Z = gp._z.T.contiguous()  # (n, k)
    m = SingleTaskGP(X, Z, likelihood=copy.deepcopy(src.likelihood),
                     covar_module=copy.deepcopy(src.covar_module),
                     mean_module=copy.deepcopy(src.mean_module), outcome_transform=None,
                     input_transform=SurrogateInputs(gp))
    m.eval()
    for p in m.parameters():
        p.requires_grad_(False)
    return m


def observed_weights(gp: GPSurrogate, sigma: float) -> torch.Tensor:
    """``a (k,)``: noise-weighted code variance per unit variance of each GP coefficient.

    ``sum_i var(eta_i) / sigma^2 = sum_k a_k var(z_k) + sum_i resid_i / sigma^2`` over the
    surrogate's ``n_y`` outputs (the observed ones, in the specimen calibration), where
    ``eta_i = mean_i + scale_i * sum_k B_ik z_k``.

    Args:
        gp: a fitted :class:`GPSurrogate`. sigma: the noise sd, in the outputs' units (um).
    """
    if not sigma > 0:
        raise ValueError(f"observed_weights: sigma must be > 0, got {sigma}")
    sv = gp.basis * gp.std.scale[:, None]  # (n_y, k)
    return sv.square().sum(0) / sigma**2
