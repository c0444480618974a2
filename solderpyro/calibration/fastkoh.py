"""Analytic log densities and gradients of the KOH posteriors for :mod:`.nuts`.

The posteriors are exactly those of the Pyro models in :mod:`.koh` on the unconstrained scale
Pyro's NUTS samples (the same priors, the same transforms, the log-Jacobians included), written
in NumPy with hand-derived gradients instead of autograd:

- :func:`direct_flat`: :func:`~.koh.observation_model` with a
  :class:`~.emulators.FunctionEmulator` (the direct mode): ``y ~ N(f(x, t), sigma^2 I)``. The
  computer model's contribution to the gradient, ``J(t)^T (y - f) / sigma^2``, is one torch
  vector-Jacobian product through ``f`` (and the theta box's unit-cube map).
- :func:`joint_flat`: :func:`~.koh.joint_model` (the full joint, beta integrated out). With
  ``S = sc2 (R + nugget I) + s2 diag(0_m, 1_n)`` (``sc2 = (sigma_c / y_scale)^2``,
  ``s2 = (sigma / y_scale)^2``), ``P = S^-1 - S^-1 F G^-1 F^T S^-1`` (``G = F^T S^-1 F``) and
  ``a = P z``, the log-likelihood ``-1/2 log|S| - 1/2 log|G| - 1/2 z^T P z`` has
  ``d ll / d S = W = 1/2 (a a^T - P)``, so ``d ll / d x = sum(W * dS/dx)`` for each parameter;
  t enters only the observation rows and columns of R.

Unconstrained coordinates (Pyro's ``biject_to``): a site with support ``(lo, hi)`` is
``x = lo + (hi - lo) sigmoid(u)``, log-Jacobian ``log(hi - lo) + log s + log(1 - s)``; a positive
site (LogNormal prior) is ``x = exp(u)``, log-Jacobian ``u``. The flat vector stacks the sites in
the models' order: t_unit, sigma (then sigma_c, corr for the joint).

Each is declared on the model it implements (``@implemented_by`` in :mod:`.koh`, the one table
of the pairs, :data:`~.koh.FAST_DENSITIES`), and :func:`flat_model` takes them from there.
Configurations these do not cover (custom priors, a discrepancy, GP emulators, ``corr_log``, a
Matern kernel, a linear mean) raise :class:`NotImplementedError` naming the option, and
:func:`flat_model` then tries the model's next declared density, then Pyro's potential of the
model (:mod:`.potential`), so a configuration never silently samples a different posterior.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from scipy.linalg import lapack

from solderpyro.calibration.emulators import FunctionEmulator
from solderpyro.calibration.flat import FlatModel, FlatSite, reject_unsupported, sigma_site
from solderpyro.calibration.koh import (
    SITE_CORR,
    SITE_SIGMA_C,
    SITE_T,
    JointInputs,
    ObsInputs,
    Priors,
)
from solderpyro.calibration.kronjoint import kron_joint

_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)


# ----------------------------------------------------------------------------- direct
def direct_flat(inp: ObsInputs, priors: Priors | None = None) -> FlatModel:
    """The direct posterior of :func:`~.koh.observation_model` (FunctionEmulator, flat prior on
    t_unit in the unit cube, sigma as :class:`~.koh.Priors` says) as a :class:`FlatModel`.

    Flat vector: ``t_unit (n_theta,)`` then ``sigma``. Cost per gradient: one evaluation of
    the computer model and one backward pass through it in torch (~0.05 ms for the seed's).

    Raises:
        NotImplementedError: a GP / low-rank emulator, a discrepancy or custom priors.
    """
    pr = priors or Priors()
    reject_unsupported(pr, {"emulators other than FunctionEmulator (the direct mode)":
                            not isinstance(inp.emulator, FunctionEmulator),
                            "discrepancy=True": inp.discrepancy})
    em = inp.emulator
    assert isinstance(em, FunctionEmulator)
    y_t = inp.y_obs
    y = y_t.detach().cpu().numpy().astype(float)
    n, p = y.shape[0], inp.theta_box.dim
    box, f, x_obs = inp.theta_box, em.f, em.x_obs
    sig, mu, sd = sigma_site(pr, y, p)
    sites = [FlatSite(SITE_T, p, True, 0.0, 1.0, 0), sig]

    # the theta box's unit-cube map in NumPy (as Box.from_unit): z = lo + u (hi - lo) on the
    # (log where flagged) scale, t = exp(z) where flagged, dt/du = (t or 1) (hi - lo)
    bnd = box.to_working(torch.tensor([box.lower, box.upper], dtype=torch.float64)).numpy()
    lo_f, w_f = bnd[0], bnd[1] - bnd[0]
    logm = np.asarray(box.log_scale, dtype=bool)

    leaf = torch.zeros(p, dtype=y_t.dtype, requires_grad=True)  # t, reused: 10 us a call
    leaf_np = leaf.detach().numpy()  # shares leaf's memory

    def loglik(x: np.ndarray) -> tuple[float, np.ndarray]:
        zt = lo_f + x[:p] * w_f
        t = np.where(logm, np.exp(np.where(logm, zt, 0.0)), zt)
        leaf_np[:] = t
        leaf.grad = None
        s = float(x[p])
        if not s * s * s > 0.0:  # sigma (or its cube) underflowed to 0: zero density
            return -math.inf, np.zeros(p + 1)
        with torch.enable_grad():
            mean = f(x_obs, leaf)
            r = y - mean.detach().numpy()
            if mean.requires_grad:  # J^T (y - f) / sigma^2 by one backward pass
                mean.backward(torch.from_numpy(r / (s * s)))
        gt = leaf.grad.numpy() if leaf.grad is not None else np.zeros(p)
        ss = float(r @ r)
        ll = -n * (math.log(s) + _HALF_LOG_2PI) - 0.5 * ss / (s * s)
        g = np.empty(p + 1)
        g[:p] = gt * np.where(logm, t, 1.0) * w_f
        g[p] = -n / s + ss / (s * s * s)
        return ll, g

    return FlatModel(sites, loglik, mu, sd, y_t.dtype)


# ------------------------------------------------------------------------------ joint
def joint_flat(inp: JointInputs, priors: Priors | None = None,
               structure: str = "auto") -> FlatModel:
    """The full-joint posterior of :func:`~.koh.joint_model` (beta integrated out) as a
    :class:`FlatModel`, with an analytic gradient.

    Flat vector: ``t_unit (n_theta,)``, ``sigma``, ``sigma_c``, ``corr (n_corr,)``. Supports the
    Gaussian kernel (shared or ARD correlation parameters), a constant mean, the default priors
    (``sigma_max``, ``sigma_known``, ``sigma_c_max``, ``corr_range``) and no discrepancy. Cost
    per gradient: one Cholesky factorization and inverse of the ``(m + n)`` square covariance
    plus a few elementwise passes over it (~0.1 ms for m + n = 58, 4.9 ms for 412); on a
    product design (every parameter set run at the same input points) of at least
    :data:`~.kronjoint.MIN_RUNS` runs, the same likelihood in Kronecker form
    (:mod:`.kronjoint`: 0.36 ms for 20 x 20 runs and 12 observations).

    Args:
        structure: "auto" (Kronecker on a product design of ``MIN_RUNS`` runs or more, else
            dense), "dense", or "kronecker" (ValueError unless the runs are a product design).

    Raises:
        NotImplementedError: any other kernel, mean, discrepancy, ``corr_log`` or custom priors.
    """
    if structure not in ("auto", "dense", "kronecker"):
        raise ValueError(f"structure={structure!r}; choose 'auto', 'dense' or 'kronecker'")
    pr = priors or Priors()
    reject_unsupported(pr, {f"kernel={inp.kernel!r}": inp.kernel != "gaussian",
                            f"mean={inp.mean!r}": inp.mean != "constant",
                            "discrepancy=True": inp.discrepancy,
                            "Priors.corr_log=True": pr.corr_log})
    d = inp.data
    p, nc = d.theta_box.dim, inp.n_corr
    sig, mu, sd = sigma_site(pr, d.y_obs.detach().cpu().numpy().astype(float), p)
    sc_hi = float(pr.sigma_c_max or 10 * inp.y_scale)
    lo_c, hi_c = pr.corr_range
    sites = [FlatSite(SITE_T, p, True, 0.0, 1.0, 0), sig,
             FlatSite(SITE_SIGMA_C, 1, False, 0.0, sc_hi, p + 1),
             FlatSite(SITE_CORR, nc, True, float(lo_c), float(hi_c), p + 2)]
    if structure != "dense":
        kron = kron_joint(inp, force=structure == "kronecker")
        if kron is not None:
            return FlatModel(sites, kron, mu, sd, inp.z.dtype)
        if structure == "kronecker":
            raise ValueError("structure='kronecker': the simulation runs are not a product "
                             "design (every parameter set at the same input points, each once)")
    return FlatModel(sites, dense_joint_loglik(inp), mu, sd, inp.z.dtype)


def dense_joint_loglik(inp: JointInputs) -> Any:
    """The full joint's log-likelihood (beta integrated out) and its analytic gradient by a
    dense Cholesky factorization of the ``(N, N)`` covariance, ``N = n_sim + n_obs`` (the
    derivation: this module's docstring), for :func:`joint_flat`.

    Returns:
        ``loglik(x) -> (ll, gradient (d,))`` on the constrained flat vector ``x = (t_unit
        (p,), sigma, sigma_c, corr (n_corr,))`` (sigma, sigma_c in output units); ``ll`` is
        ``-inf`` where the covariance is not positive definite.
    """
    u_sim = inp.u_sim.detach().cpu().numpy().astype(float)  # (m, n_x + p)
    u_xo = inp.u_xobs.detach().cpu().numpy().astype(float)  # (n, n_x)
    z = inp.z.detach().cpu().numpy().astype(float)  # (N,)
    m, n = u_sim.shape[0], u_xo.shape[0]
    nx, p = u_xo.shape[1], inp.data.theta_box.dim
    nn = m + n
    ys2 = inp.y_scale ** 2
    nug = inp.nugget
    th_sim = u_sim[:, nx:]  # (m, p)
    # fixed parts of the per-dimension squared distances: (nc, N, N) (summed when not ARD)
    u_fix = np.concatenate([u_sim, np.concatenate([u_xo, np.zeros((n, p))], 1)])
    dd = (u_fix[:, None, :] - u_fix[None, :, :]) ** 2  # (N, N, n_x + p)
    dd[m:, :, nx:] = 0.0  # the t columns of the observation rows are set per evaluation
    dd[:, m:, nx:] = 0.0
    d_fix = np.moveaxis(dd, -1, 0) if inp.ard else dd.sum(-1)[None]  # (nc, N, N)
    d_fix = np.ascontiguousarray(d_fix)
    diag = slice(None, None, nn + 1)  # the diagonal of an (N, N) array, flattened
    diag_obs = slice(m * (nn + 1), None, nn + 1)  # ... of its observation block
    tail_nx = slice(nx, None)

    def loglik(x: np.ndarray) -> tuple[float, np.ndarray]:
        t, sigma, sigma_c, corr = x[:p], x[p], x[p + 1], x[p + 2:]
        sc2 = sigma_c * sigma_c / ys2
        s2 = sigma * sigma / ys2
        dt = t[None, :] - th_sim  # (m, p)
        dt2 = dt * dt
        if inp.ard:
            k = np.tensordot(corr, d_fix, 1)  # sum_k corr_k D_k (N, N)
            add = dt2 @ corr[tail_nx]  # (m,)
        else:
            k = corr[0] * d_fix[0]
            add = corr[0] * dt2.sum(1)
        k[m:, :m] += add[None, :]
        k[:m, m:] += add[:, None]
        np.negative(k, out=k)
        np.exp(k, out=k)  # R (N, N)
        cov = k * sc2
        cov.flat[diag] += sc2 * nug
        cov.flat[diag_obs] += s2
        # S is symmetric: its transpose is the Fortran-ordered view LAPACK wants (no copy)
        chol, info = lapack.dpotrf(cov.T, lower=1, overwrite_a=1)
        if info != 0:
            return -math.inf, np.zeros_like(x)
        half_logdet = float(np.log(chol.diagonal()).sum())
        low, info = lapack.dpotri(chol, lower=1, overwrite_c=1)  # lower triangle of S^-1
        if info != 0:
            return -math.inf, np.zeros_like(x)
        inv = low + low.T
        inv.flat[diag] *= 0.5  # S^-1 (N, N)
        s1 = inv.sum(1)  # S^-1 1
        gg = float(s1.sum())  # G = 1^T S^-1 1
        a = inv @ z
        a -= s1 * (float(s1 @ z) / gg)  # P z
        ll = -half_logdet - 0.5 * math.log(gg) - 0.5 * float(z @ a)
        # 2 W = a a^T - P = [a, s1] [a, s1 / G]^T - S^-1 (one BLAS call for the rank 2)
        w2 = np.stack([a, s1], 1) @ np.stack([a, s1 / gg])
        w2 -= inv
        wk = w2 * k  # 2 W o R
        g = np.empty_like(x)
        d_sc2 = 0.5 * (float(wk.sum()) + nug * float(w2.flat[diag].sum()))
        g[p] = float(w2.flat[diag_obs].sum()) * sigma / ys2
        g[p + 1] = d_sc2 * 2.0 * sigma_c / ys2
        # d/d corr_k of sc2 exp(-sum corr D) = -sc2 D_k R; the t part of D_k lies in the
        # observation-simulation blocks (twice, by symmetry)
        cs = wk[m:, :m].sum(0)  # (m,) = 2 sum_obs W o R
        if inp.ard:
            g[p + 2:] = -0.5 * sc2 * np.tensordot(d_fix, wk, ((1, 2), (0, 1)))
            g[p + 2 + nx:] -= sc2 * (cs @ dt2)
            ct = corr[tail_nx]
        else:
            g[p + 2] = -sc2 * (0.5 * float(np.vdot(d_fix[0], wk)) + float(cs @ dt2.sum(1)))
            ct = corr[0]
        # d/d t_k: R_ij (i obs, j sim) = exp(-... - c_k (t_k - th_jk)^2), both halves
        g[:p] = -2.0 * sc2 * ct * (cs @ dt)
        return ll, g

    return loglik


def flat_model(model: Any, args: tuple) -> Any:
    """The flat log density :func:`~.mcmc.run_nuts` samples for ``model(*args)``: the first
    analytic density declared for the model (:func:`~.koh.implemented_by`; for :mod:`.koh`'s
    models: :func:`direct_flat`, :func:`joint_flat` here, :func:`~.reduced.pca_flat`) that
    covers the configuration, else Pyro's potential of the model with autograd
    (:func:`~.potential.torch_flat`). Both are the same posterior on the same unconstrained
    scale.

    Args:
        model: any Pyro model; args: its arguments (``(inputs, priors)`` for :mod:`.koh`'s).
    Returns:
        a :class:`~.flat.FlatModel` or :class:`~.potential.TorchFlat` (``dim``,
        ``logp_and_grad``, ``to_samples``, ``to_unconstrained``).
    """
    from solderpyro.calibration.koh import fast_densities
    from solderpyro.calibration.potential import torch_flat

    for density in fast_densities(model):
        try:
            return density(*args)
        except NotImplementedError:  # not this configuration: the next declared one
            continue
    return torch_flat(model, args)
