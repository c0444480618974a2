"""Calibrate any simulator from CSV tables of its runs (the ``solderpyro koh`` command)."""

from __future__ import annotations

import csv
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from solderpyro.calibration.api import calibrate_joint, calibrate_modular
from solderpyro.calibration.data import CalibrationData, InputAxes
from solderpyro.calibration.mcmc import Posterior, format_summary, write_summary
from solderpyro.params import Box
from solderpyro.surrogate import GPSurrogate

log = logging.getLogger("solderpyro")


def read_columns(path: str | Path, columns: Sequence[str], what: str) -> torch.Tensor:
    """Read named numeric columns of a CSV into ``(n_rows, len(columns))`` float64.

    Errors name the file, the missing column or the bad cell.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{what} file {p} does not exist")
    with p.open(newline="") as f:
        rows = list(csv.reader(line for line in f if not line.startswith("#")))
    if not rows:
        raise ValueError(f"{what} file {p} is empty")
    head = [h.strip() for h in rows[0]]
    missing = [c for c in columns if c not in head]
    if missing:
        raise ValueError(f"{what} file {p} has no column(s) {missing}; it has {head}")
    idx = [head.index(c) for c in columns]
    out = []
    for i, r in enumerate(rows[1:], start=2):
        if not any(cell.strip() for cell in r):
            continue
        try:
            out.append([float(r[j]) for j in idx])
        except (ValueError, IndexError) as e:
            raise ValueError(f"{what} file {p} line {i}: not a number in {columns} ({e})"
                             ) from None
    if not out:
        raise ValueError(f"{what} file {p} has no data rows")
    return torch.tensor(out, dtype=torch.float64).reshape(len(out), len(columns))


@dataclass(frozen=True)
class RunTables:
    """The two CSV tables of a calibration and the columns read from them.

    Attributes:
        sim: path of SIM.csv, the simulator's runs (columns ``x``, ``t``, ``y``).
        obs: path of OBS.csv, the observations (columns ``x``, ``y``).
        x: the controllable inputs' columns (in both tables).
        t: the calibrated inputs' columns (SIM.csv only; at least one).
        y: the response's column (in both tables, same units).
    """

    sim: str | Path
    obs: str | Path
    x: Sequence[str]
    t: Sequence[str]
    y: str


def koh_from_tables(tables: RunTables, out: str | Path, mode: str = "joint",
                    discrepancy: bool = False, propose: int = 0, **nuts: Any) -> Posterior:
    """Calibrate from the tables ``tables`` (:class:`RunTables`: SIM.csv with columns x, t, y
    and OBS.csv with columns x, y).

    The flat prior of t spans the range of the runs. ``mode`` is ``"joint"`` (the seed's full
    joint) or ``"modular"`` (GP fitted first, its LOO check written and warned on). Writes
    ``summary.csv`` (parameter, q2.5, median, mean, q97.5), ``posterior.nc``, ``traces.png``
    (and ``surrogate_loo.png`` in modular mode) into ``out``.

    ``propose > 0``: also write the next ``propose`` parameter sets for the simulator to
    ``out/proposed.csv`` (each t at every observed x; :mod:`solderpyro.design.external`),
    never one still pending from an earlier call (``out/pending.csv``).
    """
    x, t, y = tables.x, tables.t, tables.y
    if mode not in ("joint", "modular"):
        raise ValueError(f"--mode must be 'joint' or 'modular', got {mode!r}")
    if not t:
        raise ValueError("--t must name at least one calibration column")
    outd = Path(out)
    outd.mkdir(parents=True, exist_ok=True)
    s = read_columns(tables.sim, [*x, *t, y], "SIM")
    o = read_columns(tables.obs, [*x, y], "OBS")
    nx = len(x)
    data = CalibrationData.create(s[:, :nx], s[:, nx:-1], s[:, -1], o[:, :nx], o[:, -1],
                                  InputAxes(list(x), list(t)))
    log.info("%d runs, %d observations, calibrating %s (%s)", data.n_sim, data.n_obs,
             ", ".join(t), mode)
    if propose < 0:
        raise ValueError(f"--propose must be >= 0, got {propose}")
    gp = None
    if mode == "joint":
        post, _ = calibrate_joint(data, discrepancy=discrepancy, **nuts)
    else:
        post, gp = _modular(data, discrepancy, outd, nuts)
    rows = post.summary()
    write_summary(rows, outd / "summary.csv", ("parameter", "q2.5", "median", "mean", "q97.5"))
    post.save(outd / "posterior.nc")
    from solderpyro.reporting.plots import plot_traces

    plot_traces(post).savefig(outd / "traces.png", dpi=110)
    print(format_summary(rows))
    print(f"divergences per chain: {post.divergences}")
    if propose:
        _propose(data, gp, post, propose, outd, list(x), list(t))
    return post


def _propose(data: CalibrationData, gp: GPSurrogate | None, post: Posterior, q: int,
             outd: Path, x: list[str], t: list[str]) -> Path:
    """Write the next ``q`` simulator runs (``proposed.csv``) and the pending ones."""
    from solderpyro.design.external import (
        PENDING,
        distinct_x,
        propose_external,
        read_pending,
        still_pending,
        write_proposal,
    )

    if gp is None:  # joint mode: the code's GP over (x, t), as the modular mode fits it
        gp = _scalar_gp(data)
    before = read_pending(outd / PENDING, t)
    pend = still_pending(before, data.theta_sim)
    if len(before) > len(pend):
        log.info("propose: %d earlier proposal(s) now in the run table", len(before) - len(pend))
    if len(pend):
        log.info("propose: %d proposal(s) still pending (not proposed again)", len(pend))
    sigma = float(post.flat("sigma").median())
    th = propose_external(gp, data.x_obs, post.flat("t").to(torch.float64), sigma, q, pend)
    p = write_proposal(outd, x, t, data.x_obs, th, pend)
    n_x = len(distinct_x(data.x_obs)[0])
    print(f"\nproposed: {p} ({q} parameter set(s), each at the {n_x} distinct observed x; "
          f"append their results to the run table and call again)")
    return p


def _scalar_gp(data: CalibrationData) -> GPSurrogate:
    box = Box(data.x_box.names + data.theta_box.names, data.x_box.lower + data.theta_box.lower,
              data.x_box.upper + data.theta_box.upper)
    return GPSurrogate(box).fit(torch.cat([data.x_sim, data.theta_sim], -1), data.y_sim)


def _modular(data: CalibrationData, discrepancy: bool, outd: Path, nuts: dict
             ) -> tuple[Posterior, GPSurrogate]:
    gp = _scalar_gp(data)
    res = gp.loo()
    from solderpyro.reporting.plots import plot_validation

    plot_validation(res, "surrogate leave-one-out").savefig(outd / "surrogate_loo.png", dpi=110)
    gp.check(res)
    post, _ = calibrate_modular(gp, data.y_obs, data.theta_box, data.x_obs,
                                discrepancy=discrepancy, x_box=data.x_box, **nuts)
    return post, gp
