"""The exact marginal likelihood of the surrogate's batch of GPs, with its analytic gradient.

:func:`mll_closure` is what the hyperparameter fit (:func:`solderpyro.surrogate.gp._fit_mll`)
hands to ``torch.optim.LBFGS``: the loss GPyTorch's ``ExactMarginalLogLikelihood`` gives,
summed over the batch (``-sum_k log N(z_k; m_k, s_k R(l_k) + noise_k I) / n``), and its
gradient in the model's raw parameters, written into their ``.grad``. The values of the
hyperparameters come from the model's own constraints (GPyTorch's transforms, kept in torch
and differentiated by autograd: they are a few dozen numbers); the ``(k, n, n)`` part is NumPy
and LAPACK:

    d log p / d theta = 1/2 tr((alpha alpha^T - K^-1) dK/dtheta),   alpha = K^-1 (z - m),

with ``dK/d noise = I``, ``dK/ds = R`` and, for the lengthscale of input ``l``,
``dK/dl_l = s rho'(r) Delta_l^2 / l_l^3`` (Matern 5/2: ``rho' = 5/3 (1 + sqrt5 r)
exp(-sqrt5 r)``; Gaussian: ``rho' = rho``).

Why: GPyTorch's autograd through the batched Cholesky took 13 ms per evaluation on the loop's
recalibration surrogate (20 components, 98 runs; 459 evaluations, 6.1 s per fit, 7.4 ms of it
``backward``); this takes ~3 ms (BENCHMARKS.md, "Per-gradient and per-round costs of the
calibration"; ``tests/unit/surrogate/test_gp.py`` checks loss and gradient against GPyTorch's
autograd). Where a Cholesky factorization fails (GPyTorch would add jitter) the closure evaluates
GPyTorch's own loss for that step.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from scipy.linalg.lapack import dpotrf, dpotri, dpotrs

_LOG_2PI = math.log(2.0 * math.pi)


def mll_closure(model: Any, opt: torch.optim.Optimizer, fallback: Callable[[], torch.Tensor]
                ) -> Callable[[], torch.Tensor]:
    """An L-BFGS closure: the batch's summed negative exact marginal log likelihood per
    training point, gradient in ``.grad``.

    Args:
        model: a :class:`~solderpyro.surrogate.gp.BatchGP` (float64, CPU): ``k`` GPs on the
            same ``(n, d)`` training inputs (its ``train_inputs[0]`` is ``(k, n, d)``), targets
            ``(k, n)``.
        opt: the optimizer (its gradients are zeroed here).
        fallback: GPyTorch's own closure, used for an evaluation whose Cholesky fails.
    Returns:
        ``closure() -> loss`` (a 0-dim tensor).
    """
    x = model.train_inputs[0][0].detach().cpu().numpy()  # (n, d)
    Z = model.train_targets.detach().cpu().numpy()  # (k, n)
    k, n = Z.shape
    D = np.ascontiguousarray(((x[:, None, :] - x[None, :, :]) ** 2).reshape(n * n, -1))
    gaussian = isinstance(model.covar_module.base_kernel, _rbf())
    lin = hasattr(model.mean_module, "weights")
    # symmetric contractions from lower triangles: sum_ij A_ij B_ij = sum_ij W_ij A_ij B_ij
    # with W = 2 below the diagonal, 1 on it, 0 above (dpotri fills only the lower triangle)
    W = (2.0 * np.tril(np.ones((n, n)), -1) + np.eye(n)).reshape(n * n)
    diag = np.arange(n) * (n + 1)
    # (k, n^2) work arrays, allocated once: fresh ones cost more than the arithmetic (page
    # faults on every large temporary)
    r2, R, dR, K, M = (np.empty((k, n * n)) for _ in range(5))

    def closure() -> torch.Tensor:
        opt.zero_grad()
        noise = model.likelihood.noise_covar.noise.reshape(k)  # (k,)
        os_ = model.covar_module.outputscale.reshape(k)  # (k,)
        ls = model.covar_module.base_kernel.lengthscale.reshape(k, -1)  # (k, d or 1)
        if lin:
            w, b = model.mean_module.weights, model.mean_module.bias  # (k, d, 1), (k, 1)
            mean = (torch.as_tensor(x) @ w)[..., 0] + b  # (k, n)
        else:
            mean = model.mean_module.constant.reshape(k, 1).expand(k, n)
        nz, s, L = (t.detach().numpy() for t in (noise, os_, ls))
        r = Z - mean.detach().numpy()  # (k, n)
        inv_l2 = np.broadcast_to(1.0 / L**2, (k, x.shape[1]))
        np.matmul(inv_l2, D.T, out=r2)  # squared scaled distances (k, n^2)
        if gaussian:
            np.multiply(r2, -0.5, out=R)
            np.exp(R, out=R)
            np.copyto(dR, R)
        else:  # with a = sqrt5 r: rho = (1 + a + a^2/3) e^-a, rho' / r... = 5/3 (1 + a) e^-a
            np.multiply(r2, 5.0, out=r2)
            np.sqrt(r2, out=r2)  # a
            np.negative(r2, out=K)
            np.exp(K, out=K)  # e^-a
            np.multiply(r2, 1.0 / 3.0, out=R)
            np.add(R, 1.0, out=R)
            np.multiply(R, r2, out=R)
            np.add(R, 1.0, out=R)
            np.multiply(R, K, out=R)
            np.add(r2, 1.0, out=dR)
            np.multiply(dR, K, out=dR)
            np.multiply(dR, 5.0 / 3.0, out=dR)
        np.multiply(R, s[:, None], out=K)
        K[:, diag] += nz[:, None]
        alpha = np.empty((k, n))
        logdet = np.empty(k)
        for j in range(k):
            c, info = dpotrf(K[j].reshape(n, n), lower=1, clean=0)
            if info != 0:
                return fallback()
            logdet[j] = 2.0 * np.log(np.diagonal(c)).sum()
            alpha[j] = dpotrs(c, r[j], lower=1)[0]
            ci, info = dpotri(c, lower=1)
            if info != 0:
                return fallback()
            M[j] = ci.reshape(n * n)
        ll = -0.5 * (np.einsum("ki,ki->k", r, alpha) + logdet + n * _LOG_2PI)
        # M = (alpha alpha^T - K^-1) on the lower triangle, weighted by W
        np.subtract((alpha[:, :, None] * alpha[:, None, :]).reshape(k, n * n), M, out=M)
        np.multiply(M, W, out=M)
        g_noise = 0.5 * M[:, diag].sum(1)
        g_os = 0.5 * np.einsum("ki,ki->k", M, R)
        np.multiply(M, dR, out=M)
        g_ls = 0.5 * s[:, None] * (M @ D) / L**3  # (k, d) or (k, 1) after the sum
        if L.shape[1] == 1:
            g_ls = g_ls.sum(1, keepdims=True)
        scale = -1.0 / n  # the loss: -sum_k ll_k / n
        outs, grads = [noise, os_, ls], [g_noise, g_os, g_ls]
        if lin:
            outs += [w, b]
            grads += [(x.T @ alpha.T).T[:, :, None], alpha.sum(1)[:, None]]
        else:
            outs.append(model.mean_module.constant.reshape(k))
            grads.append(alpha.sum(1))
        torch.autograd.backward(outs, [torch.as_tensor(scale * g).reshape(o.shape)
                                       for o, g in zip(outs, grads, strict=True)])
        return torch.as_tensor(float(scale * ll.sum()), dtype=torch.float64)

    return closure


def _rbf() -> type:
    import gpytorch

    return gpytorch.kernels.RBFKernel
