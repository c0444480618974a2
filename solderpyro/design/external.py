"""Proposals for simulators that run outside solderpyro (ANSYS, Abaqus, a lab code).

``solderpyro koh ... --propose q`` calibrates from the run table as usual, then writes the
next ``q`` parameter sets where the surrogate's code uncertainty at the observed outputs
matters most for the posterior (:func:`~.acquisition.integrated_code_variance`: BoTorch's
integrated posterior variance at the pairs (observed x, posterior draw of t), weighted by the
noise). Each proposed t is to be run at every observed x. The user appends the results to the
run table and calls again: the loop continues from the table, as surmise's ``supplement()``
does. Proposals not yet in the table are *pending*: they are kept in ``pending.csv`` and count
as runs already asked for (BoTorch's ``X_pending``), so they are never proposed twice.
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


def propose_external(gp: GPSurrogate, x_obs: torch.Tensor, theta_draws: torch.Tensor,
                     sigma: float, q: int, pending: torch.Tensor | None = None,
                     n_mc: int = 64, n_candidates: int = 128) -> torch.Tensor:
    """The next ``q`` parameter sets ``(q, n_t)`` for an external simulator.

    Args:
        gp: a scalar :class:`GPSurrogate` over the box (x columns, then t columns).
        x_obs: ``(n_obs, n_x)`` the observations' controllable inputs (``n_x`` may be 0).
        theta_draws: ``(N, n_t)`` posterior draws of t.
        sigma: the noise sd (output units). q: how many sets.
        pending: ``(m, n_t)`` sets asked for before and not yet run (not proposed again; their
            runs count as coming).
        n_mc: posterior draws the criterion integrates over; n_candidates: draws offered.

    Returns:
        ``(q, n_t)`` distinct posterior draws, greedy in the acquisition (each choice joins the
        pending runs before the next); to be run at every row of ``x_obs``.
    """
    from solderpyro.design.acquisition import integrated_code_variance
    from solderpyro.design.loop import spread_indices
    from solderpyro.design.model import botorch_model, observed_weights

    if q < 1:
        raise ValueError(f"--propose must be >= 1, got {q}")
    N = len(theta_draws)
    n_obs = len(x_obs)

    def pairs(th: torch.Tensor) -> torch.Tensor:  # (m, n_t) -> (m, n_obs, d) unit cube
        xx = x_obs[None].expand(len(th), -1, -1)
        tt = th[:, None, :].expand(-1, n_obs, -1)
        return gp.box.to_unit(torch.cat([xx, tt], -1).to(torch.float64))

    pick = spread_indices(N, n_mc)
    mc = pairs(theta_draws[pick]).reshape(-1, gp.box.dim)
    model = botorch_model(gp)
    w = observed_weights(gp, sigma)  # (1,): code variance in output units / sigma^2
    cidx = spread_indices(N, n_candidates)
    cand_t = theta_draws[cidx]
    if pending is not None and len(pending):  # never offer a pending set again
        cand_t = still_pending(cand_t, pending)
    if len(cand_t) < q:
        raise ValueError(f"only {len(cand_t)} distinct posterior draws are left to propose "
                         f"from; ask for fewer than {q}")
    cands = pairs(cand_t)  # (C, n_obs, d)
    pend = pairs(pending).reshape(-1, gp.box.dim) if pending is not None and len(pending) \
        else None
    chosen: list[int] = []
    for _ in range(q):
        acq = integrated_code_variance(model, mc, w, X_pending=pend)
        with torch.no_grad():
            vals = acq(cands)
        if chosen:
            vals[chosen] = -float("inf")
        best = int(vals.argmax())
        chosen.append(best)
        pend = cands[best] if pend is None else torch.cat([pend, cands[best]])
    return cand_t[chosen]


def write_proposal(out: Path, x_names: Sequence[str], t_names: Sequence[str],
                   x_obs: torch.Tensor, theta: torch.Tensor, pending_before: torch.Tensor
                   ) -> Path:
    """``out/proposed.csv`` (one row per observed x per proposed t: the runs to make) and
    ``out/pending.csv`` (every set asked for and not yet in the table)."""
    p = out / "proposed.csv"
    with p.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["run", *x_names, *t_names])
        for i, th in enumerate(theta.tolist()):
            for x in x_obs.tolist():
                w.writerow([i, *[f"{v:.10g}" for v in x], *[f"{v:.10g}" for v in th]])
    allp = torch.cat([pending_before, theta])
    with (out / PENDING).open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(list(t_names))
        for th in allp.tolist():
            w.writerow([f"{v:.10g}" for v in th])
    return p
