"""The linear screen of a diagnosis: the FE and its finite-difference Jacobians at calibrated
draws (every candidate effect at "off", one batched solve with the likelihood-ratio ladder),
the misfit and a score test per candidate, and the ladder's likelihood ratio.

The statistics are :mod:`solderpyro.diagnose.stats`'; the FE goes through the diagnosis's
:class:`~solderpyro.specimen.SpecimenModels` (the run store).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from scipy.stats import chi2 as _chi2

from solderpyro.diagnose.refits import Layout
from solderpyro.diagnose.stats import Misfit, Score, evidence, misfit, score_test
from solderpyro.specimen import SpecimenModels

log = logging.getLogger("solderpyro")

#: an effect whose signature the calibrated parameters mimic to within this share is not
#: flagged however large its statistic: below it the linearised projection (finite-difference
#: Jacobians, steps 1e-3 of the box) is not accurate enough to trust what is left
MIN_IDENTIFIABLE = 0.01
#: magnitudes (share of the way from "off" to the box's far edge) of the likelihood-ratio ladder
LADDER = (0.15, 0.4, 1.0)


@dataclass
class Columns:
    """Finite-difference design: which FE member perturbs which parameter column."""

    names: list[str]  # every column: calibrated parameters, then candidates' parameters
    owner: list[str]  # "theta" or the effect's name
    step: np.ndarray  # physical step per column
    central: np.ndarray  # bool per column
    lower: np.ndarray  # each column's box (physical units): no step leaves it
    upper: np.ndarray


def fd_design(box_names: list[str], box_lo: list[float], box_hi: list[float],
              cands: dict[str, Any], rel: float) -> Columns:
    """The finite-difference columns: the calibrated parameters (``box_*``, physical units),
    then each candidate's parameters (``cands``: name -> bound effect); each steps ``rel`` of
    its box width, central except one-sided where "off" minus the step leaves the box."""
    names, owner, step, central = [], [], [], []
    lower, upper = list(map(float, box_lo)), list(map(float, box_hi))
    for nm, lo, hi in zip(box_names, box_lo, box_hi, strict=True):
        names.append(nm)
        owner.append("theta")
        step.append(rel * (hi - lo))
        central.append(True)
    for ename, eff in cands.items():
        pb = eff.params
        for j, nm in enumerate(pb.names):
            off = float(eff.off[j])
            lo, hi = float(pb.lower[j]), float(pb.upper[j])
            names.append(nm)
            owner.append(ename)
            step.append(rel * (hi - lo))
            central.append(off - rel * (hi - lo) >= lo)  # one-sided at the box edge
            lower.append(lo)
            upper.append(hi)
    return Columns(names, owner, np.array(step), np.array(central), np.array(lower),
                   np.array(upper))


def fe_jacobians(lay: Layout, theta: np.ndarray, fe: SpecimenModels | None = None,
                 rel: float = 1e-3, progress: bool = True) -> dict[str, Any]:
    """FE outputs and finite-difference Jacobians at calibrated draws, candidates at "off".

    Args:
        lay: the diagnosis's layout (:class:`~solderpyro.diagnose.refits.Layout`: the setup,
            whose ``space`` are the calibrated Anand constants, the effects already on in the
            calibration and the candidates to test, the output times (s), whether the data
            include the 31 x 18 grid).
        theta: ``(K, n_cal)`` calibrated parameter draws (Anand constants of ``setup.space``,
            then the run's own effects' parameters), physical units.
        fe: the diagnosis's :class:`~solderpyro.specimen.SpecimenModels` (run store, models);
            None: solve directly.
        rel: step as a share of each parameter's box width (one-sided at a box edge).
    Returns:
        dict: ``V (K, n_time, n_out)`` at the draws (um), ``J (K, n_time, n_out, n_col)``
        (um per unit), ``cols`` (:class:`Columns`), ``names`` (output labels), ``times``,
        ``ladder`` (per one-parameter candidate, its magnitudes and the FE there), ``n_ladder``
        (FE rows of the ladder). The draws' rows and the ladder's are one batched solve.
    """
    from solderpyro.effects import effect_set
    from solderpyro.specimen import calibration_box

    setup, run_effects, candidates = lay.setup, lay.run_effects, lay.candidates
    times, field = lay.times, lay.field
    fe = fe if fe is not None else SpecimenModels(setup)

    fx_all = effect_set(tuple(run_effects) + tuple(candidates), times, setup.effect_bounds)
    cands = {e.name: e for e in fx_all.effects if e.name in candidates}
    cal = calibration_box(setup, effect_set(run_effects, times, setup.effect_bounds)
                          if run_effects else None)
    cols = fd_design(list(cal.names), list(cal.lower), list(cal.upper), cands, rel)
    n_cal = cal.dim
    off = np.array([v for e in cands.values() for v in e.off], float)
    rows, span = fd_rows(theta, off, cols)
    ladder, lad_rows = _ladder_rows(np.concatenate([theta[0], off]), cands, cols, n_cal)
    P = torch.tensor(np.array(rows + lad_rows), dtype=torch.float64)
    n_lad = sum(len(v) for v in ladder.values())
    log.info("diagnose: %d FE rows (%d draws x %d Jacobian columns, %d ladder runs, "
             "candidates: %s)", len(rows) + len(lad_rows), len(theta), len(cols.names), n_lad,
             ", ".join(candidates) or "none")
    res = fe.runs(P, times, field, fx_all, progress=progress, keep=len(run_effects))
    V = res.V.numpy()
    if not bool(res.ok.all()):
        bad = [r for r in res.reasons if r]
        raise RuntimeError(f"{len(bad)} FE runs of the diagnosis failed: {bad[:2]}")
    Vb, J = fd_jacobians(V[:len(rows)], span, cols)
    VL, i = {}, len(rows)
    for ename, vals in ladder.items():
        VL[ename] = (vals, V[i:i + len(vals)])
        i += len(vals)
    return {"V": Vb, "J": J, "cols": cols, "names": list(res.names), "n_cal": n_cal,
            "fe": fe, "ladder": VL, "n_ladder": n_lad,
            "times": tuple(float(t) for t in res.times)}


def fd_rows(theta: np.ndarray, off: np.ndarray, cols: Columns
             ) -> tuple[list[np.ndarray], np.ndarray]:
    """FE rows per draw of ``theta (K, n_cal)``: the base (candidates at ``off``), then per
    column the forward step and, where central, the backward one, each stopped at the
    column's box (a draw at a bound: an effect's parameter outside its box is no model, e.g.
    a lag's split above 0.5). Returns the rows and ``(K, n_col)`` the distance each column's
    difference spans (physical units)."""
    rows, span = [], np.empty((len(theta), len(cols.names)))
    for k, th in enumerate(theta):
        base = np.concatenate([th, off])
        rows.append(base)
        for c in range(len(cols.names)):
            plus, minus = base.copy(), base.copy()
            plus[c] = min(base[c] + cols.step[c], cols.upper[c])
            rows.append(plus)
            if cols.central[c]:
                minus[c] = max(base[c] - cols.step[c], cols.lower[c])
                rows.append(minus)
            span[k, c] = plus[c] - minus[c]
    return rows, span


def _ladder_rows(base0: np.ndarray, cands: dict[str, Any], cols: Columns, n_cal: int
                 ) -> tuple[dict[str, np.ndarray], list[np.ndarray]]:
    """A ladder of finite magnitudes of each candidate sized by one parameter
    (:attr:`~solderpyro.effects.Effect.size_index`; its form parameters stay at "off"), from
    the first draw's row ``base0``: the likelihood ratio sees effects whose first derivative at
    "off" vanishes (thresholds, e.g. yielding). Returns ``(effect -> magnitudes, FE rows)``."""
    ladder: dict[str, np.ndarray] = {}
    rows = []
    for ename, eff in cands.items():
        k = eff.size_index
        if k is None:
            continue
        j = n_cal + int(np.flatnonzero(np.array(cols.owner[n_cal:]) == ename)[0]) + k
        ladder[ename] = ladder_values(eff)
        for v in ladder[ename]:
            r = base0.copy()
            r[j] = v
            rows.append(r)
    return ladder, rows


def fd_jacobians(V: np.ndarray, span: np.ndarray, cols: Columns
                  ) -> tuple[np.ndarray, np.ndarray]:
    """``(V (K, ...), J (K, ..., n_col))`` from the FE at the rows of :func:`fd_rows` and
    the distances ``span (K, n_col)`` their differences cover."""
    K = len(span)
    Vb = np.empty((K, *V.shape[1:]))
    J = np.empty((K, *V.shape[1:], len(cols.names)))
    i = 0
    for k in range(K):
        Vb[k] = V[i]
        i += 1
        for c in range(len(cols.names)):
            plus = V[i]
            i += 1
            if cols.central[c]:
                J[k, ..., c] = (plus - V[i]) / span[k, c]
                i += 1
            else:
                J[k, ..., c] = (plus - Vb[k]) / span[k, c]
    return Vb, J


def ladder_values(eff: Any) -> np.ndarray:
    """``(len(LADDER),)`` magnitudes of the parameter that sizes ``eff`` (bound
    :class:`~solderpyro.effects.Effect`; :attr:`~solderpyro.effects.Effect.size_index`): the
    shares :data:`LADDER` of the way from "off" to the farther edge of its box, in its own
    units."""
    k = eff.size_index
    if k is None:
        raise ValueError(f"ladder_values: effect {eff.name!r} is sized by several parameters")
    b, o = eff.params, float(eff.off[k])
    far = b.upper[k] if b.upper[k] - o >= o - b.lower[k] else b.lower[k]
    return o + np.asarray(LADDER) * (far - o)


def group(cols: Columns, owner: str) -> np.ndarray:
    """Column indices ``(m,)`` of ``owner`` (``"theta"`` or an effect's name)."""
    return np.array([j for j, o in enumerate(cols.owner) if o == owner], dtype=int)


def score_tests(y: np.ndarray, V: np.ndarray, J: np.ndarray, cols: Columns, sigma: float
                ) -> tuple[Misfit, list[Score], list[list[Score]]]:
    """The misfit at the first draw and the score test of each candidate at each draw (the
    likelihood-ratio ladder comes after: :func:`apply_ladder`).

    Args:
        y: ``(n,)`` data, um; V: ``(K, n)`` FE at the draws; J: ``(K, n, n_col)`` Jacobians;
        cols: columns; sigma: noise sd, um.
    Returns:
        ``(misfit at the first draw, scores at the first draw (one per candidate), scores per
        draw)``.
    """
    w = np.full(len(y), 1.0 / sigma**2)
    th = group(cols, "theta")
    effects = [o for o in dict.fromkeys(cols.owner) if o != "theta"]
    per_draw = []
    for k in range(V.shape[0]):
        r = y - V[k]
        per_draw.append([score_test(e, r, J[k][:, th], J[k][:, group(cols, e)], w)
                         for e in effects])
    mf = misfit(y - V[0], J[0][:, th], w)
    return mf, per_draw[0], per_draw


def apply_ladder(mf: Misfit, scores: list[Score], y: np.ndarray, J0: np.ndarray,
                 cols: Columns, sigma: float,
                 ladder: dict[str, tuple[np.ndarray, np.ndarray]] | None) -> None:
    """The likelihood ratio of each candidate with a ladder over its magnitudes
    (first draw, ``J0 (n, n_col)``); where it is the larger statistic it replaces the score's
    (``scores`` are changed in place)."""
    w = np.full(len(y), 1.0 / sigma**2)
    th = group(cols, "theta")
    for sc in scores:
        if ladder and sc.effect in ladder:
            vals, VL = ladder[sc.effect]
            lr = likelihood_ratio(mf.chi2, y, VL, J0[:, th], w)
            sc.lr, sc.lr_value = float(lr.max()), float(vals[int(np.argmax(lr))])
            if sc.lr > sc.statistic:  # a finite magnitude explains more than the slope at off
                sc.statistic = sc.lr
                sc.dof = max(sc.dof, 1)
                sc.p_value = float(_chi2.sf(sc.lr, sc.dof))
                sc.evidence = evidence(sc.lr, sc.dof)
                sc.chi2_after = mf.chi2 - sc.lr


def likelihood_ratio(chi2_base: float, y: np.ndarray, V_ladder: np.ndarray,
                     J_theta: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Chi-square drop ``(L,)`` when the effect is switched on at each ladder magnitude and the
    calibrated parameters are refitted (linearised with ``J_theta``, as the baseline misfit).

    Args:
        chi2_base: the baseline misfit chi-square; y: ``(n,)`` data, um;
        V_ladder: ``(L, n)`` FE with the effect at each magnitude; J_theta: ``(n, p)``;
        w: ``(n,)`` weights 1/um^2.
    """
    return np.array([chi2_base - misfit(y - v, J_theta, w).chi2 for v in V_ladder])


def at_observations(fej: dict[str, Any], meas: Any
                    ) -> tuple[np.ndarray, np.ndarray, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """The FE of :func:`fe_jacobians` row for row with the measurements ``meas`` (n values).

    Returns:
        ``(V (K, n), J (K, n, n_col), ladder)``, ladder: effect -> ``(values (L,), V (L, n))``.
    """
    from solderpyro.specimen import observation_index

    ti, oi = observation_index(meas, fej["times"], tuple(fej["names"]))
    lad = {k: (v, VL[:, ti, oi]) for k, (v, VL) in fej["ladder"].items()}
    return fej["V"][:, ti, oi], fej["J"][:, ti, oi, :], lad
