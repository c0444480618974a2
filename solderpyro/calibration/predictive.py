"""Posterior predictive (seed Eq. 9 and 12): mean and bands at new inputs, over posterior draws.

For each kept posterior draw the Gaussian conditional of the process at the new inputs given
all data is formed (Eq. 9 mean, Eq. 12 covariance) and sampled once; observation bands add the
noise sigma. The process is the code output at t, plus the discrepancy when it is modelled.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from solderpyro.calibration.koh import (
    SITE_CORR,
    SITE_CORR_D,
    SITE_SIGMA,
    SITE_SIGMA_C,
    SITE_SIGMA_D,
    SITE_T,
    JointInputs,
    ObsInputs,
    emulator_lowrank,
    joint_basis,
    joint_correlation,
)
from solderpyro.calibration.mcmc import Posterior
from solderpyro.surrogate.kernels import gaussian


@dataclass(frozen=True)
class Bands:
    """Posterior predictive summaries at ``n_new`` inputs (output units).

    Attributes:
        draws: ``(n_draws, n_new)`` process draws; obs_draws: the same plus noise.
        mean, median, lo, hi: ``(n_new,)`` process mean, median and 2.5 / 97.5 % quantiles.
        obs_lo, obs_hi: ``(n_new,)`` 2.5 / 97.5 % quantiles of a new observation.
        sigma: ``(n_draws,)`` the noise sd of each draw (None where not recorded).
        loc, var: ``(n_draws, n_new)`` the process's mean and variance (code uncertainty,
            plus the discrepancy's) given each draw's parameters, from which ``draws`` were
            sampled: the pointwise likelihood ``N(y_i; loc_i, var_i + sigma^2)`` of an
            observation (None where not recorded, e.g. conditioned draws).
        index: ``(n_draws,)`` which posterior draws (flat index into ``(chain, draw)``).
    """

    draws: torch.Tensor
    obs_draws: torch.Tensor
    sigma: torch.Tensor | None = None
    loc: torch.Tensor | None = None
    var: torch.Tensor | None = None
    index: torch.Tensor | None = None

    def log_likelihood(self, y: torch.Tensor) -> torch.Tensor:
        """``(n_draws, n_new)`` pointwise log density ``log N(y_i; loc_i, var_i + sigma^2)``
        of observations ``y (n_new,)`` under each draw (nats).

        Raises:
            ValueError: when ``loc``, ``var`` or ``sigma`` were not recorded.
        """
        if self.loc is None or self.var is None or self.sigma is None:
            raise ValueError("these bands carry no per-draw mean and variance")
        v = self.var + self.sigma[:, None] ** 2
        return -0.5 * ((y - self.loc) ** 2 / v + torch.log(2 * torch.pi * v))

    @property
    def mean(self) -> torch.Tensor:
        return self.draws.mean(0)

    @property
    def median(self) -> torch.Tensor:
        return self.draws.quantile(0.5, dim=0)

    @property
    def lo(self) -> torch.Tensor:
        return self.draws.quantile(0.025, dim=0)

    @property
    def hi(self) -> torch.Tensor:
        return self.draws.quantile(0.975, dim=0)

    @property
    def obs_lo(self) -> torch.Tensor:
        return self.obs_draws.quantile(0.025, dim=0)

    @property
    def obs_hi(self) -> torch.Tensor:
        return self.obs_draws.quantile(0.975, dim=0)


def _pick(post: Posterior, n_draws: int, gen: torch.Generator) -> torch.Tensor:
    total = next(iter(post.raw.values())).shape[0] * next(iter(post.raw.values())).shape[1]
    return torch.randperm(total, generator=gen)[: min(n_draws, total)]


def _raw(post: Posterior, site: str, i: int) -> torch.Tensor:
    v = post.raw[site]
    return v.reshape(-1, *v.shape[2:])[i]


def _conditional_draw(mean: torch.Tensor, cov: torch.Tensor, y: torch.Tensor, n_o: int,
                      noise_var: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """Draw block 2 of N(mean, cov) given block 1 = y, block 1 observed with noise_var."""
    c11 = cov[:n_o, :n_o] + noise_var * torch.eye(n_o, dtype=cov.dtype, device=cov.device)
    l11 = torch.linalg.cholesky(c11)
    a = torch.cholesky_solve(cov[:n_o, n_o:], l11)  # (n_o, n_p)
    m = mean[n_o:] + a.T @ (y - mean[:n_o])
    return _gaussian_draw(m, cov[n_o:, n_o:] - cov[n_o:, :n_o] @ a, gen)


def _gaussian_draw(m: torch.Tensor, c: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """One draw of N(m, c); c is symmetrized and its round-off negative eigenvalues clipped."""
    ev, evec = torch.linalg.eigh(0.5 * (c + c.T))
    e = torch.randn(m.shape[0], generator=gen, dtype=m.dtype, device=m.device)
    return m + evec @ (ev.clamp_min(0).sqrt() * e)


def predict_observation_model(post: Posterior, inp: ObsInputs, x_new: torch.Tensor | None,
                              u_new: torch.Tensor | None = None, n_draws: int = 500,
                              seed: int = 0, condition: bool | None = None,
                              index: torch.Tensor | None = None) -> Bands:
    """Predictive bands for a direct or modular calibration.

    ``condition`` (default: True for new inputs, False for ``x_new=None``) conditions the
    process on ``y_obs`` through the code and discrepancy covariances (Eq. 9, 12). Without it
    the bands are the model's own prediction at the posterior draws (code uncertainty and noise
    included), which is what a model-vs-measurement comparison must show: conditioning at the
    observed points would pull the bands onto the data and hide a misfit.

    Args:
        post: from :func:`~solderpyro.calibration.api.calibrate_direct` / ``calibrate_modular``.
        inp: the model's inputs.
        x_new: ``(n_new, n_x)`` new inputs; None predicts the observed outputs themselves.
        u_new: ``(n_new, n_x)`` unit-cube x_new, needed with a discrepancy.
        index: ``(k,)`` flat indices of the posterior draws to use (into ``(chain, draw)``);
            default ``n_draws`` drawn at random.
    Returns:
        :class:`Bands`; without new inputs and conditioning also each draw's ``loc`` and
        ``var`` (the pointwise likelihood of the observations) and ``index``.
    """
    gen = torch.Generator().manual_seed(seed)
    y = inp.y_obs
    n_o = y.shape[0]
    cond = (x_new is not None) if condition is None else condition
    proc, obs, sigmas, locs, vars_ = [], [], [], [], []
    pick = _pick(post, n_draws, gen) if index is None else torch.as_tensor(index)
    for i in pick.tolist():
        t = inp.theta_box.from_unit(_raw(post, SITE_T, i))
        sigma = _raw(post, SITE_SIGMA, i)
        sigmas.append(sigma)
        with torch.no_grad():
            lr = None if (x_new is not None or cond or inp.discrepancy) else \
                emulator_lowrank(inp.emulator, t)
            if lr is not None:  # PCA: draw through the factor, never forming the n x n cov
                m0, F, dg = lr
                locs.append(m0)
                vars_.append(F.square().sum(1) + dg)
                draw = m0 + F @ torch.randn(F.shape[1], generator=gen, dtype=m0.dtype) \
                    + dg.sqrt() * torch.randn(m0.shape, generator=gen, dtype=m0.dtype)
                proc.append(draw)
                obs.append(draw + sigma * torch.randn(draw.shape, generator=gen,
                                                      dtype=draw.dtype))
                continue
            mean, cov = _stacked(inp, t, x_new)
            if inp.discrepancy:
                assert inp.u_x is not None
                uu = torch.cat([inp.u_x, inp.u_x if u_new is None else u_new])
                kd = _raw(post, SITE_SIGMA_D, i).square() * gaussian(
                    uu, uu, _raw(post, SITE_CORR_D, i))
                cov = kd if cov is None else cov + kd
            if not cond:
                locs.append(mean[n_o:])
                vars_.append(torch.zeros_like(mean[n_o:]) if cov is None
                             else cov[n_o:, n_o:].diagonal().clone())
            if cov is None:
                draw = mean[n_o:]
            elif not cond:
                draw = _gaussian_draw(mean[n_o:], cov[n_o:, n_o:], gen)
            else:
                draw = _conditional_draw(mean, cov, y, n_o, sigma.square(), gen)
        proc.append(draw)
        obs.append(draw + sigma * torch.randn(draw.shape, generator=gen, dtype=draw.dtype))
    both = len(locs) == len(proc)
    return Bands(torch.stack(proc), torch.stack(obs), torch.stack(sigmas).reshape(-1),
                 torch.stack(locs) if both else None, torch.stack(vars_) if both else None,
                 pick.clone())


def _stacked(inp: ObsInputs, t: torch.Tensor, x_new: torch.Tensor | None
             ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Emulator mean/cov over [observation inputs; new inputs]."""
    em = inp.emulator
    if x_new is None:
        m, c = em(t)
        return torch.cat([m, m]), None if c is None else torch.cat(
            [torch.cat([c, c], 1), torch.cat([c, c], 1)])
    x_obs = getattr(em, "x_obs", None)
    if x_obs is None:
        raise ValueError("this emulator has no x inputs: call with x_new=None")
    return em(t, torch.cat([x_obs, x_new]))


def predict_joint(post: Posterior, inp: JointInputs, x_new: torch.Tensor, n_draws: int = 500,
                  seed: int = 0) -> Bands:
    """Seed Eq. 9 and 12 for the full joint model at ``x_new (n_new, n_x)`` (physical)."""
    gen = torch.Generator().manual_seed(seed)
    d = inp.data
    u_new = d.x_box.to_unit(x_new)
    m, n, p = inp.u_sim.shape[0], d.n_obs, x_new.shape[0]
    proc, obs = [], []
    for i in _pick(post, n_draws, gen).tolist():
        t_u = _raw(post, SITE_T, i)
        sigma, sigma_c = _raw(post, SITE_SIGMA, i), _raw(post, SITE_SIGMA_C, i)
        corr = _raw(post, SITE_CORR, i)
        beta = post.flat("beta")[i]  # physical -> standardized below
        with torch.no_grad():
            u_all = torch.cat([inp.u_sim,
                               torch.cat([inp.u_xobs, t_u.expand(n, t_u.shape[-1])], -1),
                               torch.cat([u_new, t_u.expand(p, t_u.shape[-1])], -1)])
            sc2 = (sigma_c / inp.y_scale).square()
            cov = sc2 * (joint_correlation(inp, u_all, u_all, corr)
                         + inp.nugget * torch.eye(m + n + p, dtype=u_all.dtype))
            if inp.discrepancy:
                ux = torch.cat([inp.u_xobs, u_new])
                kd = _raw(post, SITE_SIGMA_D, i).square() / inp.y_scale**2 * gaussian(
                    ux, ux, _raw(post, SITE_CORR_D, i))
                cov = cov + torch.nn.functional.pad(kd, (m, 0, m, 0))
            b_std = beta.clone()
            b_std[0] = (beta[0] - inp.y_mean) / inp.y_scale
            b_std[1:] = beta[1:] / inp.y_scale
            mean = joint_basis(inp, u_all) @ b_std
            noise = torch.cat([torch.zeros(m, dtype=mean.dtype),
                               (sigma / inp.y_scale).square().expand(n)])
            c11 = cov[: m + n, : m + n] + torch.diag(noise)
            cov2 = torch.cat([torch.cat([c11, cov[: m + n, m + n:]], 1), cov[m + n:]], 0)
            draw = _conditional_draw(mean, cov2, inp.z, m + n, torch.zeros((), dtype=mean.dtype),
                                     gen)
            draw = inp.y_mean + inp.y_scale * draw
        proc.append(draw)
        obs.append(draw + sigma * torch.randn(draw.shape, generator=gen, dtype=draw.dtype))
    return Bands(torch.stack(proc), torch.stack(obs))
