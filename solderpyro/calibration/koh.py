"""Kennedy-O'Hagan likelihoods as Pyro models.

Two plain model functions, each taking prepared inputs (tensors computed once, outside NUTS):

- :func:`joint_model`: the seed's full joint (Eq. 5-8). The stacked data
  z = [y_sim; y_obs] ~ N(F beta, sigma_c^2 R(D, D) + diag(0, sigma^2 I) [+ K_delta]), with
  D = [(x_sim, theta_sim); (x_obs, t)], sampled jointly in t, sigma, sigma_c and the correlation
  parameters. beta has a flat prior and is integrated out analytically (exactly; the same
  posterior for the other parameters as sampling it), then drawn from its Gaussian conditional
  afterwards (:func:`beta_conditional`).
- :func:`observation_model`: y_obs ~ N(mean(t), C(t) + sigma^2 I [+ K_delta]) for an emulator
  (direct: C = 0; modular: the GP's predictive covariance at (x_obs, t)).

Everything is computed on the unit cube (inputs) and, for the joint model, on outputs
standardized with the runs' mean and standard deviation; sampled sites are in physical units.

These models are the definition of the likelihoods. Each declares the analytic log densities
that implement it (:func:`implemented_by`, listed in :data:`FAST_DENSITIES`), which the
sampler takes where they cover the configuration; a test evaluates every declared density
against its model's log density (value and gradient).
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import pyro
import pyro.distributions as dist
import torch

from solderpyro.calibration.data import CalibrationData, check_tensor
from solderpyro.calibration.emulators import FunctionEmulator, GPEmulator
from solderpyro.params import Box
from solderpyro.surrogate.kernels import KERNELS

SITE_T = "t_unit"  #: calibration parameters on the unit cube of the theta box
SITE_SIGMA = "sigma"  #: observation noise standard deviation (output units)
SITE_SIGMA_C = "sigma_c"  #: GP standard deviation of the code (output units)
SITE_CORR = "corr"  #: correlation parameters theta of Eq. 4 on the unit cube
SITE_SIGMA_D = "sigma_delta"  #: discrepancy standard deviation (output units)
SITE_CORR_D = "corr_delta"  #: discrepancy correlation parameters on the unit cube of x
SITE_Y = "y"  #: the likelihood

#: The analytic log densities that implement each model of this module, declared on the
#: model with :func:`implemented_by`: model -> ``"module:function"`` references, tried in
#: this order by :func:`~.fastkoh.flat_model` (the first that covers the configuration, i.e.
#: does not raise :class:`NotImplementedError`, is sampled; none: Pyro's potential of the
#: model). Each is checked against the model's own log density, value and gradient, by
#: ``tests/unit/calibration/test_fastkoh.py``, which iterates over this table.
FAST_DENSITIES: dict[Callable[..., None], tuple[str, ...]] = {}

_Model = TypeVar("_Model", bound=Callable[..., None])


def implemented_by(*densities: str) -> Callable[[_Model], _Model]:
    """Declare the analytic log densities that implement a Pyro model (a decorator).

    Args:
        densities: ``"package.module:function"`` references (resolved when first used: the
            implementations import this module). Each function takes the model's arguments
            ``(inputs, priors)`` and returns a flat model (:class:`~.flat.FlatModel`: the
            model's posterior on Pyro's unconstrained scale, up to an additive constant) or
            raises :class:`NotImplementedError` naming the option it does not cover.
    Returns:
        the decorator, which records the model in :data:`FAST_DENSITIES` and returns it
        unchanged.
    """
    def declare(model: _Model) -> _Model:
        FAST_DENSITIES[model] = tuple(densities)
        return model
    return declare


def fast_densities(model: Callable[..., None]) -> tuple[Callable[..., Any], ...]:
    """The analytic log densities declared for ``model`` (:func:`implemented_by`), as
    functions, in order; empty for a model without any."""
    out = []
    for ref in FAST_DENSITIES.get(model, ()):
        mod, _, name = ref.partition(":")
        out.append(getattr(importlib.import_module(mod), name))
    return tuple(out)


@dataclass(frozen=True)
class Priors:
    """Explicit priors. Defaults are flat on boxes wide enough not to bind (as the seed).

    Attributes:
        sigma_max: sigma ~ Uniform(0, sigma_max); default 2 x range of y_obs.
        sigma_c_max: sigma_c ~ Uniform(0, sigma_c_max); default 10 x sd of y_sim.
        corr_range: Eq. 4's theta ~ Uniform(lo, hi) per correlation parameter (unit cube).
        corr_log: make the correlation prior uniform in log theta instead.
        delta_scale: sigma_delta ~ HalfNormal(delta_scale); default sd of y_obs.
        delta_corr: log theta_delta ~ Normal(loc, scale) on the unit cube of x.
        sigma_known: the measurement standard deviation when the data state it (the
            ``sigma_um`` column): sigma ~ LogNormal(log sigma_known, 0.1), i.e. known to about
            10 %, instead of the flat prior. With few observations a free sigma is
            underestimated and the posterior of t becomes too narrow.
        custom: site name -> distribution, replacing any default above.
    """

    sigma_max: float | None = None
    sigma_known: float | None = None
    sigma_c_max: float | None = None
    corr_range: tuple[float, float] = (0.01, 100.0)
    corr_log: bool = False
    delta_scale: float | None = None
    delta_corr: tuple[float, float] = (0.0, 1.5)
    custom: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        for nm in ("sigma_max", "sigma_c_max", "delta_scale", "sigma_known"):
            v = getattr(self, nm)
            if v is not None and not v > 0:
                raise ValueError(f"Priors.{nm} must be positive, got {v}")
        lo, hi = self.corr_range
        if not 0 < lo < hi:
            raise ValueError(f"Priors.corr_range must satisfy 0 < lo < hi, got {self.corr_range}")


def _site(priors: Priors, name: str, default: dist.Distribution) -> torch.Tensor:
    return pyro.sample(name, priors.custom.get(name, default))


def _uniform(lo: float | torch.Tensor, hi: float | torch.Tensor, n: int | None,
             tkw: dict[str, Any]) -> dist.Distribution:
    lo_t, hi_t = torch.as_tensor(lo, **tkw), torch.as_tensor(hi, **tkw)
    d = dist.Uniform(lo_t, hi_t)
    return d if n is None else d.expand([n]).to_event(1)


def _sigma_prior(priors: Priors, y: torch.Tensor, tkw: dict[str, Any]) -> dist.Distribution:
    """Known noise (LogNormal) or flat on (0, sigma_max); sigma_max defaults to 2 x range(y)."""
    if priors.sigma_known is not None:
        return dist.LogNormal(torch.tensor(math.log(priors.sigma_known), **tkw),
                              torch.tensor(0.1, **tkw))
    y_range = (y.max() - y.min()).item() if y.shape[0] > 1 else y.abs().item()
    return _uniform(0.0, priors.sigma_max or 2 * max(y_range, 1e-12), None, tkw)


def _corr_prior(priors: Priors, n: int, tkw: dict[str, Any]) -> dist.Distribution:
    lo, hi = priors.corr_range
    if priors.corr_log:  # uniform in log theta
        base = dist.Uniform(torch.tensor(math.log(lo), **tkw), torch.tensor(math.log(hi), **tkw))
        return dist.TransformedDistribution(base, [dist.transforms.ExpTransform()]
                                            ).expand([n]).to_event(1)
    return _uniform(lo, hi, n, tkw)


def discrepancy_cov(priors: Priors, u_x: torch.Tensor, scale_default: float) -> torch.Tensor:
    """Sample the discrepancy hyperparameters (Pyro sites) and return K_delta ``(n, n)``
    (output units^2) on the unit-scaled inputs u_x ``(n, n_x)``; ``scale_default``: the
    discrepancy sd prior scale when ``priors.delta_scale`` is unset."""
    tkw: dict[str, Any] = dict(dtype=u_x.dtype, device=u_x.device)
    sd = _site(priors, SITE_SIGMA_D, dist.HalfNormal(
        torch.tensor(priors.delta_scale or scale_default, **tkw)))
    loc, sc = priors.delta_corr
    cd = _site(priors, SITE_CORR_D, dist.LogNormal(torch.tensor(loc, **tkw),
                                                   torch.tensor(sc, **tkw))
               .expand([max(1, u_x.shape[1])]).to_event(1))
    return sd.square() * KERNELS["gaussian"](u_x, u_x, cd)


# ------------------------------------------------------------------------- joint model
@dataclass(frozen=True)
class JointInputs:
    """Tensors for :func:`joint_model`, computed once by :func:`prepare_joint`.

    Attributes:
        u_sim: ``(n_sim, n_x + n_theta)`` runs on the unit cube; u_xobs: ``(n_obs, n_x)``.
        z: ``(n_sim + n_obs,)`` standardized outputs; y_mean, y_scale: the standardization.
        ard: one correlation parameter per input (else one shared); mean: "constant"|"linear".
    """

    data: CalibrationData
    u_sim: torch.Tensor
    u_xobs: torch.Tensor
    z: torch.Tensor
    y_mean: float
    y_scale: float
    kernel: str = "gaussian"
    mean: str = "constant"
    ard: bool = False
    discrepancy: bool = False
    nugget: float = 1e-6

    @property
    def n_corr(self) -> int:
        return self.u_sim.shape[1] if self.ard else 1


def prepare_joint(data: CalibrationData, kernel: str = "gaussian", mean: str = "constant",
                  ard: bool = False, discrepancy: bool = False,
                  nugget: float = 1e-6) -> JointInputs:
    """Unit-cube inputs and standardized outputs for :func:`joint_model`."""
    if kernel not in KERNELS:
        raise ValueError(f"kernel={kernel!r}; choose one of {tuple(KERNELS)}")
    if mean not in ("constant", "linear"):
        raise ValueError(f"mean={mean!r}; choose 'constant' or 'linear'")
    u_sim = torch.cat([data.x_box.to_unit(data.x_sim), data.theta_box.to_unit(data.theta_sim)],
                      -1)
    mu = data.y_sim.mean().item()
    sd = data.y_sim.std().item() if data.n_sim > 1 else 1.0
    sd = sd if sd > 0 else 1.0
    z = (torch.cat([data.y_sim, data.y_obs]) - mu) / sd
    return JointInputs(data, u_sim, data.x_box.to_unit(data.x_obs), z, mu, sd, kernel, mean,
                       ard, discrepancy, nugget)


def joint_loglik(inp: JointInputs, t_unit: torch.Tensor, sigma: torch.Tensor,
                 sigma_c: torch.Tensor, corr: torch.Tensor,
                 k_delta: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Log-likelihood of the stacked data with beta (flat prior) integrated out.

    Args:
        t_unit: ``(n_theta,)``; sigma, sigma_c: scalars in output units; corr: ``(n_corr,)``;
        k_delta: optional ``(n_obs, n_obs)`` discrepancy covariance in output units.

    Returns:
        loglik (scalar, up to a constant), beta_hat ``(p,)`` and its covariance ``(p, p)``
        (standardized output units).
    """
    chol, h = joint_cholesky(inp, t_unit, sigma, sigma_c, corr, k_delta)
    a = torch.linalg.solve_triangular(chol, h, upper=False)  # (N, p)
    b = torch.linalg.solve_triangular(chol, inp.z.unsqueeze(-1), upper=False)  # (N, 1)
    g = a.T @ a
    lg = torch.linalg.cholesky(g)
    beta = torch.cholesky_solve(a.T @ b, lg)  # (p, 1)
    r = b - a @ beta
    ll = -chol.diagonal().log().sum() - lg.diagonal().log().sum() - 0.5 * r.square().sum()
    return ll, beta[:, 0], torch.cholesky_inverse(lg)


def _joint_points(inp: JointInputs, t_unit: torch.Tensor) -> torch.Tensor:
    n = inp.u_xobs.shape[0]
    u_obs = torch.cat([inp.u_xobs, t_unit.expand(n, t_unit.shape[-1])], -1)
    return torch.cat([inp.u_sim, u_obs])  # (N, d)


def joint_basis(inp: JointInputs, u: torch.Tensor) -> torch.Tensor:
    """The mean's basis ``F (N, p)`` at unit-cube points ``u (N, n_x + n_theta)``: a column
    of ones (``mean="constant"``, p = 1), followed by the columns of ``u`` (``"linear"``,
    p = 1 + n_x + n_theta)."""
    one = torch.ones(u.shape[0], 1, dtype=u.dtype, device=u.device)
    return one if inp.mean == "constant" else torch.cat([one, u], -1)  # (N, p)


def joint_correlation(inp: JointInputs, a: torch.Tensor, b: torch.Tensor,
                      corr: torch.Tensor) -> torch.Tensor:
    """The code GP's correlation ``R(a, b) (n_a, n_b)`` between unit-cube points
    ``a (n_a, d)`` and ``b (n_b, d)`` for Eq. 4's parameters ``corr (n_corr,)`` (shared or
    one per input): ``exp(-sum_k corr_k (a_k - b_k)^2)`` for the Gaussian kernel, Matern 5/2
    with length ``l = (2 corr)^-1/2`` otherwise. Dimensionless."""
    if inp.kernel == "gaussian":
        return KERNELS["gaussian"](a, b, corr)
    return KERNELS["matern52"](a, b, (0.5 / corr).sqrt())  # theta = 1/(2 l^2)


def joint_cholesky(inp: JointInputs, t_unit: torch.Tensor, sigma: torch.Tensor,
                   sigma_c: torch.Tensor, corr: torch.Tensor, k_delta: torch.Tensor | None
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """The lower Cholesky factor ``(N, N)`` of the stacked data's covariance ``S`` (in
    standardized output units, ``N = n_sim + n_obs``) and the mean's basis ``F (N, p)``, for
    the arguments of :func:`joint_loglik`."""
    u = _joint_points(inp, t_unit)
    m, n = inp.u_sim.shape[0], inp.u_xobs.shape[0]
    sc2 = (sigma_c / inp.y_scale).square()
    cov = sc2 * (joint_correlation(inp, u, u, corr)
                 + inp.nugget * torch.eye(m + n, dtype=u.dtype, device=u.device))
    noise = (sigma / inp.y_scale).square() * torch.ones(n, dtype=u.dtype, device=u.device)
    cov = cov + torch.diag(torch.cat([torch.zeros_like(inp.z[:m]), noise]))
    if k_delta is not None:
        cov = cov + torch.nn.functional.pad(k_delta / inp.y_scale**2, (m, 0, m, 0))
    return torch.linalg.cholesky(cov), joint_basis(inp, u)


@implemented_by("solderpyro.calibration.fastkoh:joint_flat")
def joint_model(inp: JointInputs, priors: Priors) -> None:
    """The seed's full-joint KOH posterior (Eq. 5-8) as a Pyro model (beta integrated out)."""
    d = inp.data
    tkw: dict[str, Any] = dict(dtype=inp.z.dtype, device=inp.z.device)
    t_unit = _site(priors, SITE_T, _uniform(0.0, 1.0, d.theta_box.dim, tkw))
    sigma = _site(priors, SITE_SIGMA, _sigma_prior(priors, d.y_obs, tkw))
    sigma_c = _site(priors, SITE_SIGMA_C, _uniform(0.0, priors.sigma_c_max or 10 * inp.y_scale,
                                                   None, tkw))
    corr = _site(priors, SITE_CORR, _corr_prior(priors, inp.n_corr, tkw))
    k_delta = (discrepancy_cov(priors, inp.u_xobs, d.y_obs.std().item() if d.n_obs > 1 else 1.0)
               if inp.discrepancy else None)
    ll, _, _ = joint_loglik(inp, t_unit, sigma, sigma_c, corr, k_delta)
    pyro.factor(SITE_Y, ll)


# ------------------------------------------------------------------- observation model
@dataclass(frozen=True)
class ObsInputs:
    """Inputs of :func:`observation_model`.

    Attributes:
        y_obs: ``(n_obs,)``; emulator: direct or GP; theta_box: support of the flat t prior;
        u_x: ``(n_obs, n_x)`` unit-cube x of the observations (for the discrepancy GP).
    """

    y_obs: torch.Tensor
    emulator: FunctionEmulator | GPEmulator
    theta_box: Box
    u_x: torch.Tensor | None = None
    discrepancy: bool = False


def prepare_observation(y_obs: torch.Tensor, emulator: FunctionEmulator | GPEmulator | Any,
                        theta_box: Box, x_obs: torch.Tensor | None = None,
                        x_box: Box | None = None, discrepancy: bool = False) -> ObsInputs:
    """Validate and bundle the inputs of :func:`observation_model`."""
    check_tensor("y_obs", y_obs, 1)
    u_x = None
    if x_obs is not None:
        check_tensor("x_obs", x_obs, 2)
        if x_obs.shape[0] != y_obs.shape[0]:
            raise ValueError(f"x_obs has {x_obs.shape[0]} rows but y_obs has {y_obs.shape[0]}")
        xb = x_box or Box.around([f"x{i + 1}" for i in range(x_obs.shape[1])], x_obs)
        u_x = xb.to_unit(x_obs)
    if discrepancy and u_x is None:
        raise ValueError("discrepancy=True needs x_obs (the discrepancy is a GP over x)")
    with torch.no_grad():
        mean, _ = emulator(theta_box.from_unit(torch.full((theta_box.dim,), 0.5,
                                                          dtype=y_obs.dtype)))
    if mean.shape != y_obs.shape:
        raise ValueError(f"the emulator returns {tuple(mean.shape)} outputs but y_obs has shape "
                         f"{tuple(y_obs.shape)}")
    return ObsInputs(y_obs, emulator, theta_box, u_x, discrepancy)


def observation_covariance(inp: ObsInputs, cov: torch.Tensor | None, sigma: torch.Tensor,
                           k_delta: torch.Tensor | None) -> torch.Tensor:
    """C(t) + sigma^2 I + K_delta ``(n_obs, n_obs)``."""
    n = inp.y_obs.shape[0]
    out = sigma.square() * torch.eye(n, dtype=inp.y_obs.dtype, device=inp.y_obs.device)
    if cov is not None:
        out = out + cov
    return out if k_delta is None else out + k_delta


def emulator_lowrank(emulator: Any, t: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """The emulator's low-rank form ``(mean, F, d)`` at ``t`` when it has one (PCA), else None."""
    lr = getattr(emulator, "lowrank", None)
    return None if lr is None else lr(t)


@implemented_by("solderpyro.calibration.fastkoh:direct_flat",
                "solderpyro.calibration.reduced:pca_flat")
def observation_model(inp: ObsInputs, priors: Priors) -> None:
    """Direct or modular KOH posterior as a Pyro model."""
    y = inp.y_obs
    tkw: dict[str, Any] = dict(dtype=y.dtype, device=y.device)
    t_unit = _site(priors, SITE_T, _uniform(0.0, 1.0, inp.theta_box.dim, tkw))
    t = inp.theta_box.from_unit(t_unit)
    lr = None if inp.discrepancy else emulator_lowrank(inp.emulator, t)
    if lr is not None:  # PCA surrogate (full field): Woodbury, O(n k^2) per evaluation
        sigma = _site(priors, SITE_SIGMA, _sigma_prior(priors, y, tkw))
        pyro.sample(SITE_Y, dist.LowRankMultivariateNormal(lr[0], lr[1],
                                                           lr[2] + sigma.square()), obs=y)
        return
    mean, cov = inp.emulator(t)
    sigma = _site(priors, SITE_SIGMA, _sigma_prior(priors, y, tkw))
    k_delta = None
    if inp.discrepancy:
        assert inp.u_x is not None
        k_delta = discrepancy_cov(priors, inp.u_x, y.std().item() if y.shape[0] > 1 else 1.0)
    if cov is None and k_delta is None:
        pyro.sample(SITE_Y, dist.Normal(mean, sigma).to_event(1), obs=y)
        return
    c = observation_covariance(inp, cov, sigma, k_delta)
    pyro.sample(SITE_Y, dist.MultivariateNormal(mean, scale_tril=torch.linalg.cholesky(c)),
                obs=y)
