"""The fitted GPyTorch surrogate as a BoTorch :class:`~botorch.models.model.Model`.

BoTorch's acquisition functions (and ``optimize_acqf``) work in the box's unit cube
``X (..., d)``; the surrogate's GPs see ``GPSurrogate.gp_inputs`` of the physical inputs (the unit
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
import functools
from typing import TYPE_CHECKING, Any

import torch

from solderpyro.surrogate import GPSurrogate
from solderpyro.surrogate.gp import BatchGP, botorch_imports

if TYPE_CHECKING:
    from botorch.models import SingleTaskGP
    from botorch.models.transforms.input import InputTransform


@functools.cache
def _surrogate_inputs_class() -> type[InputTransform]:
    """:class:`SurrogateInputs`, defined on first use (BoTorch is imported only where it is
    used, in :func:`~solderpyro.surrogate.gp.botorch_imports`)."""
    with botorch_imports():
        from botorch.models.transforms.input import InputTransform

    class SurrogateInputs(InputTransform, torch.nn.Module):
        """BoTorch input transform: unit cube ``X (..., d)`` -> the surrogate's GP inputs.

        ``X`` is :meth:`Box.to_unit` of the physical parameters (log-scale coordinates in their
        logarithm); the transform applies :meth:`Box.from_unit` and the surrogate's own input
        map (differentiable, so ``optimize_acqf`` gets gradients through it).

        Args:
            gp: the fitted :class:`GPSurrogate`.
        """

        def __init__(self, gp: GPSurrogate) -> None:
            super().__init__()
            self.transform_on_train = True
            self.transform_on_eval = True
            self.transform_on_fantasize = True
            self._gp = gp

        def transform(self, X: torch.Tensor) -> torch.Tensor:
            """``X (..., d)`` in the unit cube -> ``(..., d')`` GP inputs."""
            return self._gp.gp_inputs(self._gp.box.from_unit(X))

        def equals(self, other: InputTransform) -> bool:
            return isinstance(other, SurrogateInputs) and other._gp is self._gp

    SurrogateInputs.__qualname__ = SurrogateInputs.__name__  # pickled by module and name
    return SurrogateInputs


def __getattr__(name: str) -> Any:
    """``SurrogateInputs``: BoTorch input transform, unit cube ``X (..., d)`` -> the
    surrogate's GP inputs (``SurrogateInputs(gp)``, a BoTorch ``InputTransform``); the class is
    defined on first access, when BoTorch is imported."""
    if name == "SurrogateInputs":
        return _surrogate_inputs_class()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def botorch_model(gp: GPSurrogate) -> SingleTaskGP:
    """The fitted surrogate ``gp`` as a BoTorch ``SingleTaskGP`` with ``k`` outputs.

    Hyperparameters (kernel, lengthscales, output scales, means, nuggets) are copies of the
    fitted ones and stay fixed; the training data are the surrogate's runs. The model's
    posterior at ``X (..., q, d)`` (unit cube) equals the surrogate's GP coefficients'
    predictive distribution (:meth:`GPSurrogate.coefficients`) to rounding.

    Args:
        gp: a fitted :class:`GPSurrogate` (any output layout).

    Returns:
        ``SingleTaskGP`` over the unit cube of ``gp.box`` with ``num_outputs = k``
        (``gp.basis.shape[1]``); inputs ``(..., q, d)``, outputs ``(..., q, k)`` in the
        standardized coefficient units of the surrogate.
    """
    with botorch_imports():
        from botorch.models import SingleTaskGP

    z = gp.factors().z  # (k, n); raises before a fit
    src = gp.model
    assert src is not None
    X = gp.box.to_unit(gp.x_train).to(z)  # (n, d)
    Z = z.T.contiguous()  # (n, k)
    k = Z.shape[1]
    if k == 1:  # BoTorch's single-output models carry no output batch dimension
        u = src.train_inputs[0][0]
        one = BatchGP(u[None], Z.T, gp.kernel, gp.mean, gp.ard, gp.nugget).to(Z)
        st = {kk: v.reshape(-1) if v.ndim == 1 else v for kk, v in src.state_dict().items()}
        one.load_state_dict(st)
        mods = [_unbatch(m_) for m_ in (one.likelihood, one.covar_module, one.mean_module)]
    else:
        mods = [copy.deepcopy(m_) for m_ in (src.likelihood, src.covar_module,
                                              src.mean_module)]
    m = SingleTaskGP(X, Z, likelihood=mods[0], covar_module=mods[1], mean_module=mods[2],
                     outcome_transform=None, input_transform=_surrogate_inputs_class()(gp))
    m.eval()
    for p in m.parameters():
        p.requires_grad_(False)
    return m


def _unbatch(module: torch.nn.Module) -> torch.nn.Module:
    """A copy of a GPyTorch module with batch shape ``(1,)`` as one with no batch shape."""
    import gpytorch

    if isinstance(module, gpytorch.likelihoods.GaussianLikelihood):
        new: torch.nn.Module = gpytorch.likelihoods.GaussianLikelihood(
            noise_constraint=module.noise_covar.raw_noise_constraint)
    elif isinstance(module, gpytorch.kernels.ScaleKernel):
        b = module.base_kernel
        kw = dict(ard_num_dims=b.ard_num_dims, lengthscale_constraint=b.raw_lengthscale_constraint)
        base = (gpytorch.kernels.RBFKernel(**kw) if isinstance(b, gpytorch.kernels.RBFKernel)
                else gpytorch.kernels.MaternKernel(nu=b.nu, **kw))
        new = gpytorch.kernels.ScaleKernel(base)
    elif isinstance(module, gpytorch.means.ConstantMean):
        new = gpytorch.means.ConstantMean()
    else:
        new = gpytorch.means.LinearMean(int(module.weights.shape[-2]))  # type: ignore[index]
    st = module.state_dict()
    tgt = new.state_dict()
    new.load_state_dict({k: st[k].reshape(tgt[k].shape) for k in tgt})
    return new.to(next(iter(st.values())))


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
