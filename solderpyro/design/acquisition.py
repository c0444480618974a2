"""Acquisition functions that place FE runs where the surrogate's code uncertainty matters for
the calibration, and the optimizer that proposes a q-batch from them.

Both criteria are BoTorch ``AcquisitionFunction`` s over the unit cube of the FE's parameter
box, ``forward(X (b, q, d)) -> (b,)`` (larger is better), and both integrate over the current
posterior of the parameters (``mc_points``: posterior draws, unit cube):

- :func:`integrated_code_variance`: BoTorch's ``qNegIntegratedPosteriorVariance`` with a
  scalarization that makes it ``-E_post[sum_i var(eta_i(theta) | runs + X) / sigma^2]``: the
  surrogate's variance at the observed outputs, weighted by the noise, that remains after the
  q new runs (Seo et al. 2000; BoTorch's active-learning function).
- :class:`qIntegratedLogLikVariance`: likelihood-aware. The code uncertainty of the
  Gaussian log-likelihood ``l(theta) = -|y - eta(theta)|^2 / (2 sigma^2)`` at each posterior
  draw, after the q new runs: with ``eta = m + S B z``, ``z ~ N(mu, diag v)``,
  ``Var l = sum_k g_k^2 v_k + 1/2 sum_kl M_kl^2 v_k v_l``, ``g = (S B)^T (y - m) / sigma^2``,
  ``M = (S B)^T (S B) / sigma^2`` (exact for a quadratic form of a Gaussian). Runs go where
  the code error would move the posterior, not merely where the GP is unsure
  (cf. Jarvenpaa et al. 2019, "Efficient acquisition rules for model-based ABC").

The variance of a GP with fixed hyperparameters after new runs does not depend on their
outputs, so one fantasy (BoTorch's default dummy sampler) makes both criteria exact.

BoTorch is imported where it is used, in :func:`~solderpyro.surrogate.gp.botorch_imports`
(importing this module leaves a host's GPyTorch settings as they were), so
:class:`qIntegratedLogLikVariance`, a BoTorch subclass, is defined on first access. Both
criteria, and :func:`propose`, evaluate in BoTorch's settings
(:func:`~solderpyro.surrogate.exact_linear_algebra`) whatever the host's.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import torch

from solderpyro.design.model import observed_weights
from solderpyro.surrogate import GPSurrogate, exact_linear_algebra
from solderpyro.surrogate.gp import botorch_imports

if TYPE_CHECKING:
    from botorch.acquisition import AcquisitionFunction
    from botorch.acquisition.active_learning import qNegIntegratedPosteriorVariance
    from botorch.models.model import Model

CRITERIA = ("loglik", "variance")
OPTIMIZERS = ("optimize", "draws")


def integrated_code_variance(model: Model, mc_points: torch.Tensor, weights: torch.Tensor,
                             X_pending: torch.Tensor | None = None
                             ) -> qNegIntegratedPosteriorVariance:
    """BoTorch's ``qNegIntegratedPosteriorVariance``, scalarized to the noise-weighted code
    variance at the observed outputs.

    Args:
        model: :func:`~solderpyro.design.model.botorch_model` of the surrogate (k outputs).
        mc_points: ``(N, d)`` posterior draws of the FE parameters, unit cube.
        weights: ``(k,)`` from :func:`~solderpyro.design.model.observed_weights` (1/um^2 x
            um^2: dimensionless per unit coefficient variance).
        X_pending: ``(m, d)`` runs already asked for and not yet back.

    Returns:
        acquisition with ``forward(X (b, q, d)) -> (b,)`` = ``-mean_j sum_k a_k v_k(theta_j |
        runs + X)``, in chi-square units (dimensionless).
    """
    if weights.ndim != 1 or weights.shape[0] != model.num_outputs:
        raise ValueError(f"weights must have shape ({model.num_outputs},), got "
                         f"{tuple(weights.shape)}")
    with botorch_imports():
        from botorch.acquisition.objective import ScalarizedPosteriorTransform
    pt = ScalarizedPosteriorTransform(weights.clamp_min(0).sqrt().to(mc_points))
    return _code_variance_class()(model, mc_points, posterior_transform=pt, X_pending=X_pending)


@functools.cache
def _code_variance_class() -> type[qNegIntegratedPosteriorVariance]:
    """BoTorch's ``qNegIntegratedPosteriorVariance``, evaluated in BoTorch's settings
    (:func:`~solderpyro.surrogate.exact_linear_algebra`) whatever the host's; defined on first
    use (BoTorch is imported only where it is used)."""
    with botorch_imports():
        from botorch.acquisition.active_learning import qNegIntegratedPosteriorVariance

    class IntegratedCodeVariance(qNegIntegratedPosteriorVariance):
        def forward(self, X: torch.Tensor) -> torch.Tensor:
            with exact_linear_algebra():
                return super().forward(X)

    return IntegratedCodeVariance


@functools.cache
def _loglik_variance_class() -> type[AcquisitionFunction]:
    """:class:`qIntegratedLogLikVariance`, defined on first use (BoTorch is imported only where
    it is used, in :func:`~solderpyro.surrogate.gp.botorch_imports`)."""
    with botorch_imports():
        from botorch.acquisition import AcquisitionFunction
        from botorch.sampling.normal import SobolQMCNormalSampler
        from botorch.utils.transforms import concatenate_pending_points, t_batch_mode_transform

    class qIntegratedLogLikVariance(AcquisitionFunction):
        """``-E_post[Var_code l(theta) | runs + X]``: the posterior-weighted code variance of the
        Gaussian log-likelihood that remains after the q-batch ``X`` (nats^2).

        Args:
            model: :func:`~solderpyro.design.model.botorch_model` of the surrogate (k outputs).
            mc_points: ``(N, d)`` posterior draws, unit cube.
            grad: ``(N, k)`` ``g_j = (S B)^T (y - m(theta_j)) / sigma^2`` (1/coefficient unit).
            curvature: ``(k, k)`` ``M = (S B)^T (S B) / sigma^2``.
            X_pending: ``(m, d)`` runs asked for and not yet back.
        See :func:`loglik_terms` for ``grad`` and ``curvature``.
        """

        def __init__(self, model: Model, mc_points: torch.Tensor, grad: torch.Tensor,
                     curvature: torch.Tensor, X_pending: torch.Tensor | None = None) -> None:
            super().__init__(model=model)
            k = model.num_outputs
            if mc_points.ndim != 2 or grad.shape != (mc_points.shape[0], k) \
                    or curvature.shape != (k, k):
                raise ValueError(f"qIntegratedLogLikVariance: need mc_points (N, d), grad (N, {k}) "
                                 f"and curvature ({k}, {k}); got {tuple(mc_points.shape)}, "
                                 f"{tuple(grad.shape)}, {tuple(curvature.shape)}")
            self.register_buffer("mc_points", mc_points)
            self.register_buffer("grad2", grad.square())
            self.register_buffer("curv2", curvature.square())
            self.sampler = SobolQMCNormalSampler(sample_shape=torch.Size([1]))
            self.set_X_pending(X_pending)

        @concatenate_pending_points
        @t_batch_mode_transform()  # type: ignore[arg-type]
        def forward(self, X: torch.Tensor) -> torch.Tensor:
            """``X (b, q, d)`` unit cube -> ``(b,)``, in BoTorch's settings
            (:func:`~solderpyro.surrogate.exact_linear_algebra`) whatever the host's."""
            with exact_linear_algebra():
                fm = self.model.fantasize(X=X, sampler=self.sampler)  # type: ignore[operator]
                # one point at a time (as qNegIntegratedPosteriorVariance does for several
                # outputs): a joint posterior over the N points would form (b, k, N, N)
                # covariances
                bdims = tuple(1 for _ in X.shape[:-2])
                mc = self.mc_points.view(-1, *bdims, 1, X.size(-1))  # type: ignore[operator]
                v = fm.posterior(mc).variance  # (N, 1, b, 1, k); mc: (N, 1, 1, d)
            v = v.reshape(v.shape[0], -1, v.shape[-1]).transpose(0, 1)  # (b, N, k)
            var = (self.grad2 * v).sum(-1) + 0.5 * torch.einsum("bnk,kl,bnl->bn", v,
                                                                  self.curv2, v)
            return -var.mean(-1)

    qIntegratedLogLikVariance.__qualname__ = qIntegratedLogLikVariance.__name__  # for pickle
    return qIntegratedLogLikVariance


def __getattr__(name: str) -> Any:
    """``qIntegratedLogLikVariance``: the likelihood-aware acquisition (a BoTorch
    ``AcquisitionFunction``, ``qIntegratedLogLikVariance(model, mc_points, grad, curvature,
    X_pending=None)``); the class is defined on first access, when BoTorch is imported."""
    if name == "qIntegratedLogLikVariance":
        return _loglik_variance_class()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def loglik_terms(gp: GPSurrogate, theta: torch.Tensor, y: torch.Tensor, sigma: float,
                 offset: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """``grad (N, k)`` and ``curvature (k, k)`` of :class:`qIntegratedLogLikVariance`.

    Args:
        gp: the fitted surrogate of the ``n_y`` observed outputs (um).
        theta: ``(N, d)`` posterior draws of the FE parameters, physical units.
        y: ``(n_y,)`` the observations, um. sigma: the noise sd, um.
        offset: ``(N, n_y)`` what observation-side effects add at each draw, um (or None).
    """
    with torch.no_grad():
        mean, _ = gp.predict(theta)
    mean = mean.reshape(theta.shape[0], -1)
    r = y.to(mean) - mean - (0 if offset is None else offset.to(mean))
    sv = gp.basis * gp.std.scale[:, None]  # (n_y, k)
    return r @ sv / sigma**2, sv.T @ sv / sigma**2


class _PosteriorColumns:
    """Blocks of a fitted surrogate's coefficient posterior covariance over points ``S``
    (``cov0 = K_SS - K_SX K_XX^-1 K_XS`` per component), formed only where asked for.

    Args:
        gp: a fitted :class:`~solderpyro.surrogate.GPSurrogate`; S: ``(M, d)`` physical.
    """

    def __init__(self, gp: GPSurrogate, S: torch.Tensor) -> None:
        self.gp = gp
        self.u, _, self.v = gp.cross_covariance(S)  # (k, M, d'), (k, n, M)
        self.os = gp.factors().outputscale  # (k,)

    def diag(self) -> torch.Tensor:
        """``(k, M)`` the variances."""
        return self.os[:, None] - self.v.square().sum(-2)

    def block(self, a: slice, b: slice) -> torch.Tensor:
        """``(k, |a|, |b|)`` the covariance between the points ``a`` and ``b``."""
        kab = self.os[:, None, None] * self.gp.correlation(self.u[:, a], self.u[:, b])
        return kab - self.v[:, :, a].transpose(-1, -2) @ self.v[:, :, b]

    def column(self, i: int) -> torch.Tensor:
        """``(k, M)`` the covariance of every point with point ``i``."""
        return self.block(slice(None), slice(i, i + 1))[:, :, 0]


class AcquisitionPoints(NamedTuple):
    """The parameter sets one greedy choice of runs works over (physical units).

    Attributes:
        draws: ``(N, d)`` posterior draws the criterion integrates over.
        candidates: ``(C, d)`` the runs to choose from.
        pending: ``(P, d)`` runs asked for and not yet back (None: none).
    """

    draws: torch.Tensor
    candidates: torch.Tensor
    pending: torch.Tensor | None = None


def greedy_draws(gp: GPSurrogate, criterion: str, points: AcquisitionPoints, q: int,
                 sigma: float, y: torch.Tensor | None = None, offset: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, float]:
    """The best ``q`` of ``points.candidates`` for a criterion, chosen greedily one at a time
    (each choice joins the pending runs before the next), in closed form.

    This is BoTorch's ``optimize_acqf_discrete`` on :func:`integrated_code_variance`
    (``criterion="variance"``) or :class:`qIntegratedLogLikVariance` (``"loglik"``): the same
    choices and values (tested), without building a fantasy model per candidate. With fixed
    hyperparameters a new run at ``c`` lowers the coefficients' posterior covariance by the
    rank-1 term ``S[:, c] S[c, :] / (S[c, c] + tau)``, so one posterior covariance over the
    draws, candidates and pending runs ``(k, N + C + P, N + C + P)`` and rank-1 updates give
    every candidate's value. Measured on the full-field case (k = 8 components, 256 draws,
    512 candidates, q = 8): BoTorch's fantasies took 353 s per round, this 1.4 s
    (5-6 s with 15-16 components).

    Args:
        gp: the fitted surrogate. criterion: ``"variance"`` or ``"loglik"``.
        points: the posterior draws ``(N, d)`` integrated over, the candidates ``(C, d)`` and
            the pending runs ``(P, d)`` (:class:`AcquisitionPoints`, physical).
        q: how many to choose (<= C). sigma: noise sd (um).
        y, offset: the data ``(n_y,)`` and observation-side offsets ``(N, n_y)`` (for
            ``"loglik"``).

    Returns:
        the chosen candidates' indices ``(q,)`` and the acquisition's value at the q-batch.
    """
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be one of {CRITERIA}, got {criterion!r}")
    mc_theta, cand_theta, pending = points
    N, C = len(mc_theta), len(cand_theta)
    if not 1 <= q <= C:
        raise ValueError(f"greedy_draws: need 1 <= q <= {C} candidates, got q={q}")
    parts = [mc_theta, cand_theta] + ([pending] if pending is not None and len(pending) else [])
    P = len(parts[2]) if len(parts) > 2 else 0
    S = torch.cat(parts).to(torch.float64)
    with torch.no_grad():
        cols = _PosteriorColumns(gp, S)
        tau = gp.factors().noise  # (k,)
        # the coefficients' posterior covariance is kept as the prior one minus the rank-1
        # terms of the runs conditioned on so far, and only its diagonal and draws x
        # candidates block are formed: the full (k, N + C + P, N + C + P) matrix and its
        # rank-1 updates took 2.9 s per design round on one thread (20 components, 256 draws,
        # 512 candidates, q 8 + 4 pending; 6.8 s on a busy machine), this 0.5 s, the same choices
        # (benchmarks/round_costs.py; tests/unit/design/test_loop.py)
        d_all = cols.diag()  # (k, N + C + P)
        X = cols.block(slice(0, N), slice(N, N + C))  # (k, N, C)
        W: list[torch.Tensor] = []  # the rank-1 terms w (k, N + C + P), cov = cov0 - sum w w^T

        def condition(i: int) -> None:
            nonlocal d_all, X
            c = cols.column(i)  # (k, N + C + P)
            for w in W:
                c = c - w * w[:, i:i + 1]
            w = c / (c[:, i:i + 1] + tau[:, None]).sqrt()
            W.append(w)
            d_all = d_all - w.square()
            X = X - w[:, :N, None] * w[:, None, N:N + C]

        for i in range(N + C, N + C + P):
            condition(i)
        if criterion == "loglik":
            if y is None:
                raise ValueError("greedy_draws(criterion='loglik') needs the data y")
            g, M = loglik_terms(gp, mc_theta, y, sigma, offset)
            g2, M2 = g.square().T, M.square()  # (k, N), (k, k)
        else:
            a = observed_weights(gp, sigma)  # (k,)
        chosen: list[int] = []
        val = torch.zeros(C, dtype=torch.float64)
        for _ in range(q):
            vn = (d_all[:, :N, None] - X.square() / (d_all[:, None, N:N + C] + tau[:, None, None])
                  ).clamp_min(0.0)  # (k, N, C): variance at the draws after adding c
            if criterion == "variance":
                val = -(a[:, None, None] * vn).sum(0).mean(0)
            else:
                val = -((g2[:, :, None] * vn).sum(0)
                        + 0.5 * torch.einsum("knc,kl,lnc->nc", vn, M2, vn)).mean(0)
            if chosen:
                val[chosen] = -float("inf")
            b = int(val.argmax())
            chosen.append(b)
            condition(N + b)
    return torch.tensor(chosen), float(val[chosen[-1]])


def propose(acq: AcquisitionFunction, d: int, q: int, method: str = "optimize",
            candidates: torch.Tensor | None = None, seed: int = 0
            ) -> tuple[torch.Tensor, float]:
    """The next q runs: ``(q, d)`` in the unit cube, and the acquisition's value there.

    Args:
        acq: an acquisition function over ``[0, 1]^d``.
        method: ``"optimize"``: BoTorch's ``optimize_acqf`` (sequential greedy q-batch,
            L-BFGS-B from 8 restarts; raw samples and the ``candidates`` as starting points);
            ``"draws"``: ``optimize_acqf_discrete`` over ``candidates`` (e.g. posterior draws).
        candidates: ``(N, d)`` unit-cube points (required for ``"draws"``).
        seed: for the raw samples of ``"optimize"``.
    """
    if method not in OPTIMIZERS:
        raise ValueError(f"propose: method must be one of {OPTIMIZERS}, got {method!r}")
    if q < 1:
        raise ValueError(f"propose: q must be >= 1, got {q}")
    with botorch_imports():
        from botorch.optim import optimize_acqf, optimize_acqf_discrete
    mcp = getattr(acq, "mc_points", None)
    dt: torch.dtype = mcp.dtype if isinstance(mcp, torch.Tensor) else torch.float64
    with exact_linear_algebra():  # BoTorch's settings, whatever the host's
        if method == "draws":
            if candidates is None or candidates.shape[0] < q:
                raise ValueError("propose(method='draws') needs at least q candidates")
            X, val = optimize_acqf_discrete(acq, q, candidates.to(dt), unique=True)
            return X.detach(), float(acq(X[None]).item())
        bounds = torch.stack([torch.zeros(d, dtype=dt), torch.ones(d, dtype=dt)])
        with torch.random.fork_rng():
            torch.manual_seed(seed)
            np.random.seed(seed % 2**32)
            X, _ = optimize_acqf(acq, bounds, q=q, num_restarts=8, raw_samples=128,
                                 sequential=True, options={"maxiter": 100, "seed": seed})
        return X.detach(), float(acq(X[None]).item())
