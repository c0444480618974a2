"""Proposals for simulators that run outside solderpyro (ANSYS, Abaqus, a lab code).

``solderpyro koh ... --propose q`` calibrates from the run table as usual, then writes the
next ``q`` parameter sets where the surrogate's code uncertainty at the observed outputs
matters most for the posterior: the posterior draws of t whose runs would most lower the GP's
variance at the pairs (observed x, posterior draw of t), averaged over the observations and
the draws, chosen one at a time (:func:`propose_external`). That variance is computed in
closed form from the GP's posterior covariance with rank-``n_u`` updates, not through
BoTorch; it ranks the candidates as :func:`~.acquisition.integrated_code_variance`
(BoTorch's ``qNegIntegratedPosteriorVariance``) with one output does. Each proposed t is to
be run at every distinct observed x (one run serves an x's replicated observations). The
user appends the results to the run table and calls again: the loop continues from the
table, as surmise's ``supplement()`` does. Proposals not yet in the table are *pending*:
they are kept in ``pending.csv`` and the GP is conditioned on them as runs already asked for
(the role of BoTorch's ``X_pending``), so they are never proposed twice.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path

import torch

from solderpyro.surrogate import GPSurrogate

PENDING = "pending.csv"


def read_pending(path: Path, t_names: Sequence[str]) -> torch.Tensor:
    """``(m, n_t)`` pending parameter sets of ``path`` (empty when there is none)."""
    if not path.is_file():
        return torch.zeros(0, len(t_names), dtype=torch.float64)
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    try:
        return torch.tensor([[float(r[n]) for n in t_names] for r in rows],
                            dtype=torch.float64).reshape(-1, len(t_names))
    except KeyError as e:
        raise ValueError(f"{path}: pending proposals lack column {e}; they were made for "
                         f"other calibration columns (delete the file to start afresh)"
                         ) from None


def still_pending(pending: torch.Tensor, theta_sim: torch.Tensor, rtol: float = 1e-6
                  ) -> torch.Tensor:
    """The rows of ``pending (m, n_t)`` that no run of ``theta_sim (n, n_t)`` matches (to
    ``rtol`` of each column's scale): the proposals whose results are not in the table yet."""
    if len(pending) == 0:
        return pending
    scale = theta_sim.abs().amax(0).clamp_min(1e-300)
    d = ((pending[:, None, :] - theta_sim[None]).abs() / scale).amax(-1)  # (m, n)
    return pending[~(d <= rtol).any(1)]


def distinct_x(x_obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The distinct rows of ``x_obs (n_obs, n_x)`` ``(n_u, n_x)`` and how many observations
    each has ``(n_u,)`` (replicated observations at one x share one simulator run). With no x
    columns (``n_x = 0``) every observation is at the one x: ``(1, 0)`` and ``[n_obs]``."""
    if x_obs.shape[1] == 0:
        return x_obs[:1], torch.tensor([len(x_obs)])
    xu, counts = torch.unique(x_obs, dim=0, return_counts=True)
    return xu, counts


def propose_external(gp: GPSurrogate, x_obs: torch.Tensor, theta_draws: torch.Tensor,
                     sigma: float, q: int, pending: torch.Tensor | None = None,
                     n_mc: int = 64, n_candidates: int = 128) -> torch.Tensor:
    """The next ``q`` parameter sets ``(q, n_t)`` for an external simulator.

    The criterion is the GP's variance at the pairs (observed x, posterior draw of t),
    averaged over ``n_mc`` draws and over the observations (a replicated x counts once per
    observation), left after a candidate's runs, one at each distinct observed x, and the
    pending ones; each step takes the candidate that lowers it most. No BoTorch function
    runs: the variance is computed in closed form, as
    :func:`~.acquisition.greedy_draws` does for single runs: with fixed hyperparameters a
    batch of runs at points ``I`` lowers the posterior covariance by
    ``S[:, I] (S[I, I] + tau)^-1 S[I, :]``, so one posterior covariance block (integration
    points x candidates' runs) and rank-``n_u`` updates give every candidate's value. The
    choices are those of :func:`~.acquisition.integrated_code_variance` (BoTorch's
    ``qNegIntegratedPosteriorVariance``) with one output, maximized over the candidates with
    the chosen runs as ``X_pending`` (tested), without the memory of its fantasy models: those
    form a full covariance over the integration points per candidate, 128 x 1,920^2 values
    (3.8 GB) for 30 observations.

    Args:
        gp: a scalar :class:`GPSurrogate` over the box (x columns, then t columns).
        x_obs: ``(n_obs, n_x)`` the observations' controllable inputs (``n_x`` may be 0).
        theta_draws: ``(N, n_t)`` posterior draws of t.
        sigma: the noise sd (output units); it scales the criterion, not the choice.
        q: how many sets.
        pending: ``(m, n_t)`` sets asked for before and not yet run (not proposed again; their
            runs count as coming).
        n_mc: posterior draws the criterion integrates over; n_candidates: draws offered.

    Returns:
        ``(q, n_t)`` distinct posterior draws, greedy in the acquisition (each choice joins the
        pending runs before the next); each to be run at every distinct row of ``x_obs``.
    """
    from solderpyro.design.loop import spread_indices

    if q < 1:
        raise ValueError(f"--propose must be >= 1, got {q}")
    del sigma  # a positive factor of every candidate's value
    xu, counts = distinct_x(x_obs.to(torch.float64))
    n_u = len(xu)
    N = len(theta_draws)
    th = theta_draws.to(torch.float64)
    mc_t = th[spread_indices(N, n_mc)]
    cand_t = th[spread_indices(N, n_candidates)]
    pend = pending.to(torch.float64) if pending is not None and len(pending) else th[:0]
    if len(pend):  # never offer a pending set again
        cand_t = still_pending(cand_t, pend)
    if len(cand_t) < q:
        raise ValueError(f"only {len(cand_t)} distinct posterior draws are left to propose "
                         f"from; ask for fewer than {q}")
    M, C = len(mc_t) * n_u, len(cand_t)

    def pairs(t: torch.Tensor) -> torch.Tensor:  # (m, n_t) -> (m * n_u, d), physical
        return torch.cat([xu[None].expand(len(t), -1, -1),
                          t[:, None, :].expand(-1, n_u, -1)], -1).reshape(-1, gp.box.dim)

    S = torch.cat([pairs(mc_t), pairs(cand_t), pairs(pend)])
    w = (counts.to(torch.float64) / counts.sum()).repeat(len(mc_t)) / len(mc_t)  # (M,)
    with torch.no_grad():
        u, _, v = gp.cross_covariance(S)  # (1, n_S, d'), (1, n, n_S)
        u, v = u[0], v[0]
        f = gp.factors()
        os_, tau = f.outputscale[0], f.noise[0]

        def cov0(a: slice | torch.Tensor, b: slice | torch.Tensor) -> torch.Tensor:
            return os_ * gp.correlation(u[a][None], u[b][None])[0] - v[:, a].T @ v[:, b]

        cand = slice(M, M + C * n_u)
        X = cov0(slice(0, M), cand)  # (M, C n_u): integration points x candidates' runs
        A = torch.stack([cov0(slice(M + c * n_u, M + (c + 1) * n_u),
                              slice(M + c * n_u, M + (c + 1) * n_u)) for c in range(C)])
        W: list[torch.Tensor] = []  # rank-n_u terms (n_S, n_u): cov = cov0 - sum W W^T

        def condition(idx: torch.Tensor) -> None:
            nonlocal X, A
            c = cov0(slice(None), idx)  # (n_S, n_u)
            for Wi in W:
                c = c - Wi @ Wi[idx].T
            L = torch.linalg.cholesky(c[idx] + tau * torch.eye(len(idx), dtype=c.dtype))
            Wn = torch.linalg.solve_triangular(L, c.T, upper=False).T  # (n_S, n_u)
            W.append(Wn)
            X = X - Wn[:M] @ Wn[cand].T
            Wc = Wn[cand].reshape(C, n_u, -1)
            A = A - Wc @ Wc.transpose(-1, -2)

        def block(i: int) -> torch.Tensor:  # the point indices of candidate/pending run i
            return torch.arange(i * n_u, (i + 1) * n_u)

        for j in range(len(pend)):
            condition(M + C * n_u + block(j))
        chosen: list[int] = []
        eye = tau * torch.eye(n_u, dtype=A.dtype)
        for _ in range(q):
            L = torch.linalg.cholesky(A + eye)  # (C, n_u, n_u)
            B = X.reshape(M, C, n_u).permute(1, 2, 0)  # (C, n_u, M)
            Z = torch.linalg.solve_triangular(L, B, upper=False)
            gain = (Z.square().sum(1) * w).sum(-1)  # (C,): the criterion's fall
            if chosen:
                gain[chosen] = -float("inf")
            best = int(gain.argmax())
            chosen.append(best)
            condition(M + block(best))
    return cand_t[chosen]


def write_proposal(out: Path, x_names: Sequence[str], t_names: Sequence[str],
                   x_obs: torch.Tensor, theta: torch.Tensor, pending_before: torch.Tensor
                   ) -> Path:
    """``out/proposed.csv`` (one row per run to make: each proposed t at each distinct
    observed x, in sorted x order; replicated observations share a run) and
    ``out/pending.csv`` (every set asked for and not yet in the table)."""
    p = out / "proposed.csv"
    xu, _ = distinct_x(x_obs)
    with p.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["run", *x_names, *t_names])
        for i, th in enumerate(theta.tolist()):
            for x in xu.tolist():
                w.writerow([i, *[f"{v:.10g}" for v in x], *[f"{v:.10g}" for v in th]])
    allp = torch.cat([pending_before, theta])
    with (out / PENDING).open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(list(t_names))
        for th in allp.tolist():
            w.writerow([f"{v:.10g}" for v in th])
    return p
