"""The DOE runner over the crash-safe run store: :func:`run_doe`.

:func:`run_doe` reads back the rows of a design already in the run store
(:mod:`solderpyro.compute.runstore`: the layout on disk, the records and their hashes), hands the
others to the current executor (:mod:`solderpyro.compute.executor`) in batches, and stores each
member of a batch as soon as the batch finishes: a kill loses at most the batch in flight, and a
rerun computes only what is missing. Failed members are stored (``ok=False`` with the reason)
and are not recomputed on rerun.

Imports run one way: runstore <- executor <- store.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from solderpyro.compute.executor import current_executor
from solderpyro.compute.runstore import RunRecord, RunStore, param_hash
from solderpyro.params import ANAND_NAMES

log = logging.getLogger(__name__)

__all__ = ["DoeOptions", "DoeResult", "run_doe"]


@dataclass(frozen=True)
class DoeOptions:
    """How :func:`run_doe` runs the rows it must solve.

    Attributes:
        batch_size: members per FE solve (>= 1).
        progress: a tqdm bar over the batches.
        executor: where the batches run (:mod:`solderpyro.compute.executor`); None: the
            current one (:func:`~solderpyro.compute.executor.current_executor`).
    """

    batch_size: int = 64
    progress: bool = True
    executor: Any = None


@dataclass(frozen=True)
class DoeResult:
    """Outputs of :func:`run_doe`, row for row with its ``params``.

    Attributes:
        params: ``(n, 9 + n_eff)`` Anand constants (then effect parameters), float64.
        V: ``(n, n_time, n_out)`` um, float64; NaN rows for failed members.
        ok: ``(n,)`` bool. reasons: ``n`` strings, empty for converged members.
        n_reused: rows served from the store as it was before this call.
        n_computed: distinct parameter sets solved in this call.
        times: ``(n_time,)`` output times, s (sorted); names: ``n_out`` output labels.
        fe_s: FE seconds summed over the batches solved in this call, where they ran.
    """

    params: torch.Tensor
    V: torch.Tensor
    ok: torch.Tensor
    reasons: list[str]
    n_reused: int
    n_computed: int
    times: tuple[float, ...] = ()
    names: tuple[str, ...] = ()
    fe_s: float = 0.0

    @property
    def n_failed(self) -> int:
        """The number of rows whose member failed (``~ok``)."""
        return int((~self.ok).sum())


def _assemble(keys: list[str], found: dict[str, RunRecord],
              times: list[float]) -> tuple[torch.Tensor, torch.Tensor, list[str], tuple]:
    names = {found[k].names for k in keys}
    if len(names) > 1:
        raise ValueError(f"stored runs of one config have different outputs: {names}")
    nm = names.pop() if names else ()
    V = torch.full((len(keys), len(times), len(nm)), float("nan"), dtype=torch.float64)
    ok = torch.zeros(len(keys), dtype=torch.bool)
    reasons = []
    for i, k in enumerate(keys):
        r = found[k]
        ok[i] = r.ok
        reasons.append(r.reason)
        if r.ok:
            V[i] = torch.as_tensor(r.V, dtype=torch.float64)
    return V, ok, reasons, nm


def run_doe(solver: Any, store: RunStore, cfg_hash: str, params: torch.Tensor,
            times: Sequence[float], param_names: Sequence[str] | None = None,
            options: DoeOptions | None = None) -> DoeResult:
    """Solve a design ``params (n, 9 + n_eff)``, reusing and filling ``store``.

    Rows already stored under ``cfg_hash`` (converged or failed) are read back; the others are
    solved in batches of at most ``options.batch_size`` by the executor (``options.executor``,
    default :func:`~solderpyro.compute.executor.current_executor`: in this process unless a Dask
    cluster was chosen), and every member of a batch is stored as soon as that batch finishes.
    Duplicate rows are solved once.

    Args:
        solver: a :class:`~solderpyro.fem.solver.SpecimenSolver` (anything with
            ``.solve(params (b, 9 + n_eff), times, progress=False)``), or a callable
            ``(params (b, 9 + n_eff), times) -> SolveResult``-like (``V (b, n_time, n_out)``,
            ``ok (b,)``, ``reasons``, ``times``, ``names``). It must match ``cfg_hash`` (see
            :meth:`RunStore.register`); the store cannot check that.
        store: the run store. cfg_hash: hash of the problem, times, field flag, dtype
            and effects.
        params: ``(n, 9 + n_eff)`` Anand constants in ANAND_NAMES order (MPa, K, 1/s), then
            the effects' parameters (``n_eff = 0`` without effects), finite.
        times: output times, s.
        param_names: names of the ``params`` columns; default ``solver.param_names(times)``
            when the solver has it, else ANAND_NAMES.
        options: batch size, progress bar and executor (:class:`DoeOptions`; None: its
            defaults).

    Returns:
        :class:`DoeResult`; V is NaN for failed members, whose reasons are logged.
    """
    opt = options or DoeOptions()
    batch_size = opt.batch_size
    p = torch.as_tensor(params).detach().to(device="cpu", dtype=torch.float64)
    tt = sorted(float(t) for t in times)
    pnames = _param_names(solver, tt, param_names)
    if p.ndim != 2 or p.shape[1] != len(pnames):
        raise ValueError(f"params must have shape (n, {len(pnames)}) ({', '.join(pnames)}), "
                         f"got {tuple(p.shape)}")
    if not torch.isfinite(p).all():
        raise ValueError("params contain NaN or inf")
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    keys = [param_hash(row) for row in p]
    first = {k: i for i, k in reversed(list(enumerate(keys)))}  # key -> first row holding it
    found: dict[str, RunRecord] = {}
    for k, i in first.items():
        rec = store.get(cfg_hash, p[i])
        if rec is not None and np.allclose(rec.times, tt, rtol=0, atol=1e-9):
            found[k] = rec
        elif rec is not None:
            log.warning("run store: %s has times %s, not %s; recomputing",
                        store.path(cfg_hash, p[i]), rec.times, tt)
    n_reused = sum(k in found for k in keys)
    missing = [first[k] for k in sorted(first, key=first.__getitem__) if k not in found]
    where = store.config_dir(cfg_hash)
    log.debug("run store %s: %d of %d runs reused, %d parameter sets to compute", where,
              n_reused, len(keys), len(missing))
    from tqdm.auto import tqdm

    ex = opt.executor if opt.executor is not None else current_executor()
    batches = [[missing[j] for j in part] for part in ex.partition(len(missing), batch_size)]
    fe_s = 0.0
    with tqdm(total=len(missing), desc=f"FE runs ({ex.describe()})", unit="run",
              disable=not opt.progress or not batches) as bar:
        for out in ex.run(solver, [p[rows] for rows in batches], tt, pnames, store, cfg_hash):
            for rec in out.records:
                if not (out.stored or out.lost):
                    store.put(cfg_hash, rec)
                found[param_hash(rec.values)] = rec
            fe_s += out.seconds if math.isfinite(out.seconds) else 0.0
            bar.update(len(out.records))
    V, ok, reasons, names = _assemble(keys, found, tt)
    _log_summary(where, n_reused, len(missing), ok, reasons, p, pnames)
    return DoeResult(p, V, ok, reasons, n_reused, len(missing), tuple(tt), names, fe_s)


def _param_names(solver: Any, times: list[float],
                 names: Sequence[str] | None) -> list[str]:
    if names is not None:
        out = [str(n) for n in names]
    elif callable(getattr(solver, "param_names", None)):
        out = list(solver.param_names(times))
    else:
        out = list(ANAND_NAMES)
    if out[:len(ANAND_NAMES)] != list(ANAND_NAMES) or len(set(out)) != len(out):
        raise ValueError(f"param_names must be ANAND_NAMES followed by distinct effect "
                         f"parameter names, got {out}")
    return out


def _log_summary(where: Path, n_reused: int, n_computed: int, ok: torch.Tensor,
                 reasons: list[str], p: torch.Tensor, names: Sequence[str]) -> None:
    bad = torch.nonzero(~ok).squeeze(1).tolist()
    # one DEBUG line per call (the calibration makes dozens; its stages log their FE counts);
    # failed rows are warnings
    log.debug("DOE done: %d rows, %d reused, %d computed, %d failed; store %s", len(ok),
              n_reused, n_computed, len(bad), where)
    for i in bad[:10]:
        log.warning("DOE row %d failed (params %s): %s",
                    i, dict(zip(names, p[i].tolist(), strict=True)), reasons[i])
    if len(bad) > 10:
        log.warning("... and %d more failed rows", len(bad) - 10)
