"""Model-form error in the intervals: a Kennedy-O'Hagan discrepancy at the FE's best fit.

When the model misses part of the physics, its best fit leaves a structured residual and the
constants absorb what they can of the missing effect. The likelihood ``y = f(theta) + eps``
with independent noise then gives intervals as narrow as if the model were right, around
constants that are wrong. Kennedy and O'Hagan's answer is a discrepancy term:

    y = f(theta) + delta(x) + eps,   delta ~ GP(0, k),   eps ~ N(0, sigma^2 I),

over the observation coordinates ``x`` (time and position). Where ``delta`` could explain the
part of the residual that a change of ``theta`` would, the data no longer pin ``theta`` down as
firmly, and the interval widens by as much as the two are confounded.

This module does that in its modular form (Liu, Bayarri and Berger 2009, "Modularization in
Bayesian analysis, with emphasis on analysis of computer models", Bayesian Analysis 4(1)):

1. :func:`fit_discrepancy` fits the GP's hyperparameters to the residual at the FE's best fit
   (BoTorch's ``SingleTaskGP``, a Matern-5/2 ARD kernel with a learned amplitude, the noise
   fixed at the stated sd where the file gives one, marginal likelihood by L-BFGS) on at most
   :data:`MAX_FIT` values; the covariance ``Sigma = K_delta + sigma^2 I`` is then built on all.
2. :func:`koh_laplace` gives the Gaussian (Laplace) posterior of ``theta`` under that
   likelihood, linearised at the best fit: ``Cov = (J' Sigma^-1 J)^-1`` and the generalised
   least-squares shift ``Cov J' Sigma^-1 r``. Since ``Sigma >= sigma^2 I``, ``Cov`` is never
   smaller than the independent-noise Laplace covariance.
3. :func:`widened_intervals` turns it into 95 % intervals on the box's unit scale (logarithmic
   where flagged), clipped to the box.

Units: ``x`` any (each column is scaled to the unit interval), residuals um, ``theta`` the box's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.linalg import cho_factor, cho_solve
from scipy.stats import norm

from solderpyro.params import Box

#: the most residual values the discrepancy's hyperparameters are fitted on (a random subset;
#: the fit's cost grows as its cube, and a few hundred values fix four hyperparameters well)
MAX_FIT = 500


@dataclass(frozen=True)
class Discrepancy:
    """A fitted discrepancy GP over the observations.

    Attributes:
        cov: ``(n, n)`` um^2, ``K_delta + sigma^2 I`` at the observations.
        sd_um: the discrepancy's prior sd, um (the kernel's amplitude).
        noise_sd_um: the noise sd, um (the stated one, or fitted).
        lengthscales: ``(d,)`` correlation lengths, in the units of the coordinates' columns
            (inf for a constant column).
    """

    cov: np.ndarray
    sd_um: float
    noise_sd_um: float
    lengthscales: np.ndarray


def fit_discrepancy(X: np.ndarray, r: np.ndarray, noise_sd: float | None = None,
                    seed: int = 0) -> Discrepancy:
    """Fit a GP discrepancy to the residual ``r`` at the best fit.

    Args:
        X: ``(n, d)`` observation coordinates (e.g. time s, x mm, y mm); constant columns are
            left out of the kernel.
        r: ``(n,)`` residual ``y - f(theta_best)``, um.
        noise_sd: the stated noise sd, um (held fixed), or None (fitted with the GP).
        seed: which :data:`MAX_FIT` values the hyperparameters are fitted on, if there are
            more.
    Returns:
        :class:`Discrepancy`.
    Raises:
        ValueError: for mismatched shapes, non-finite values or a non-positive ``noise_sd``.
    """
    from gpytorch.kernels import ScaleKernel
    from gpytorch.mlls import ExactMarginalLogLikelihood

    from solderpyro.surrogate.gp import botorch_imports, exact_linear_algebra

    with botorch_imports():
        from botorch.fit import fit_gpytorch_mll
        from botorch.models import SingleTaskGP
        from botorch.models.transforms import Normalize, Standardize
        from botorch.models.utils.gpytorch_modules import get_covar_module_with_dim_scaled_prior

    X = np.asarray(X, float)
    r = np.asarray(r, float).reshape(-1)
    if X.ndim != 2 or X.shape[0] != r.shape[0]:
        raise ValueError(f"fit_discrepancy: X must be (n, d) with n = len(r) = {r.shape[0]}, "
                         f"got {X.shape}")
    if not (np.isfinite(X).all() and np.isfinite(r).all()):
        raise ValueError("fit_discrepancy: X and r must be finite")
    if noise_sd is not None and not noise_sd > 0:
        raise ValueError(f"fit_discrepancy: noise_sd must be > 0 um, got {noise_sd}")
    varies = np.ptp(X, axis=0) > 0
    lengths = np.full(X.shape[1], np.inf)
    if not varies.any() or r.shape[0] < 3:  # nothing to correlate over: white noise only
        s2 = noise_sd**2 if noise_sd else float(np.mean(r**2))
        return Discrepancy(np.eye(r.shape[0]) * s2, 0.0, float(np.sqrt(s2)), lengths)
    Xv = X[:, varies]
    lo, span = Xv.min(0), np.ptp(Xv, axis=0)
    fit_idx = np.arange(r.shape[0])
    if r.shape[0] > MAX_FIT:
        fit_idx = np.sort(np.random.default_rng(seed).choice(r.shape[0], MAX_FIT,
                                                             replace=False))
    Xt = torch.as_tensor(Xv[fit_idx], dtype=torch.float64)
    Yt = torch.as_tensor(r[fit_idx], dtype=torch.float64)[:, None]
    d = Xv.shape[1]
    # BoTorch's fit in BoTorch's settings (exact linear algebra), whatever the host's
    with exact_linear_algebra():
        kernel = ScaleKernel(get_covar_module_with_dim_scaled_prior(d, use_rbf_kernel=False))
        standardize = Standardize(1)
        model = SingleTaskGP(
            Xt, Yt, train_Yvar=None if noise_sd is None else torch.full_like(Yt, noise_sd**2),
            covar_module=kernel,
            input_transform=Normalize(d, bounds=torch.as_tensor(np.vstack([lo, lo + span]))),
            outcome_transform=standardize)
        fit_gpytorch_mll(ExactMarginalLogLikelihood(model.likelihood, model))
        model.eval()
        with torch.no_grad():
            scale = float(standardize.stdvs.reshape(())) ** 2
            u = torch.as_tensor((Xv - lo) / span, dtype=torch.float64)
            K = kernel(u).to_dense().numpy() * scale
            amp = float(kernel.outputscale) * scale
            ls = kernel.base_kernel.lengthscale.reshape(-1).numpy() * span
            s2 = (noise_sd**2 if noise_sd is not None
                  else float(model.likelihood.noise.mean()) * scale)
    lengths[varies] = ls
    return Discrepancy(K + s2 * np.eye(r.shape[0]), float(np.sqrt(amp)), float(np.sqrt(s2)),
                       lengths)


def koh_laplace(J: np.ndarray, r: np.ndarray, cov: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """The Laplace posterior of ``theta`` under ``y = f(theta) + N(0, cov)``, linearised at a
    point where the residual is ``r``.

    Args:
        J: ``(n, p)`` Jacobian ``df/dtheta`` (um per unit of theta's scale).
        r: ``(n,)`` residual ``y - f``, um.
        cov: ``(n, n)`` um^2, the errors' covariance (:attr:`Discrepancy.cov`).
    Returns:
        ``(shift (p,), Cov (p, p))``: the generalised least-squares step from the point, and
        ``(J' cov^-1 J)^+`` (pseudo-inverse: a direction the data do not see has no bound
        here; the box bounds it).
    """
    c = cho_factor(np.asarray(cov, float), lower=True)
    J = np.asarray(J, float)
    F = J.T @ cho_solve(c, J)
    C = np.linalg.pinv(F, rcond=1e-12, hermitian=True)
    shift = C @ (J.T @ cho_solve(c, np.asarray(r, float)))
    return shift, C


@dataclass(frozen=True)
class WidenedInterval:
    """One parameter's interval admitting model-form error.

    Attributes:
        parameter: its name. lo, hi: the interval's ends, the parameter's units.
        centre: the generalised least-squares estimate, the parameter's units.
        widening: the interval's half-width on the unit scale over the independent-noise
            Laplace one (>= 1 before clipping to the box).
    """

    parameter: str
    lo: float
    hi: float
    centre: float
    widening: float


def widened_intervals(space: Box, x_best: np.ndarray, J_unit: np.ndarray, r: np.ndarray,
                      d: Discrepancy, level: float = 0.95) -> list[WidenedInterval]:
    """``level`` intervals of each parameter under the discrepancy likelihood, linearised at the
    best fit, on the box's unit scale and clipped to the box.

    Args:
        space: the box (names, bounds, log scales).
        x_best: ``(p,)`` the FE's best fit, physical units.
        J_unit: ``(n, p)`` its Jacobian on the box's unit scale (``df/du``, um;
            :meth:`~solderpyro.exact.fit.LMFit.jacobian_unit`).
        r: ``(n,)`` the residual there, um. d: the fitted discrepancy.
    Returns:
        one :class:`WidenedInterval` per parameter, in the box's order.
    """
    z = float(norm.ppf(0.5 + level / 2.0))
    shift, C = koh_laplace(J_unit, r, d.cov)
    C0 = np.linalg.pinv(J_unit.T @ J_unit, rcond=1e-12, hermitian=True) * d.noise_sd_um**2
    u0 = space.to_unit(torch.as_tensor(np.asarray(x_best, float))[None]).numpy()[0]
    uc = np.clip(u0 + shift, 0.0, 1.0)
    half = z * np.sqrt(np.clip(np.diag(C), 0.0, None))
    half0 = z * np.sqrt(np.clip(np.diag(C0), 0.0, None))
    ends = np.vstack([np.clip(uc - half, 0.0, 1.0), np.clip(uc + half, 0.0, 1.0), uc])
    phys = space.from_unit(torch.as_tensor(ends)).numpy()
    return [WidenedInterval(nm, float(phys[0, i]), float(phys[1, i]), float(phys[2, i]),
                            float(half[i] / half0[i]) if half0[i] > 0 else float("inf"))
            for i, nm in enumerate(space.names)]
