"""Exact-GP surrogate (GPyTorch) of a computer model y = f(X), X in a named box.

Three output layouts, one code path (GPs on coefficients, a fixed basis back to outputs):

- ``"scalar"``: one output, controllable inputs x are GP inputs beside t (the seed's way);
  basis = [[1]].
- ``"batched"``: one independent GP per output column, batched in GPyTorch; basis = identity.
- ``"pca"``: principal components of the standardized outputs (Higdon et al. 2008), a GP per
  kept component; basis = the first k right singular vectors, plus the truncation variance.

Transforms are explicit: inputs go to the unit cube through :class:`solderpyro.params.Box`
(or, with ``inputs=``, through a physics-informed map such as
:class:`solderpyro.surrogate.features.FlowStressInputs`, scaled to [0, 1] over the box),
outputs are standardized per column by :class:`Standardizer`. Hyperparameters are fitted by
maximizing the exact marginal likelihood (L-BFGS, several restarts, best kept per GP). After the
fit, predictions run through plain torch (:meth:`GPSurrogate.mean_cov`): differentiable in the
inputs and cheap enough to sit inside an MCMC likelihood.
"""

from __future__ import annotations

import inspect
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import gpytorch
import torch
from linear_operator import settings as linop_settings

from solderpyro.params import Box
from solderpyro.surrogate.kernels import gaussian, matern52
from solderpyro.surrogate.mll import mll_closure
from solderpyro.surrogate.transforms import Standardizer

#: training rows up to which GPyTorch factorizes exactly (Cholesky) inside
#: :func:`exact_linear_algebra`, instead of conjugate gradients and Lanczos
EXACT_ROWS = 4096


@contextmanager
def exact_linear_algebra() -> Iterator[None]:
    """The context the surrogate's GPyTorch computations run in: exact linear algebra
    (Cholesky, not conjugate gradients or Lanczos) up to :data:`EXACT_ROWS` training rows, no
    fast solves, log-probabilities or root decompositions, up to 6 jitter tries; kernels
    evaluated eagerly up to :data:`EXACT_ROWS` rows. These are the values importing BoTorch sets
    as process-wide defaults (botorch/__init__.py): in a context they make a fit independent of
    whether BoTorch was imported (without them the surrogate-vs-direct calibration test moved
    by 4 Monte Carlo standard errors with import order), and they leave a host's own
    GPyTorch settings as they were outside it. ``tests/unit/test_host_settings.py`` checks that
    importing solderpyro changes no GPyTorch or linear_operator setting."""
    with linop_settings.fast_computations(covar_root_decomposition=False, log_prob=False,
                                          solves=False), \
            linop_settings.cholesky_max_tries(6), \
            linop_settings.max_cholesky_size(EXACT_ROWS), \
            gpytorch.settings.max_eager_kernel_size(EXACT_ROWS):
        yield


def _settings_state() -> dict[tuple[type, str], tuple[bool, object]]:
    """Every GPyTorch and linear_operator setting: ``(class, attribute) -> (whether the class
    sets it itself, value)`` for each class of the two settings modules and each attribute a
    setting keeps its value in (``_default``, ``_state``, ``_global_value``,
    ``_global_float_value``, ...)."""
    out: dict[tuple[type, str], tuple[bool, object]] = {}
    for mod in (gpytorch.settings, linop_settings):
        for cls in vars(mod).values():
            if inspect.isclass(cls):
                for k in dir(cls):
                    if k in ("_default", "_state") or k.startswith("_global"):
                        out[(cls, k)] = (k in vars(cls), getattr(cls, k))
    return out


@contextmanager
def botorch_imports() -> Iterator[None]:
    """The context solderpyro imports BoTorch in, where it uses it (never at a module's top)::

        with botorch_imports():
            from botorch.models import SingleTaskGP

    Importing BoTorch the first time sets six GPyTorch and linear_operator settings as
    process-wide defaults (botorch/__init__.py: ``max_cholesky_size`` 800 -> 4096 and
    ``cholesky_max_tries`` 3 -> 6, one class each in both packages' settings modules;
    ``max_eager_kernel_size`` 512 -> 4096; the defaults of ``fast_solves``, ``fast_log_prob``
    and ``fast_covar_root_decomposition`` True -> False). On exit every class attribute that
    holds a setting's value in the two settings modules is given back what it had on entry:
    a host's own GPs keep their numbers whether or not solderpyro imported BoTorch, and a host
    that imported BoTorch itself keeps BoTorch's defaults. solderpyro's BoTorch computations
    run in :func:`exact_linear_algebra`, which has BoTorch's values.
    ``tests/unit/test_host_settings.py`` checks both hosts."""
    before = _settings_state()
    try:
        yield
    finally:
        after = _settings_state()
        for cls, k in before.keys() | after.keys():
            was, now = before.get((cls, k)), after.get((cls, k))
            if was is not None and now is not None and was[0] == now[0] and was[1] is now[1]:
                continue
            if was is not None and was[0]:
                setattr(cls, k, was[1])
            elif k in vars(cls):  # set on the class inside the context: inherited again
                delattr(cls, k)


class SurrogateWarning(UserWarning):
    """The surrogate fails its own validation: predictions are not to be trusted."""


class BatchGP(gpytorch.models.ExactGP):
    """``b`` independent exact GPs on the unit cube (GPyTorch batch mode): the model that
    :class:`GPSurrogate` fits, one GP per coefficient.

    Args:
        x: ``(b, n, d)`` training inputs (the GP's input scale, about [0, 1]).
        z: ``(b, n)`` training targets (standardized units).
        kernel: ``"gaussian"`` (RBF) or ``"matern52"``, each with an output scale.
        mean: ``"constant"`` or ``"linear"``.
        ard: one lengthscale per input dimension (else one shared).
        nugget: lower bound of the noise variance (standardized units).
    """

    def __init__(self, x: torch.Tensor, z: torch.Tensor, kernel: str, mean: str, ard: bool,
                 nugget: float) -> None:
        b, _, d = x.shape
        bs = torch.Size([b])
        lik = gpytorch.likelihoods.GaussianLikelihood(
            batch_shape=bs, noise_constraint=gpytorch.constraints.GreaterThan(nugget))
        super().__init__(x, z, lik)
        self.mean_module = (gpytorch.means.ConstantMean(batch_shape=bs) if mean == "constant"
                            else gpytorch.means.LinearMean(d, batch_shape=bs))
        kw = dict(batch_shape=bs, ard_num_dims=d if ard else None,
                  lengthscale_constraint=gpytorch.constraints.Interval(1e-3, 1e3))
        base = (gpytorch.kernels.RBFKernel(**kw) if kernel == "gaussian"
                else gpytorch.kernels.MaternKernel(nu=2.5, **kw))
        self.covar_module = gpytorch.kernels.ScaleKernel(base, batch_shape=bs)

    def forward(self, x: torch.Tensor) -> gpytorch.distributions.MultivariateNormal:
        """The GPs' prior at inputs ``x (b, n*, d)``: mean ``(b, n*)``, covariance
        ``(b, n*, n*)``."""
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x),
                                                         self.covar_module(x))


@dataclass(frozen=True)
class LooResult:
    """Validation of a surrogate against known outputs (leave-one-out or held-out).

    Attributes:
        y: ``(n, n_y)`` true outputs; mean, sd: ``(n, n_y)`` predictions (physical units).
        z: ``(n, n_y)`` standardized errors (y - mean) / sd, ~N(0, 1) for a calibrated GP.
        coverage95: fraction of |z| <= 1.96. rmse_rel: RMSE / output standard deviation.
    """

    y: torch.Tensor
    mean: torch.Tensor
    sd: torch.Tensor
    z: torch.Tensor
    coverage95: float
    rmse_rel: float
    max_abs_z: float

    def problems(self, min_coverage: float = 0.8, max_rmse_rel: float = 0.1) -> list[str]:
        """Reasons not to trust the surrogate (empty when it passes)."""
        out = []
        if self.coverage95 < min_coverage:
            out.append(f"95% intervals cover {self.coverage95:.0%} of the checks "
                       f"(< {min_coverage:.0%}): the GP is overconfident")
        if self.rmse_rel > max_rmse_rel:
            out.append(f"RMSE is {self.rmse_rel:.1%} of the output spread "
                       f"(> {max_rmse_rel:.0%}): too few runs or a poor kernel")
        return out


@dataclass(frozen=True)
class GPFactors:
    """The fitted GPs' prediction factors: ``k`` GPs (one per coefficient), ``n`` runs, ``d'``
    GP inputs (:meth:`GPSurrogate.gp_inputs`). Everything is in the GP's own scale: inputs in
    about [0, 1], targets and variances in standardized coefficient units. The tensors are the
    surrogate's own (detached): read them, do not modify them in place.

    The coefficients' predictive mean at GP inputs ``u* (n*, d')`` is
    ``m(u*) + K(u*, u) alpha`` with the prior mean ``m(u) = mean_const (+ u @ mean_weights)``
    and ``K = outputscale * correlation``; the variance is
    ``outputscale - |L^-1 K(u, u*)|^2``.

    Attributes:
        u: ``(k, n, d')`` the training inputs (the same rows for every GP).
        z: ``(k, n)`` the training targets.
        outputscale: ``(k,)`` the kernels' prior variances.
        lengthscale: ``(k, d')`` with ARD, else ``(k, 1)``; GP-input units.
        noise: ``(k,)`` the fitted noise (nugget) variances.
        mean_const: ``(k,)`` the constant mean, or the linear mean's bias.
        mean_weights: ``(k, d')`` the linear mean's weights; None for a constant mean.
        chol: ``(k, n, n)`` lower Cholesky factor ``L`` of ``K(u, u) + noise I``.
        alpha: ``(k, n)`` ``(K(u, u) + noise I)^-1 (z - m(u))``.
    """

    u: torch.Tensor
    z: torch.Tensor
    outputscale: torch.Tensor
    lengthscale: torch.Tensor
    noise: torch.Tensor
    mean_const: torch.Tensor
    mean_weights: torch.Tensor | None
    chol: torch.Tensor
    alpha: torch.Tensor


@dataclass(frozen=True)
class GPOptions:
    """How many components a ``"pca"`` surrogate keeps, and how its GPs are fitted.

    Attributes:
        n_pc: kept components for ``"pca"`` (None: enough for ``var_explained``).
        var_explained: fraction of the standardized output variance the kept PCs explain,
            in (0, 1].
        resid_chi2: with ``noise_sd``, keep more components (``"pca"``) until the truncation
            variance the PCs leave, summed over the outputs in units of the noise variance,
            ``sum_i resid_i / noise_sd^2``, is at most this (a chi-square: the code variance
            no added run can remove; 0.1 * sqrt(2 n_y) is a tenth of the chi-square's own
            sampling sd), but never more than half as many components as runs. Measured on
            102 full-field runs (2,240 outputs, sigma 0.05 um): var_explained 0.999 keeps 8 PCs
            and leaves 178; 15 PCs leave 4.9, 20 leave 0.7.
        noise_sd: the data's noise sd, output units (for ``resid_chi2``; both or neither).
        nugget: lower bound of the GP noise variance (standardized units), for conditioning.
        restarts: L-BFGS restarts from different initial lengthscales (at least 1 is run).

    Raises:
        ValueError: naming the field when one is out of range.
    """

    n_pc: int | None = None
    var_explained: float = 0.999
    resid_chi2: float | None = None
    noise_sd: float | None = None
    nugget: float = 1e-6
    restarts: int = 3

    def __post_init__(self) -> None:
        if not 0 < self.var_explained <= 1:
            raise ValueError(f"var_explained must be in (0, 1], got {self.var_explained}")
        if (self.resid_chi2 is None) != (self.noise_sd is None):
            raise ValueError("resid_chi2 and noise_sd go together (both or neither)")
        if self.noise_sd is not None and not (self.noise_sd > 0 and self.resid_chi2 is not None
                                              and self.resid_chi2 > 0):
            raise ValueError(f"need noise_sd > 0 and resid_chi2 > 0, got {self.noise_sd}, "
                             f"{self.resid_chi2}")
        if self.n_pc is not None and self.n_pc < 1:
            raise ValueError(f"n_pc must be a positive integer or None, got {self.n_pc}")


class GPSurrogate:
    """GPyTorch exact-GP surrogate over a named input box.

    The hyperparameter fit runs in :func:`exact_linear_algebra`; predictions, the leave-one-out
    check and :meth:`factors` are plain torch on the cached factors and read no GPyTorch
    setting, so a host's GPyTorch settings change none of this class's numbers.

    Args:
        box: the inputs (names, bounds, log-scale); ``d = box.dim``.
        output: ``"scalar"``, ``"batched"`` or ``"pca"`` (see module docstring).
        kernel: ``"gaussian"`` (seed Eq. 4) or ``"matern52"``.
        mean: ``"constant"`` (seed's f(X) beta with f = 1) or ``"linear"``.
        ard: one lengthscale per input (else one shared, as the seed's single theta).
        options: the PCA truncation, nugget and restarts (:class:`GPOptions`; None: its
            defaults).
        inputs: optional differentiable map of physical inputs ``(..., d) -> (..., d')`` that
            the GP sees instead of the box's unit cube (e.g. ``FlowStressInputs``); its values
            are rescaled to [0, 1] over the range they take on the box (a 1024-point LHS and
            the training runs).
    """

    def __init__(self, box: Box, output: str = "scalar", kernel: str = "gaussian",
                 mean: str = "constant", ard: bool = False, options: GPOptions | None = None,
                 inputs: Callable[[torch.Tensor], torch.Tensor] | None = None) -> None:
        for name, val, ok in (("output", output, ("scalar", "batched", "pca")),
                              ("kernel", kernel, ("gaussian", "matern52")),
                              ("mean", mean, ("constant", "linear"))):
            if val not in ok:
                raise ValueError(f"GPSurrogate {name}={val!r}; choose one of {ok}")
        o = options if options is not None else GPOptions()
        self.box, self.output, self.kernel, self.mean = box, output, kernel, mean
        self.ard, self.options = ard, o
        self.n_pc, self.var_explained = o.n_pc, o.var_explained
        self.resid_chi2, self.noise_sd = o.resid_chi2, o.noise_sd
        self.nugget, self.restarts = o.nugget, o.restarts
        self.inputs = inputs
        self.model: BatchGP | None = None

    # ------------------------------------------------------------------ fitting
    def fit(self, x: torch.Tensor, y: torch.Tensor) -> GPSurrogate:
        """Fit to runs.

        Args:
            x: ``(n, d)`` inputs in physical units (columns as ``box.names``).
            y: ``(n,)`` for ``"scalar"``, ``(n, n_y)`` otherwise.

        Returns:
            self, fitted.
        """
        x, y = self._check_xy(x, y)
        with exact_linear_algebra():
            self._fit(x, y)
        return self

    def _fit(self, x: torch.Tensor, y: torch.Tensor) -> None:
        self._x_train, self._y_train = x, y
        self.std = Standardizer.fit(y)
        ys = self.std.forward(y)  # (n, n_y)
        self.basis, self.resid_var = self._basis(ys)  # (n_y, k), (n_y,)
        z = (ys @ self.basis).T.contiguous()  # (k, n)
        if self.inputs is not None:  # the map's range over the box, for the [0, 1] scaling
            from scipy.stats import qmc

            u0 = torch.as_tensor(qmc.LatinHypercube(d=self.box.dim, seed=0).random(1024))
            with torch.no_grad():  # (the LHS of solderpyro.design.lhs, which sits above us)
                f = self.inputs(torch.cat([x, self.box.from_unit(u0).to(x)]))
            self._in_lo = f.min(0).values
            self._in_span = (f.max(0).values - self._in_lo).clamp_min(1e-12)
        u = self.gp_inputs(x)
        # hyperparameters in the data's dtype: GPyTorch creates them in torch's default dtype
        # (float32 outside the tests), which rounded the CLI's lengthscales to 1e-8 and the
        # predictive means of a PCA surrogate to ~1e-6 of their size
        self.model = BatchGP(u.expand(z.shape[0], *u.shape), z, self.kernel, self.mean,
                              self.ard, self.nugget).to(dtype=u.dtype, device=u.device)
        _fit_mll(self.model, self.restarts)
        self._freeze()

    def _check_xy(self, x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if x.ndim != 2 or x.shape[1] != self.box.dim:
            raise ValueError(f"x must have shape (n, {self.box.dim}) for inputs "
                             f"{self.box.names}, got {tuple(x.shape)}")
        if self.output == "scalar":
            if y.ndim == 2 and y.shape[1] == 1:
                y = y[:, 0]
            if y.ndim != 1:
                raise ValueError(f"y must have shape (n,) for output='scalar', got "
                                 f"{tuple(y.shape)}")
            y = y.unsqueeze(-1)
        elif y.ndim != 2:
            raise ValueError(f"y must have shape (n, n_y) for output={self.output!r}, got "
                             f"{tuple(y.shape)}")
        if y.shape[0] != x.shape[0]:
            raise ValueError(f"x has {x.shape[0]} rows but y has {y.shape[0]}")
        if x.shape[0] < 2:
            raise ValueError(f"need at least 2 runs to fit a GP, got {x.shape[0]}")
        for nm, t in (("x", x), ("y", y)):
            if not torch.isfinite(t).all():
                raise ValueError(f"{nm} contains NaN or inf (rows "
                                 f"{torch.nonzero(~torch.isfinite(t).all(-1)).flatten()[:10].tolist()})")
        return x, y

    def _basis(self, ys: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        n_y = ys.shape[1]
        if self.output != "pca":
            return torch.eye(n_y, dtype=ys.dtype, device=ys.device), torch.zeros_like(ys[0])
        _, s, vt = torch.linalg.svd(ys, full_matrices=False)
        frac = torch.cumsum(s**2, 0) / (s**2).sum()
        k = self.n_pc or int((frac < self.var_explained).sum().item()) + 1
        if self.n_pc is None and self.noise_sd is not None and self.resid_chi2 is not None:
            # truncation chi-square after k components: sum_i scale_i^2 sum_{j>k} (U S V^T)^2/n
            sc2 = self.std.scale.square() / self.noise_sd**2  # (n_y,)
            per = (vt.square() * sc2).sum(1) * s.square() / ys.shape[0]  # (r,) per component
            tail = per.flip(0).cumsum(0).flip(0)  # tail[j]: left when keeping j components
            left = torch.cat([tail[1:], tail.new_zeros(1)])
            # at most half as many components as runs: with few runs spread over the box the
            # rule asks for nearly one per run (a GP per noise-like component, slow to fit)
            k = max(k, min(int((left > self.resid_chi2).sum().item()) + 1, ys.shape[0] // 2))
        k = min(k, vt.shape[0])
        v = vt[:k].T  # (n_y, k)
        resid = ys - ys @ v @ v.T
        return v, resid.square().mean(0)

    def _freeze(self) -> None:
        """Cache plain-tensor hyperparameters, Cholesky factor and weights for prediction."""
        m = self.model
        assert m is not None
        with torch.no_grad():
            self._u = m.train_inputs[0].detach()  # (k, n, d)
            zt = m.train_targets.detach()  # (k, n)
            self._os = m.covar_module.outputscale.detach()  # (k,)
            self._ls = m.covar_module.base_kernel.lengthscale.detach()[:, 0, :]  # (k, d|1)
            self._noise = m.likelihood.noise.detach().reshape(-1)  # (k,)
            mm = m.mean_module
            self._c = mm.constant.detach().reshape(-1) if self.mean == "constant" \
                else mm.bias.detach().reshape(-1)
            self._w = None if self.mean == "constant" else mm.weights.detach()[..., 0]  # (k, d)
            n = self._u.shape[1]
            eye = torch.eye(n, dtype=zt.dtype, device=zt.device)
            kxx = self._os[:, None, None] * self.correlation(self._u, self._u) \
                + self._noise[:, None, None] * eye
            self._chol = torch.linalg.cholesky(kxx)  # (k, n, n)
            r = (zt - self._prior_mean(self._u)).unsqueeze(-1)
            self._alpha = torch.cholesky_solve(r, self._chol)[..., 0]  # (k, n)
            self._kinv_diag = torch.cholesky_inverse(self._chol).diagonal(dim1=-2, dim2=-1)
            self._z = zt

    def gp_inputs(self, x: torch.Tensor) -> torch.Tensor:
        """Physical inputs ``(..., d)`` -> the GP's inputs ``(..., d')`` in about [0, 1]:
        ``box.to_unit(x)`` (``d' = d``), or with an input map ``(inputs(x) - lo) / span``
        (:attr:`input_scaling`). Differentiable in ``x``."""
        if self.inputs is None:
            return self.box.to_unit(x)
        return (self.inputs(x) - self._in_lo) / self._in_span

    def correlation(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """The fitted kernels' correlations ``(k, n_a, n_b)`` between GP inputs ``a (k, n_a, d')``
        and ``b (k, n_b, d')`` (see :meth:`gp_inputs`); the covariance is
        ``outputscale[:, None, None]`` times it (:meth:`factors`)."""
        self._need_fit()
        if self.kernel == "gaussian":
            return gaussian(a, b, 0.5 / self._ls.square())
        return matern52(a, b, self._ls)

    def _prior_mean(self, u: torch.Tensor) -> torch.Tensor:
        out = self._c[:, None].expand(-1, u.shape[-2])
        if self._w is not None:
            out = out + (u * self._w[:, None, :]).sum(-1)
        return out  # (k, n*)

    @property
    def theta(self) -> torch.Tensor:
        """Seed-style correlation parameters ``(k, d|1)`` on the unit cube (gaussian kernel)."""
        return 0.5 / self._ls.square()

    # ------------------------------------------------------------- fitted factors
    def factors(self) -> GPFactors:
        """The fitted GPs' training inputs, hyperparameters, Cholesky factor and weights
        (:class:`GPFactors`), for code that predicts outside this class (the reduced
        likelihood's NumPy GPs, the closed-form acquisition)."""
        self._need_fit()
        return GPFactors(self._u, self._z, self._os, self._ls, self._noise, self._c, self._w,
                         self._chol, self._alpha)

    @property
    def input_scaling(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        """With an input map (``inputs``): ``(lo, span)``, each ``(d',)``, that rescale its
        values to the GP's inputs ``(inputs(x) - lo) / span`` (the map's range over the box);
        None without one (the GP's inputs are then ``box.to_unit(x)``). Needs :meth:`fit`."""
        self._need_fit()
        return None if self.inputs is None else (self._in_lo, self._in_span)

    @property
    def x_train(self) -> torch.Tensor:
        """``(n, d)`` the training runs' inputs, physical units (as given to :meth:`fit`)."""
        self._need_fit()
        return self._x_train

    @property
    def y_train(self) -> torch.Tensor:
        """``(n, n_y)`` the training runs' outputs, physical units (``n_y = 1`` for
        ``"scalar"``)."""
        self._need_fit()
        return self._y_train

    # --------------------------------------------------------------- prediction
    def cross_covariance(self, x: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """For physical inputs ``x (n*, d)``: the GP inputs ``u (k, n*, d')``, the
        covariances with the runs ``ks (k, n*, n)`` (standardized units^2) and
        ``v = L^-1 ks^T (k, n, n*)`` (``L``: :attr:`GPFactors.chol`), so the coefficients'
        posterior covariance between points ``a`` and ``b`` is
        ``outputscale * correlation(u_a, u_b) - v_a^T v_b``."""
        self._need_fit()
        u = self.gp_inputs(x)
        u = u.expand(self._u.shape[0], *u.shape)  # (k, n*, d')
        ks = self._os[:, None, None] * self.correlation(u, self._u)  # (k, n*, n)
        v = torch.linalg.solve_triangular(self._chol, ks.transpose(-1, -2), upper=False)
        return u, ks, v

    def coefficients(self, x: torch.Tensor, full_cov: bool = False
                     ) -> tuple[torch.Tensor, torch.Tensor]:
        """Predictive mean ``(k, n*)`` and variance ``(k, n*)`` (``full_cov``: covariance
        ``(k, n*, n*)``) of the ``k`` GP coefficients at physical inputs ``x (n*, d)``, in the
        standardized coefficient units (outputs are ``std.inverse(mean^T basis^T)``); no
        observation noise. Differentiable in ``x``."""
        self._need_fit()
        u, ks, v = self.cross_covariance(x)
        mean = self._prior_mean(u) + (ks * self._alpha[:, None, :]).sum(-1)  # (k, n*)
        if full_cov:
            kss = self._os[:, None, None] * self.correlation(u, u)
            return mean, kss - v.transpose(-1, -2) @ v  # (k, n*, n*)
        return mean, (self._os[:, None] - v.square().sum(-2)).clamp_min(0.0)  # (k, n*)

    def predict(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Predictive mean and variance of the code output (no observation noise).

        Args:
            x: ``(n*, d)`` physical inputs.

        Returns:
            mean, var: ``(n*,)`` for ``"scalar"``, else ``(n*, n_y)``; physical units.
        """
        self._need_fit()
        mc, vc = self.coefficients(x, full_cov=False)  # (k, n*)
        mean = self.std.inverse(mc.T @ self.basis.T)  # (n*, n_y)
        var = (vc.T @ self.basis.T.square() + self.resid_var) * self.std.scale.square()
        if self.output == "scalar":
            return mean[:, 0], var[:, 0]
        return mean, var

    def mean_cov(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Joint predictive mean and covariance over points and outputs (differentiable in x).

        Args:
            x: ``(n*, d)`` physical inputs.

        Returns:
            mean ``(n* * n_y,)`` and cov ``(n* * n_y, n* * n_y)``, point-major order
            (index ``i * n_y + j`` is point i, output j); physical units.
        """
        self._need_fit()
        mc, cc = self.coefficients(x, full_cov=True)  # (k, n*), (k, n*, n*)
        sv = self.basis * self.std.scale[:, None]  # (n_y, k)
        mean = self.std.inverse(mc.T @ self.basis.T).reshape(-1)
        cov = torch.einsum("jk,kab,lk->ajbl", sv, cc, sv)  # (n*, n_y, n*, n_y)
        n, n_y = x.shape[0], sv.shape[0]
        cov = cov.reshape(n * n_y, n * n_y)
        extra = (self.resid_var * self.std.scale.square()).repeat(n)
        return mean, cov + torch.diag(extra)

    def mean_lowrank(self, x: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Predictive mean and covariance at ONE input as ``F F^T + diag(d)`` (differentiable).

        For a PCA surrogate of ``n_y`` outputs with ``k`` kept components this is what makes
        full-field likelihoods cheap: O(n_y k^2) instead of O(n_y^3).

        Args:
            x: ``(d,)`` or ``(1, d)`` physical input.
        Returns:
            mean ``(n_y,)``, factor ``F (n_y, k)`` and diagonal ``d (n_y,)``; physical units
            (the covariance equals :meth:`mean_cov`'s).
        """
        self._need_fit()
        x = x.reshape(1, -1)
        mc, vc = self.coefficients(x, full_cov=False)  # (k, 1), (k, 1)
        sv = self.basis * self.std.scale[:, None]  # (n_y, k)
        mean = self.std.inverse(mc.T @ self.basis.T)[0]
        return mean, sv * vc[:, 0].clamp_min(0.0).sqrt(), self.resid_var * self.std.scale.square()

    def _need_fit(self) -> None:
        if self.model is None:
            raise RuntimeError("GPSurrogate.fit(x, y) must be called before predicting")

    # --------------------------------------------------------------- validation
    def loo(self) -> LooResult:
        """Closed-form leave-one-out check (hyperparameters held at their fitted values)."""
        self._need_fit()
        with torch.no_grad():
            vc = 1.0 / self._kinv_diag  # (k, n)
            mc = self._z - self._alpha * vc
            mean = self.std.inverse(mc.T @ self.basis.T)
            var = (vc.T @ self.basis.T.square() + self.resid_var) * self.std.scale.square()
        return _result(self._y_train, mean, var)

    def validate(self, x: torch.Tensor, y: torch.Tensor) -> LooResult:
        """Held-out check on runs not used in the fit: ``x (n, d)``, ``y`` as in :meth:`fit`."""
        x, y = self._check_xy(x, y)
        with torch.no_grad():
            mean, var = self.predict(x)
        if self.output == "scalar":
            mean, var = mean[:, None], var[:, None]
        return _result(y, mean, var)

    def check(self, result: LooResult | None = None, **kw: float) -> list[str]:
        """Warn (:class:`SurrogateWarning`) with every reason not to trust the surrogate."""
        res = result if result is not None else self.loo()
        probs = res.problems(**kw)
        for p in probs:
            warnings.warn(f"surrogate not trustworthy: {p}", SurrogateWarning, stacklevel=2)
        return probs


def _result(y: torch.Tensor, mean: torch.Tensor, var: torch.Tensor) -> LooResult:
    sd = var.clamp_min(1e-300).sqrt()
    z = (y - mean) / sd
    spread = y.std(0).clamp_min(1e-300) if y.shape[0] > 1 else torch.ones_like(y[0])
    rmse_rel = ((y - mean).square().mean(0).sqrt() / spread).mean().item()
    return LooResult(y, mean, sd, z, (z.abs() <= 1.96).double().mean().item(), rmse_rel,
                     z.abs().max().item())


#: L-BFGS stops when an iteration changes the negative log marginal likelihood, summed over
#: the batch's GPs, by less than this many nats per GP. With torch's default (1e-9) every
#: restart ran its 300 iterations on the design's surrogates (20 PCA components, 50-70 runs);
#: at 5e-6 per GP (1e-4 for the 20) it stops after 108-153, the fit takes ~0.55x the time, the
#: summed -log likelihood is 0.1 nat higher, and at 200 posterior draws the predictive means
#: move by <= 0.011 noise sd and the code variance by <= 1.3 % (the loop's recalibration,
#: round 3)
LBFGS_TOL_CHANGE = 5e-6


def _fit_mll(model: BatchGP, restarts: int) -> None:
    """Maximize the exact marginal likelihood; keep, per GP in the batch, the best restart.

    BLAS runs on one thread here: the closure's products and factorizations are small (``(k, n^2) x
    (n^2, d)``, ``n``-square Cholesky factors) and two OpenBLAS threads made a fit of 86 runs 4.7x
    slower on two cores (10.6 s against 2.2 s; BENCHMARKS.md, "Per-gradient and per-round costs of
    the calibration")."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        _fit_mll_restarts(model, restarts)


def _fit_mll_restarts(model: BatchGP, restarts: int) -> None:
    mll = gpytorch.mlls.ExactMarginalLogLikelihood(model.likelihood, model)
    x, z = model.train_inputs[0], model.train_targets
    best_state, best_loss = None, None
    inits = [0.3, 1.0, 0.1, 3.0, 0.03][: max(1, restarts)]
    for ls0 in inits:
        model.covar_module.base_kernel.lengthscale = ls0
        model.covar_module.outputscale = z.var(-1).clamp_min(1e-6)
        model.likelihood.noise = max(1e-4, 10 * model.likelihood.noise_covar.raw_noise_constraint
                                     .lower_bound.item())
        model.train()
        opt = torch.optim.LBFGS(model.parameters(), lr=1.0, max_iter=300,
                                line_search_fn="strong_wolfe", tolerance_grad=1e-9,
                                tolerance_change=LBFGS_TOL_CHANGE * z.shape[0])

        def autograd_closure(opt: torch.optim.LBFGS = opt) -> torch.Tensor:
            opt.zero_grad()
            loss = -mll(model(x), z).sum()
            loss.backward()
            return loss

        closure = (mll_closure(model, opt, autograd_closure)
                   if x.dtype == torch.float64 and x.device.type == "cpu" else autograd_closure)

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", gpytorch.utils.warnings.NumericalWarning)
            try:
                opt.step(closure)
            except (RuntimeError, ValueError):  # a restart that runs into a bad region
                continue
            with torch.no_grad():
                loss_b = -mll(model(x), z)  # (k,)
        if not torch.isfinite(loss_b).all():
            continue
        state = {k: v.detach().clone() for k, v in model.state_dict().items()}
        if best_state is None:
            best_state, best_loss = state, loss_b
        else:
            better = loss_b < best_loss
            for k, v in state.items():
                if v.ndim and v.shape[0] == better.shape[0] and k.startswith(
                        ("mean_module", "covar_module", "likelihood")):
                    mask = better.reshape(-1, *([1] * (v.ndim - 1)))
                    best_state[k] = torch.where(mask, v, best_state[k])
            assert best_loss is not None
            best_loss = torch.minimum(best_loss, loss_b)
    if best_state is None:
        raise RuntimeError("GP hyperparameter fit failed from every starting point")
    model.load_state_dict(best_state)
    model.eval()
