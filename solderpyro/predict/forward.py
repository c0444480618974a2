"""The FE at the posterior draws, with the solder's fields recorded, in chunks kept on disk.

Each chunk of draws is one batched solve (split over this machine's cores, one thread each:
:func:`~solderpyro.compute.executor.split_rows`) with a
:class:`~solderpyro.fem.record.SolderRecorder`; its fields are written to
``CACHE/chunk-<hash>.npz`` as soon as it is done, the hash covering the configuration, the
marks, the history points and the chunk's rows. A rerun (after a crash, or with more draws)
reads the chunks it finds and solves the others: nothing computed is lost.
"""

from __future__ import annotations

import hashlib
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch

log = logging.getLogger(__name__)

#: draws per batched solve (and per cached chunk): a 32-member batch keeps the default mesh's
#: per-member cost near its large-batch value while a crash loses at most one chunk
CHUNK = 32


@dataclass
class Fields:
    """The recorded fields of ``N`` draws (numpy, float64; NaN rows: failed draws).

    Attributes:
        theta: ``(N, n)`` the draws' parameters (the target's columns).
        ok: ``(N,)`` bool; reasons: ``(N,)`` str, why a draw's solve failed ("" if not).
        V: ``(N, n_time, n_out)`` um, the displacements at the target's outputs.
        work, eps_p_eq: ``(N, K, n_e, n_qp)`` inelastic work density (MPa) and equivalent
            inelastic strain at the ``K`` marks.
        vm_max, tau_max: ``(N, n_e, n_qp)`` MPa; rate_max: ``(N, n_e, n_qp)`` 1/s.
        t: ``(S,)`` s; sigma, eps_p: ``(N, S, n_p, 4)`` Mandel stress (MPa) and inelastic
            strain histories at the history points; p_hist: ``(N, S, n_p)`` their accumulated
            equivalent inelastic strain.
    """

    theta: np.ndarray
    ok: np.ndarray
    reasons: np.ndarray
    V: np.ndarray
    work: np.ndarray
    eps_p_eq: np.ndarray
    vm_max: np.ndarray
    tau_max: np.ndarray
    rate_max: np.ndarray
    t: np.ndarray
    sigma: np.ndarray
    eps_p: np.ndarray
    p_hist: np.ndarray

    @classmethod
    def concat(cls, parts: list[Fields]) -> Fields:
        """The parts' draws in order (``t`` from the first)."""
        kw = {f.name: np.concatenate([getattr(p, f.name) for p in parts])
              for f in fields(cls) if f.name != "t"}
        return cls(t=parts[0].t, **kw)

    def save(self, path: Path) -> None:
        """Write ``path`` (an ``.npz``) atomically."""
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, **{f.name: getattr(self, f.name) for f in fields(self)})
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: Path) -> Fields:
        """Read what :meth:`save` wrote."""
        with np.load(path) as z:
            return cls(**{f.name: z[f.name] for f in fields(cls)})


def solve_fields(model: Any, marks: tuple[float, ...], points: tuple[tuple[int, int], ...],
                 theta: torch.Tensor) -> Fields:
    """One batched solve of ``model`` (:class:`~solderpyro.specimen.SpecimenModel`) at
    ``theta`` ``(b, n_theta)`` with the solder's fields recorded at ``marks`` (s) and
    ``points`` (``(element, Gauss point)``)."""
    from solderpyro.fem.record import SolderRecorder

    rec = SolderRecorder(marks, points)
    with torch.no_grad():
        res = model.solver.solve(model.solver_rows(theta[:, model.fe_cols]), model.times,
                                 recorder=rec)
    f = res.extra["solder"]

    def a(x: torch.Tensor) -> np.ndarray:
        return x.detach().cpu().to(torch.float64).numpy()

    ok = a(res.ok.to(torch.float64)) > 0.5
    return Fields(a(theta), ok, np.array([str(r) for r in res.reasons]), a(res.V), a(f.work),
                  a(f.eps_p_eq), a(f.vm_max), a(f.tau_max), a(f.rate_max), a(f.t), a(f.sigma),
                  a(f.eps_p), a(f.p_hist))


def chunk_key(signature: str, theta: np.ndarray) -> str:
    """The cache key of a chunk: the configuration's ``signature`` and the rows ``theta``."""
    h = hashlib.sha256(signature.encode())
    h.update(np.ascontiguousarray(theta, dtype=np.float64).tobytes())
    return h.hexdigest()[:20]


def solve_draws(model: Any, marks: tuple[float, ...], points: tuple[tuple[int, int], ...],
                theta: np.ndarray, cache: Path, signature: str, chunk: int = CHUNK,
                on_chunk: Callable[[int, int, float, bool], None] | None = None) -> Fields:
    """The fields at every draw ``theta`` ``(N, n_theta)``, chunk by chunk: each chunk read
    from ``cache`` when a run before solved it, else solved on the current executor
    (:func:`~solderpyro.compute.executor.current_executor`: this machine's cores, or one Dask
    task per chunk) and written there as soon as it is done.

    Args:
        model: the target's :class:`~solderpyro.specimen.SpecimenModel`.
        marks, points: as :class:`~solderpyro.fem.record.SolderRecorder` takes them.
        signature: what the fields depend on besides the rows (configuration, marks, points).
        chunk: draws per batched solve.
        on_chunk: called ``(draws done, total, seconds, from_cache)`` after each chunk.
    """
    from solderpyro.compute.executor import current_executor

    cache.mkdir(parents=True, exist_ok=True)
    n = len(theta)
    rows = [theta[j:j + chunk] for j in range(0, n, chunk)]
    paths = [cache / f"chunk-{chunk_key(signature, r)}.npz" for r in rows]
    parts: list[Fields | None] = [None] * len(rows)
    done = 0
    for i, path in enumerate(paths):
        if path.exists():
            try:
                parts[i] = Fields.load(path)
            except (OSError, ValueError, KeyError) as e:
                log.warning("cached chunk %s unreadable (%s): solved again", path, e)
        if parts[i] is not None:
            done += len(rows[i])
            if on_chunk is not None:
                on_chunk(done, n, 0.0, True)
    todo = [i for i, p in enumerate(parts) if p is None]
    batches = [torch.as_tensor(rows[i], dtype=model.dtype, device=model.device) for i in todo]

    def solve(p: torch.Tensor) -> Fields:
        return solve_fields(model, marks, points, p)

    t0 = time.perf_counter()
    for k, got in current_executor().map(solve, batches, what="a prediction's chunk"):
        i = todo[k]
        f = Fields.concat(got)
        f.save(paths[i])
        parts[i] = f
        done += len(rows[i])
        if on_chunk is not None:
            on_chunk(done, n, time.perf_counter() - t0, False)
    return Fields.concat([p for p in parts if p is not None])
