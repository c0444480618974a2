"""The FE fits of a diagnosis: its one base point and the candidates' refits (issue 20).

* :func:`base_fit`: the FE's own best fit. Several starts (the posterior median, and where the
  FE check rejected the posterior also the literature constants and another draw) advance
  together by Levenberg-Marquardt, one batch per step, each until an iteration gains less than
  :data:`LM_TOL` in chi-square (at most :data:`BASE_ITERS`); every :data:`SCOUT_ITERS`
  iterations the starts far behind the best stop. Every statistic of the diagnosis is taken
  against the best.
* :func:`refit_candidates`: each candidate (or, in a forward step, the effects already chosen
  plus one more) refitted with the FE from the base point, all models in one batch per step.
  A refit that ends above its base (:attr:`~solderpyro.diagnose.decide.Refit.ok` false) is
  retried once from the base point with the candidate at "off"; if it still ends above, it is
  a failed fit.

Rows are laid out as :class:`Layout` says: the calibrated parameters (``setup.space``, then the
run's own effects), then every candidate's parameters bound to the measured times. Every FE
row goes through the diagnosis's :class:`~solderpyro.specimen.SpecimenModels` (the run store), so
rows shared with the Jacobians or an earlier diagnosis are read back, not solved.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from solderpyro.diagnose.decide import Refit
from solderpyro.fit import LMFit, lm_fit

log = logging.getLogger("solderpyro")

#: stop a fit once an iteration gains less than this chi-square (its sampling sd on 2,240
#: values is 67; APART_CHI2 is 6)
LM_TOL = 0.5
#: most Levenberg-Marquardt iterations of each refit
LM_ITERS = 15
#: most iterations of the base fit (every statistic is measured from it: a base that has not
#: converged lends its remaining gain to every refit's likelihood ratio; on the hidden
#: stress-free-temperature field data it still gained 6 chi2 per iteration at 15)
BASE_ITERS = 30
#: the base fit's starts are compared (and the poor ones stopped) after every this many
SCOUT_ITERS = 3
#: refits run per step at most (the screen's strongest candidates)
MAX_REFITS = 4


@dataclass
class Layout:
    """The row layout of a diagnosis's fits.

    Attributes:
        setup: the run's Setup; run_effects, candidates: effect names.
        fx_all: the :class:`~solderpyro.effects.EffectSet` of both, bound to ``times`` (s).
        field: whether the data include the 31 x 18 grid.
        n_cal: calibrated parameters (Anand constants, then the run's effects' parameters).
        lo, hi: ``(n_col,)`` box of every column; off: ``(n_col - n_cal,)`` each candidate
            parameter's "off" value; owner: ``(n_col - n_cal,)`` the candidate of each.
    """

    setup: Any
    run_effects: tuple[str, ...]
    candidates: tuple[str, ...]
    times: tuple[float, ...]
    field: bool
    fx_all: Any
    n_cal: int
    lo: np.ndarray
    hi: np.ndarray
    off: np.ndarray
    owner: np.ndarray
    names: tuple[str, ...] = ()

    def named(self, x: np.ndarray, effects: tuple[str, ...]) -> dict[str, float]:
        """``name -> value`` of the columns a model with ``effects`` fits, from a full row
        ``x (n_col,)`` (physical units): what a recalibration with those effects starts from."""
        return {self.names[k]: float(x[k]) for k in self.free(tuple(effects))}

    def cols(self, effect: str) -> np.ndarray:
        """Column indices of a candidate's parameters."""
        return self.n_cal + np.flatnonzero(self.owner == effect)

    def free(self, effects: tuple[str, ...]) -> np.ndarray:
        """Columns a model fits: the calibrated parameters and ``effects``'."""
        return np.concatenate([np.arange(self.n_cal), *[self.cols(e) for e in effects]])

    def row(self, theta: np.ndarray) -> np.ndarray:
        """A full row ``(n_col,)`` from calibrated parameters ``theta (n_cal,)``, every candidate
        at "off"."""
        return np.concatenate([np.asarray(theta, float), self.off])


def layout(setup: Any, run_effects: tuple[str, ...], candidates: tuple[str, ...],
           meas: Any) -> Layout:
    """The :class:`Layout` of a diagnosis of ``meas`` (its times and whether it is field data)."""
    from solderpyro.effects import effect_set
    from solderpyro.specimen import calibration_box

    field = any(p not in setup.problem.points for p in meas.points())
    times = tuple(float(t) for t in meas.times())
    fx_all = effect_set(tuple(run_effects) + tuple(candidates), times, setup.effect_bounds)
    cal = calibration_box(setup, effect_set(run_effects, times, setup.effect_bounds)
                          if run_effects else None)
    lo, hi, off, owner = list(cal.lower), list(cal.upper), [], []
    names = list(cal.names)
    for e in fx_all.effects[len(run_effects):]:
        names += list(e.params.names)
        lo += list(e.params.lower)
        hi += list(e.params.upper)
        off += list(e.off)
        owner += [e.name] * e.n_params
    return Layout(setup, tuple(run_effects), tuple(candidates), times, field, fx_all, cal.dim,
                  np.array(lo, float), np.array(hi, float), np.array(off, float),
                  np.array(owner, dtype=object), tuple(names))


def fit_models(lay: Layout, fe: Any, meas: Any, sigma: float,
               models: dict[str, tuple[tuple[str, ...], np.ndarray]],
               iters: int = LM_ITERS, tol: float | None = LM_TOL, rel: float = 1e-3
               ) -> dict[str, LMFit]:
    """Fit several models through the FE at once (one batched solve per LM step).

    Args:
        lay: the layout; fe: the diagnosis's :class:`~solderpyro.specimen.SpecimenModels`;
            meas: the data; sigma: noise sd, um.
        models: name -> (the candidates it fits beside the calibrated parameters, its start
            row ``(n_col,)``, physical units).
        iters, tol, rel: of :func:`~solderpyro.fit.lm_fit`.
    Returns:
        name -> :class:`~solderpyro.fit.LMFit` (``x`` a full row).
    """
    from solderpyro.specimen import observation_index

    y = np.asarray(meas.value_um, float)
    idx: dict[str, Any] = {}

    def run(rows: np.ndarray) -> np.ndarray:
        P = torch.tensor(rows, dtype=torch.float64)
        res = fe.runs(P, lay.times, lay.field, lay.fx_all)
        if "ti" not in idx:
            idx["ti"], idx["oi"] = observation_index(meas, res.times, res.names)
        V = res.V.numpy()[:, idx["ti"], idx["oi"]]
        V[~res.ok.numpy()] = np.nan
        return V

    names = list(models)
    X0 = np.array([np.clip(models[m][1], lay.lo, lay.hi) for m in names])
    out = lm_fit(run, X0, lay.lo, lay.hi, y, sigma, [lay.free(models[m][0]) for m in names],
                 iters, rel, tol=tol)
    return dict(zip(names, out, strict=True))


def base_fit(lay: Layout, fe: Any, meas: Any, sigma: float,
             starts: dict[str, np.ndarray]) -> dict[str, Any]:
    """The FE's best fit of the calibrated parameters (see the module docstring).

    The starts advance together, :data:`SCOUT_ITERS` iterations at a time (one batched solve
    per step); after each round a start that has converged, or whose chi-square is more than
    twice the best one's (+ 50), stops; the last one goes on to convergence, at most
    :data:`BASE_ITERS` iterations in all.

    Args:
        starts: label -> ``(n_cal,)`` start, physical units (clipped into the box).
    Returns:
        ``{"x": (n_col,) row (candidates off), "chi2", "history": [chi2, ...] of the winner,
        "start": its label, "scouts": {label: chi2 where it stopped}, "converged"}``.
    """
    if not starts:
        raise ValueError("base_fit: no start given")
    x = {k: lay.row(v) for k, v in starts.items()}
    chi = {k: np.inf for k in x}
    hist: dict[str, list[float]] = {k: [] for k in x}
    conv = dict.fromkeys(x, False)
    alive = list(x)
    done = 0
    while alive and done < BASE_ITERS:
        # several starts: compare them every SCOUT_ITERS; one left: on to convergence
        step = SCOUT_ITERS if len(alive) > 1 else BASE_ITERS - done
        fits = fit_models(lay, fe, meas, sigma, {k: ((), x[k]) for k in alive},
                          iters=min(step, BASE_ITERS - done))
        done += step
        for k, f in fits.items():
            x[k], chi[k], conv[k] = f.x, float(f.chi2), bool(f.converged)
            hist[k] += [c for c in f.history if not hist[k] or c != hist[k][-1]]
        best = min(chi.values())
        alive = [k for k in alive if not conv[k] and chi[k] <= 2.0 * best + 50.0]
    win = min(chi, key=lambda k: chi[k])
    return {"x": x[win], "chi2": chi[win], "history": hist[win], "start": win,
            "scouts": chi if len(chi) > 1 else {}, "converged": conv[win]}


def refit_candidates(lay: Layout, fe: Any, meas: Any, sigma: float, base_x: np.ndarray,
                     base_chi2: float, chosen: tuple[str, ...], starts: dict[str, np.ndarray]
                     ) -> list[Refit]:
    """Refit ``chosen + (c,)`` for each candidate ``c`` of ``starts`` (see the module docstring).

    Args:
        base_x: ``(n_col,)`` the base model's fit (``chosen`` on, the others off);
        base_chi2: its chi-square; chosen: effects already added (forward steps).
        starts: candidate -> start row ``(n_col,)`` (e.g. ``base_x`` with the candidate at its
            best ladder magnitude).
    Returns:
        one :class:`~solderpyro.diagnose.decide.Refit` per candidate, in the order of
        ``starts``; ``starts`` counts the retry.
    """
    if not starts:
        return []
    fits = fit_models(lay, fe, meas, sigma,
                      {c: (chosen + (c,), x) for c, x in starts.items()})
    out = {c: Refit(chosen + (c,), float(f.chi2), len(lay.cols(c)), f.x, base_chi2)
           for c, f in fits.items()}
    retry = [c for c, r in out.items() if not r.ok and not np.array_equal(starts[c], base_x)]
    if retry:
        log.info("diagnose: refits above their base chi2 %.1f (%s); retrying from the base "
                 "point with the effect off", base_chi2,
                 ", ".join(f"{c} {out[c].chi2:.1f}" for c in retry))
        again = fit_models(lay, fe, meas, sigma, {c: (chosen + (c,), base_x) for c in retry})
        for c, f in again.items():
            r = Refit(chosen + (c,), float(f.chi2), len(lay.cols(c)), f.x, base_chi2, starts=2)
            out[c] = r if r.chi2 < out[c].chi2 else dataclasses.replace(out[c], starts=2)
    return [out[c] for c in starts]
