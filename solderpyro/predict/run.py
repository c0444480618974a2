"""``predict``: what the calibration's posterior says happens inside the solder.

The FE runs at ``N`` posterior draws of a calibration (evenly spread through its reported
draws) on the calibration's specimen and cycle, or on the user's assembly and cycle (config
overrides), with the solder's fields recorded (:mod:`solderpyro.fem.record`). From them, per
cycle, the inelastic strain energy density and the inelastic strain in the solder's interface
rows and the whole joint, the largest stresses, and histories at chosen points, each as a
median and a 95 % band over the draws with the share due to the Anand constants
(:mod:`solderpyro.predict.quantities`). What was solved is kept chunk by chunk in
``OUT/fields`` (:mod:`solderpyro.predict.forward`); the files are written by
:mod:`solderpyro.predict.write`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from solderpyro.predict.forward import Fields
from solderpyro.predict.quantities import Band, Region
from solderpyro.predict.target import Target

log = logging.getLogger(__name__)

#: posterior draws a prediction solves by default: the 2.5 and 97.5 % quantiles of 200 draws
#: move by about 1.5 % of the band's width between repeats (binomial error of the order
#: statistics), against ~1.5 min of FE on the reference mesh (two cores)
N_DRAWS = 200


@dataclass(frozen=True)
class HistoryPoint:
    """A solder Gauss point whose stress and strain histories are kept.

    Attributes:
        name: its label. xy: ``(2,)`` mm, where it was asked for; at: ``(2,)`` mm, the Gauss
            point used (the nearest). index: ``(element, Gauss point)``.
    """

    name: str
    xy: tuple[float, float]
    at: tuple[float, float]
    index: tuple[int, int]


@dataclass
class Prediction:
    """What :func:`predict` computed.

    Attributes:
        target: the model solved (:class:`~solderpyro.predict.target.Target`).
        fields: the draws' recorded fields (:class:`~solderpyro.predict.forward.Fields`).
        cycle_ends: ``(n_cycles,)`` s. regions: the averaging regions.
        per_cycle: ``{(quantity, region): (N, n_cycles)}`` per draw: ``dW`` MPa and ``dp``
            (1), region ``upper_interface``, ``lower_interface``, ``joint`` or ``max``.
        bands: ``{(quantity, region, cycle): Band}`` (cycle 1-based; 0 for whole-prediction
            maxima ``vm_max``, ``tau_max`` MPa, ``rate_max`` 1/s, region ``max``).
        points: the history points. weight, xy: ``(n_e, n_qp)`` mm^2 and ``(n_e, n_qp, 2)``
            mm of the solder's Gauss points.
        temperature: ``{"calibration": (lo, hi), "target": (lo, hi)}`` degC.
        rate: ``{"calibration": r, "target": r}`` 1/s, the largest equivalent inelastic
            strain rate in the joint (the median draw's).
        notes: what the user should know. seconds: wall time of the FE.
    """

    target: Target
    fields: Fields
    cycle_ends: tuple[float, ...]
    regions: list[Region]
    per_cycle: dict[tuple[str, str], np.ndarray]
    bands: dict[tuple[str, str, int], Band]
    points: list[HistoryPoint]
    weight: np.ndarray
    xy: np.ndarray
    temperature: dict[str, tuple[float, float]]
    rate: dict[str, float]
    notes: list[str]
    seconds: float


def default_points(problem: Any) -> dict[str, tuple[float, float]]:
    """History points of a specimen's solder layer (mm): at the free end, on the upper
    interface and at mid-thickness, and at mid-thickness in the middle of the joint."""
    lay = next(x for x in problem.layers if x.material == "solder")
    x_end = float(getattr(lay, "x1", None) or problem.half_length)
    mid = 0.5 * (lay.y0 + lay.y1)
    return {"end, upper interface": (x_end, float(lay.y1)), "end, mid-thickness": (x_end, mid),
            "middle, mid-thickness": (0.5 * x_end, mid)}


def _model(setup: Any, space: Any, effects: tuple[str, ...], bounds: Any) -> Any:
    from solderpyro.effects import effect_set
    from solderpyro.specimen import SpecimenModel

    return SpecimenModel(setup.problem, space, setup.times,
                         effects=effect_set(effects, setup.times, bounds),
                         dtype=setup.dtype, device=setup.device)


def _marks(model: Any) -> tuple[tuple[float, ...], bool]:
    """The marks to read the cumulative fields at: the cycle ends, after ``0`` when a
    pre-history precedes the cycle (whose work then does not count in the first cycle)."""
    ends = tuple(float(t) for t in model.problem.cycle.cycle_ends)
    pre = model.fx_fe is not None and model.fx_fe.pre_history() is not None
    return ((0.0, *ends) if pre else ends), pre


def _signature(model: Any, marks: tuple[float, ...], points: Sequence[tuple[int, int]]) -> str:
    from solderpyro.compute.runstore import config_hash

    h = config_hash(model.problem, model.times, False, model.dtype, model.fx_fe or ())
    return f"{h}|{model.param_names}|{marks}|{tuple(points)}"


def predict(run_dir: str | Path, overrides: Sequence[str] = (), n_draws: int = N_DRAWS,
            points: dict[str, tuple[float, float]] | None = None,
            out: str | Path | None = None, theta: np.ndarray | None = None,
            chunk: int | None = None, progress: bool = True,
            layer_mm: float | None = None) -> Prediction:
    """Predict the solder's stresses, strains and inelastic work at a calibration's posterior
    draws, and write them (CSV, ArviZ, figures, an index page) to ``out``.

    Args:
        run_dir: a ``solderpyro calibrate`` run directory.
        overrides: config overrides of the target on top of the run's own (e.g.
            ``["specimen=die_attach", "mesh=die_attach", "loading=jedec_m40_125"]``); none:
            the calibration's specimen and cycle.
        n_draws: posterior draws to solve, spread evenly through the run's draws.
        points: history points ``{name: (x, y)}`` mm (the nearest solder Gauss point each);
            default :func:`default_points`.
        out: the output directory (default ``run_dir/prediction``).
        theta: ``(N, n_draw_cols)`` parameter rows to solve instead of the posterior's (the
            run's draw columns, physical units).
        chunk: draws per batched solve (default :data:`~solderpyro.predict.forward.CHUNK`).
        progress: log each chunk.
        layer_mm: thickness of the interface layers the work is averaged over, mm (default
            a quarter of the solder's thickness).
    Raises:
        ValueError: a bad ``n_draws`` or point, another alloy than the calibration's (naming
            both), ``theta`` of the wrong width.
        FileNotFoundError: ``run_dir`` lacks a file ``calibrate`` writes (named).
    """
    from solderpyro.config.compose import build, compose
    from solderpyro.design.loop import spread_indices
    from solderpyro.diagnose.load import load_run
    from solderpyro.fem.record import nearest_points
    from solderpyro.predict import forward, quantities, target, write

    if theta is None and (not isinstance(n_draws, int) or n_draws < 1):
        raise ValueError(f"n_draws must be a positive integer, got {n_draws!r}")
    run_dir = Path(run_dir)
    out = Path(out) if out is not None else run_dir / "prediction"
    loaded = load_run(run_dir)
    info, run_setup, draws = loaded["info"], loaded["setup"], loaded["draws"]
    names = list(draws["names"])
    tgt_setup = build(compose([*info.overrides, *overrides]))
    tgt = target.build_target(run_setup, tuple(info.effects), names, tgt_setup)
    notes = list(tgt.notes)
    if not info.checks.fe_ok:
        notes.append("the calibration's FE check did not accept its posterior (run.json "
                     "checks.fe_check): the bands inherit whatever is wrong there")
    if theta is None:
        rows = draws["theta"][spread_indices(len(draws["theta"]), n_draws)]
    else:
        rows = np.atleast_2d(np.asarray(theta, dtype=np.float64))
        if rows.shape[1] != len(names):
            raise ValueError(f"theta must have {len(names)} columns ({', '.join(names)}), got "
                             f"{rows.shape[1]}")
    rows = rows[:, list(tgt.columns)]
    model = _model(tgt_setup, run_setup.space, tgt.effects, run_setup.effect_bounds)
    marks, pre = _marks(model)
    pts = dict(points) if points is not None else default_points(tgt_setup.problem)
    idx = nearest_points(model.solver, list(pts.values())) if pts else ()
    regs, weight, g = solder_regions(model, layer_mm)
    hist = [HistoryPoint(k, (float(v[0]), float(v[1])), (float(g[i, q, 0]), float(g[i, q, 1])),
                         (i, q))
            for (k, v), (i, q) in zip(pts.items(), idx, strict=True)]
    for h in hist:
        d = float(np.hypot(h.at[0] - h.xy[0], h.at[1] - h.xy[1]))
        if d > 0.5 * max(float(np.ptp(g[..., 1])), 1e-3) + _cell(g):
            raise ValueError(f"history point {h.name!r} at {h.xy} mm is {d:.3g} mm from the "
                             "nearest solder point: give a point inside the solder")

    def report(done: int, total: int, sec: float, hit: bool) -> None:
        if progress:
            log.info("predict: %d/%d draws (%s, %.1f s)", done, total,
                     "read from the cache" if hit else "solved", sec)

    t0 = time.perf_counter()
    f = forward.solve_draws(model, marks, tuple(idx), rows, out / "fields",
                            _signature(model, marks, idx), chunk or forward.CHUNK,
                            on_chunk=report)
    seconds = time.perf_counter() - t0
    bad = int((~f.ok).sum())
    if bad:
        why = sorted({str(r) for r in f.reasons if r})
        notes.append(f"{bad} of {len(f.ok)} draws failed to solve and are left out ({why[0]})")
    per, dW = cycle_quantities(f, pre, regs, weight)
    k = run_setup.space.n_theta
    consts, others = rows[:, :k], rows[:, k:]
    bands = {(q, r, c + 1): quantities.band(v[:, c], consts, others)
             for (q, r), v in per.items() for c in range(v.shape[1])}
    for q in ("vm_max", "tau_max", "rate_max"):
        v = np.where(f.ok, getattr(f, q).reshape(len(f.ok), -1).max(1), np.nan)
        bands[(q, "max", 0)] = quantities.band(v, consts, others)
    t_cal = target.temperature_range(run_setup, draws["theta"], tuple(names))
    t_tgt = target.temperature_range(tgt_setup, rows, tgt.names)
    rate = {"target": bands[("rate_max", "max", 0)].median}
    rate["calibration"] = (_calibration_rate(run_setup, tgt, rows)
                           if tgt.transfer else rate["target"])
    if t_tgt[0] < t_cal[0] - 0.5 or t_tgt[1] > t_cal[1] + 0.5:
        notes.append(f"the target's temperatures ({t_tgt[0]:g} to {t_tgt[1]:g} degC) leave "
                     f"the range the calibration saw ({t_cal[0]:g} to {t_cal[1]:g} degC): the "
                     "constants are extrapolated there")
    if rate["target"] > 1.1 * rate["calibration"]:
        notes.append(f"the target's largest inelastic strain rate ({rate['target']:.3g} 1/s) "
                     f"exceeds the calibration's ({rate['calibration']:.3g} 1/s) "
                     f"{rate['target'] / rate['calibration']:.3g} times: the constants are "
                     "extrapolated in rate")
    for n in notes:
        log.warning("predict: %s", n)
    pred = Prediction(tgt, f, tuple(model.problem.cycle.cycle_ends), regs, per, bands, hist,
                      weight, g, {"calibration": t_cal, "target": t_tgt}, rate, notes, seconds)
    write.write_prediction(pred, out, run_dir, list(overrides), dW)
    return pred


def solder_regions(model: Any, layer_mm: float | None = None
                   ) -> tuple[list[Region], np.ndarray, np.ndarray]:
    """The averaging regions of ``model``'s solder (:func:`~solderpyro.predict.quantities.
    regions`, interface layers ``layer_mm`` thick), its Gauss points' weights ``(n_e, n_qp)``
    mm^2 and positions ``(n_e, n_qp, 2)`` mm."""
    from solderpyro.fem.record import gauss_points
    from solderpyro.predict import quantities

    slv = model.solver
    solder = next(x for x in model.problem.layers if x.material == "solder")
    el = np.asarray(slv.el_solder)
    ny = np.asarray(slv.mesh.nodes)[np.asarray(slv.mesh.elems)[el]][..., 1]
    el_y = np.stack([ny.min(1), ny.max(1)], 1)
    weight = slv.wdet[:slv.n_s].detach().cpu().double().numpy()
    regs = quantities.regions(el_y, float(solder.y0), float(solder.y1), weight.shape[1],
                              layer_mm)
    return regs, weight, gauss_points(slv).cpu().double().numpy()


def cycle_quantities(f: Fields, pre: bool, regs: list[Region], weight: np.ndarray
                     ) -> tuple[dict[tuple[str, str], np.ndarray], np.ndarray]:
    """Per draw and cycle, ``{("dW" | "dp", region | "max"): (N, n_cycles)}`` of the fields
    ``f`` read at the cycle ends (after a mark at 0 where ``pre``: a pre-history), and the
    per-cycle work density at the Gauss points ``(N, n_cycles, n_e, n_qp)`` MPa (failed draws
    NaN)."""
    from solderpyro.predict import quantities

    work = np.where(f.ok[:, None, None, None], f.work, np.nan)
    peq = np.where(f.ok[:, None, None, None], f.eps_p_eq, np.nan)
    k0 = 1 if pre else 0
    dW = quantities.per_cycle(work[:, k0:], work[:, 0] if pre else None)
    dp = quantities.per_cycle(peq[:, k0:], peq[:, 0] if pre else None)
    per: dict[tuple[str, str], np.ndarray] = {}
    for qname, x in (("dW", dW), ("dp", dp)):
        for rname, v in quantities.averages(x, weight, regs).items():
            per[(qname, rname)] = v
    return per, dW


def _cell(g: np.ndarray) -> float:
    """The largest spacing of neighbouring solder Gauss points along x, mm (a point asked
    for within it of the solder is inside)."""
    x = np.unique(np.round(g[..., 0].ravel(), 9))
    return float(np.diff(x).max()) if len(x) > 1 else 0.0


def _calibration_rate(run_setup: Any, tgt: Target, rows: np.ndarray) -> float:
    """The largest equivalent inelastic strain rate (1/s) in the calibration's own specimen
    and cycle at the median of the draws (its effects kept as the target keeps them)."""
    from solderpyro.predict.forward import solve_fields

    model = _model(run_setup, run_setup.space, tgt.effects, run_setup.effect_bounds)
    mid = np.median(rows, 0)[None]
    f = solve_fields(model, (), (), torch.as_tensor(mid, dtype=model.dtype, device=model.device))
    return float(np.nanmax(f.rate_max))


__all__ = ["HistoryPoint", "N_DRAWS", "Prediction", "default_points", "predict"]
