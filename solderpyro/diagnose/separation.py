"""Which measurement would tell apart effects whose FE refits fit the data equally well: the FE
at each refit (:func:`refit_predictions`) and over a richer set of outputs
(:func:`separation_options`), compared pairwise (:func:`separation`)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from solderpyro.diagnose.decide import APART_CHI2
from solderpyro.specimen import SpecimenModels


def refit_predictions(setup: Any, run_effects: tuple[str, ...], candidates: tuple[str, ...],
                      fits: dict[str, dict[str, Any]], meas: Any, fe: SpecimenModels
                      ) -> dict[str, np.ndarray]:
    """The FE at each refit of the first step (:func:`~.refits.refit_candidates`;
    ``"baseline"`` and every candidate), row for row with ``meas``; their rows were solved by
    the refits, so the run store serves them.

    Returns:
        model -> ``(n,)`` V, um.
    """
    from solderpyro.effects import effect_set
    from solderpyro.specimen import observation_index

    times = tuple(float(t) for t in meas.times())
    field = any(p not in setup.problem.points for p in meas.points())
    fx_all = effect_set(tuple(run_effects) + tuple(candidates), times, setup.effect_bounds)
    names = list(fits)
    X = torch.tensor(np.array([fits[m]["x"] for m in names]), dtype=torch.float64)
    res = fe.runs(X, times, field, fx_all, keep=len(run_effects))
    ti, oi = observation_index(meas, res.times, res.names)
    V = res.V.numpy()
    return {m: V[k][ti, oi] for k, m in enumerate(names) if res.ok[k]}


def separation(setup: Any, run_effects: tuple[str, ...], candidates: tuple[str, ...],
               fits: dict[str, dict[str, Any]], group: list[str], meas: Any,
               sigma: float, fe: SpecimenModels | None = None) -> dict[str, Any]:
    """Which measurement would tell the effects in ``group`` apart?

    Each effect's refit (:func:`~.refits.refit_candidates`: the FE with that effect on,
    refitted to the data) explains the data about equally well. The FE is run at each fit over
    a richer set of outputs (V at the points and on the 31 x 18 grid, at the measured and the
    extended times); for each candidate measurement (what it adds to the data) the fits'
    predictions are compared: where they differ by many noise sd, that measurement separates them
    (:func:`separation_options`).

    Args:
        fits: the first step's refits (rows laid out as calibrated parameters, then the
            candidates' parameters bound to the measured times); group: effect names (>= 2).
        meas: the data; sigma: noise sd, um; fe: the diagnosis's
            :class:`~solderpyro.specimen.SpecimenModels` (run store); None: solve directly.
    Returns:
        ``{"effects", "options": [{"measurement", "n_new", "pair", "rms_diff_um",
        "max_diff_um", "time_s", "point", "xy_mm", "chi2_apart"}, ...] best first,
        "advice"}``; chi2_apart is ``sum((V_a - V_b)^2) / sigma^2`` of the worst-separated pair
        over the new values (the expected chi-square by which the right effect would win;
        APART_CHI2 is needed).
    """
    options: list[dict[str, Any]] = []
    if len(group) >= 2:
        X = np.array([fits[g]["x"] for g in group])
        options, failed = separation_options(setup, tuple(run_effects) + tuple(candidates), X,
                                             list(group), meas, sigma, fe=fe)
        if failed is not None:
            return {"effects": list(group), "options": [],
                    "advice": f"the FE at the best fit of {', '.join(failed[0])} did not "
                              f"converge on the extended outputs ({failed[1]}); no separation "
                              "computed"}
    who = " and ".join([", ".join(group[:-1]), group[-1]]) if len(group) > 1 else group[0]
    if options and options[0]["chi2_apart"] >= APART_CHI2:
        o = options[0]
        advice = (f"to tell {who} apart, measure {o['measurement']}: their best fits to these "
                  f"data differ there by up to {o['max_diff_um']:.3g} um "
                  f"({o['max_diff_um'] / sigma:.1f} noise sd) at t = {o['time_s']:g} s, point "
                  f"{o['point']} {tuple(round(v, 2) for v in o['xy_mm'])} mm; expected "
                  f"chi-square between them {o['chi2_apart']:.0f} (>= {APART_CHI2:.1f} "
                  "decides)")
    else:
        advice = (f"{who}: no measurement tried (points at the extended times, the full field "
                  "at the measured and extended times) separates their best fits by the "
                  f"chi-square {APART_CHI2:.1f} needed; another test (a different temperature "
                  "cycle or dwell) is needed")
    return {"effects": list(group), "options": options, "advice": advice}


def separation_options(setup: Any, effects: tuple[str, ...], X: np.ndarray,
                       labels: list[str], meas: Any, sigma: float,
                       fe: SpecimenModels | None = None
                       ) -> tuple[list[dict[str, Any]], tuple[list[str], str] | None]:
    """Where would new measurements tell apart parameter sets that fit ``meas`` equally well?

    The FE is run at each row of ``X`` over a richer set of outputs (V at the points and on
    the 31 x 18 grid, at the measured and the extended times, one batched solve); for each
    candidate measurement (what it adds to the data: the points at the extended times, the
    full field at the measured times, the full field at the extended times) the rows'
    predictions are compared pairwise over the new values only.

    Args:
        effects: the switched-on effects, in the order of their parameters in ``X``.
        X: ``(g, dim)`` parameter rows (g >= 2): the Anand constants of ``setup.space``, then
            the effects' parameters bound to the measured times; labels: ``g`` names of them.
        meas: the data (which values exist already); sigma: noise sd, um.
        fe: a :class:`~solderpyro.specimen.SpecimenModels` (the diagnosis's run store and
            models); None: solve directly.
    Returns:
        ``(options, failed)``: options ``[{"measurement", "n_new", "pair", "rms_diff_um",
        "max_diff_um", "time_s", "point", "xy_mm", "chi2_apart"}, ...]`` best first, where
        ``chi2_apart = sum((V_a - V_b)^2) / sigma^2`` over the new values of the pair that is
        hardest to separate; failed: None, or ``(labels, reason)`` of the rows where the FE did
        not converge (then no options).
    Raises:
        ValueError: fewer than two rows, a label count that differs, or a column count that is
            not the Anand constants' plus the effects' parameters.
    """
    from solderpyro.effects import effect_set
    from solderpyro.fem.loading import EXTENDED_TIMES
    from solderpyro.fem.problem import reference_grid

    if len(X) < 2 or len(labels) != len(X):
        raise ValueError(f"separation_options: need >= 2 rows and one label per row, got "
                         f"{len(X)} rows and {len(labels)} labels")
    t_meas = tuple(sorted(float(t) for t in meas.times()))
    t_ext = tuple(t for t in EXTENDED_TIMES if t <= setup.problem.cycle.end)
    t_u = tuple(sorted(set(t_meas) | set(t_ext)))
    n_a = setup.space.dim
    Xt = torch.as_tensor(np.asarray(X, float), dtype=torch.float64)
    fx_m = effect_set(tuple(effects), t_meas, setup.effect_bounds) if effects else None
    n_cols = n_a + (fx_m.n_params if fx_m is not None else 0)
    if Xt.ndim != 2 or Xt.shape[1] != n_cols:
        raise ValueError(f"separation_options: X must have {n_cols} columns (the Anand "
                         f"constants, then the parameters of {list(effects)} at the measured "
                         f"times), got shape {tuple(Xt.shape)}")
    if fx_m is not None:
        fx_u = effect_set(tuple(effects), t_u, setup.effect_bounds)
        rows = torch.cat([Xt[:, :n_a], fx_m.rebind_params(Xt[:, n_a:], t_meas, t_u)], 1)
    else:
        fx_u, rows = None, Xt[:, :n_a]
    grid = reference_grid()
    fe = fe if fe is not None else SpecimenModels(setup)
    res = fe.runs(rows, t_u, True, fx_u)
    if not bool(res.ok.all()):
        bad = [g for g, ok in zip(labels, res.ok.tolist(), strict=True) if not ok]
        return [], (bad, next(r for r in res.reasons if r))
    V = res.V.numpy()  # (g, T, n_out)
    times = [float(t) for t in res.times]
    out_names = list(res.names)
    xy = {n: tuple(float(v) for v in p) for n, p in setup.problem.points.items()}
    xy.update({n: (float(p[0]), float(p[1])) for n, p in zip(grid[0], grid[1], strict=True)})
    measured = {(float(t), str(n)) for t, n in zip(meas.time_s, meas.point, strict=True)}
    on_grid = np.array([n in set(grid[0]) for n in out_names])
    pts = ~on_grid
    opts = [("V at the points at the extended times", t_ext, pts),
            ("full-field V (31 x 18 grid) at the measured times", t_meas, on_grid),
            ("full-field V (31 x 18 grid) at the extended times", t_ext, on_grid)]
    options: list[dict[str, Any]] = []
    seen: list[np.ndarray] = []
    for label, ts, cols in opts:
        mask = _new_values(times, out_names, ts, cols, measured)
        if not mask.any() or any(np.array_equal(mask, m) for m in seen):
            continue  # nothing new, or the same values as an option already listed
        seen.append(mask)
        c2, a, b, dV = _worst_pair(V, mask, sigma)
        ti, oj = (int(v) for v in np.unravel_index(int(np.argmax(np.abs(dV))), dV.shape))
        options.append({"measurement": label, "n_new": int(mask.sum()),
                        "pair": [labels[a], labels[b]],
                        "rms_diff_um": float(np.sqrt((dV[mask] ** 2).mean())),
                        "max_diff_um": float(np.abs(dV[ti, oj])), "time_s": times[ti],
                        "point": out_names[oj], "xy_mm": list(xy.get(out_names[oj], ())),
                        "chi2_apart": c2})
    options.sort(key=lambda o: -o["chi2_apart"])
    return options, None


def _new_values(times: list[float], out_names: list[str], ts: tuple[float, ...],
                cols: np.ndarray, measured: set[tuple[float, str]]) -> np.ndarray:
    """``(T, n_out)`` mask of the values a measurement adds: outputs ``cols`` at the times
    ``ts`` (s), less those already ``measured`` ``(time, output)``."""
    mask = np.zeros((len(times), len(out_names)), dtype=bool)
    for i, t in enumerate(times):
        if any(abs(t - s) < 1e-6 for s in ts):
            mask[i] = cols
    for i, t in enumerate(times):
        for j, n in enumerate(out_names):
            if (t, n) in measured:
                mask[i, j] = False
    return mask


def _worst_pair(V: np.ndarray, mask: np.ndarray, sigma: float
                ) -> tuple[float, int, int, np.ndarray]:
    """The pair of rows of ``V (g, T, n_out)`` (um) hardest to separate over ``mask``:
    ``(chi2_apart, a, b, dV (T, n_out))``, chi2_apart ``= sum(dV^2) / sigma^2`` (first pair
    on ties)."""
    worst: tuple[float, int, int, np.ndarray] | None = None
    for a in range(len(V)):
        for b in range(a + 1, len(V)):
            dV = np.where(mask, V[a] - V[b], 0.0)
            c2 = float((dV**2).sum() / sigma**2)
            if worst is None or c2 < worst[0]:
                worst = (c2, a, b, dV)
    assert worst is not None  # at least two rows
    return worst
