"""Calibrate any simulator from CSV tables of its runs (the ``solderpyro koh`` command)."""

from __future__ import annotations

import csv
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from solderpyro.calibration.api import calibrate_joint, calibrate_modular
from solderpyro.calibration.data import CalibrationData, InputAxes
from solderpyro.calibration.mcmc import Posterior, format_summary, write_summary
from solderpyro.config.settings import SamplerSettings
from solderpyro.io.text import read_text
from solderpyro.params import Box
from solderpyro.surrogate import GPSurrogate

log = logging.getLogger("solderpyro")

#: chains that agree to this R-hat are taken as converged: the specimen calibration's bar
#: (:class:`~solderpyro.config.settings.SamplerSettings` ``max_rhat``, 1.01)
MAX_RHAT = SamplerSettings.max_rhat
#: the smallest bulk ESS per chain of a converged run: the specimen calibration's bar
#: (``min_ess``, 400) over its default chains (4): 100
MIN_ESS_PER_CHAIN = SamplerSettings.min_ess / SamplerSettings.chains


def read_columns(path: str | Path, columns: Sequence[str], what: str) -> torch.Tensor:
    """Read named numeric columns of a CSV into ``(n_rows, len(columns))`` float64.

    Errors name the file, the missing column or the bad cell (or the first byte that is not
    UTF-8 text).
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{what} file {p} does not exist")
    text = read_text(p, f"{what} file")
    rows = list(csv.reader(line for line in text.splitlines(keepends=True)
                           if not line.startswith("#")))
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
    (and ``surrogate_loo.png`` in modular mode) into ``out``, and last ``index.html``, the
    entry page linking them (:func:`~solderpyro.reporting.index.write_index`). Chains that
    have not converged (:func:`convergence_problems`) are warned on, in the log and on the
    index page.

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
    problems = convergence_problems(rows, post.n_chains)
    for msg in problems:
        log.warning("koh: %s", msg)
    if propose:
        _propose(data, gp, post, propose, outd, list(x), list(t))
    from solderpyro.reporting.index import write_index

    verdict = (f"Kennedy-O'Hagan calibration ({mode}) of {', '.join(t)} from {data.n_sim} "
               f"runs ({tables.sim}) and {data.n_obs} observations ({tables.obs}): the chains "
               f"{'have not converged' if problems else 'converged'} ({_extremes(rows)}; "
               f"{post.n_chains} chains, divergences per chain {post.divergences})")
    write_index(outd, verdict=("bad" if problems else "good", verdict), warnings=problems)
    return post


def _extremes(rows: Sequence[dict]) -> str:
    """"largest R-hat 1.002 (t); smallest bulk ESS 812 (sigma)" of summary ``rows``."""
    rh = [r for r in rows if math.isfinite(float(r["r_hat"]))]
    es = [r for r in rows if math.isfinite(float(r["ess_bulk"]))]
    out = []
    if rh:
        r = max(rh, key=lambda r: float(r["r_hat"]))
        out.append(f"largest R-hat {float(r['r_hat']):.3f} ({r['parameter']})")
    if es:
        r = min(es, key=lambda r: float(r["ess_bulk"]))
        out.append(f"smallest bulk ESS {float(r['ess_bulk']):.0f} ({r['parameter']})")
    return "; ".join(out) or "no R-hat or ESS"


def convergence_problems(rows: Sequence[dict], n_chains: int) -> list[str]:
    """What says the chains have not converged: a parameter's R-hat above :data:`MAX_RHAT`
    or its bulk ESS under :data:`MIN_ESS_PER_CHAIN` per chain (the specimen calibration's
    bars), or no R-hat at all (one chain), one message per criterion; empty where none.

    Args:
        rows: :meth:`Posterior.summary` rows (``parameter``, ``r_hat``, ``ess_bulk``).
        n_chains: the chains sampled.
    """
    min_ess = MIN_ESS_PER_CHAIN * n_chains
    split = [r for r in rows if float(r["r_hat"]) > MAX_RHAT]
    unchecked = [r for r in rows if math.isnan(float(r["r_hat"]))]
    short = [r for r in rows if not float(r["ess_bulk"]) >= min_ess]  # NaN too
    out = []
    if unchecked:
        out.append(f"no R-hat for {', '.join(str(r['parameter']) for r in unchecked)} "
                   f"({n_chains} chain(s)): convergence is not checked; run 2 or more chains "
                   f"(--chains)")
    if split:
        out.append("the chains disagree: R-hat " + ", ".join(
            f"{r['parameter']} {float(r['r_hat']):.3f}" for r in split)
            + f" > {MAX_RHAT:g}; run longer chains (--warmup, --draws) and look at traces.png")
    if short:
        out.append("too few effective draws: bulk ESS " + ", ".join(
            f"{r['parameter']} {float(r['ess_bulk']):.0f}" for r in short)
            + f" < {min_ess:.0f} ({MIN_ESS_PER_CHAIN:.0f} per chain x {n_chains} chains); "
            f"the intervals are uncertain: run more draws (--draws)")
    return out


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
