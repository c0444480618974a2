"""The FE fits of a diagnosis: its one base point and the candidates' refits.

* :func:`base_fit`: the FE's own best fit. Several starts (the posterior median, and where the
  FE check rejected the posterior also the literature constants and another draw) advance
  together by Levenberg-Marquardt, one batch per step, each until an iteration gains less than
  :data:`LM_TOL` in chi-square (at most :data:`BASE_ITERS`); every :data:`SCOUT_ITERS`
  iterations the starts far behind the best stop. Every statistic of the diagnosis is taken
  against the best.
* :func:`base_starts`: where the base fit starts (the calibration's FE best fit, the posterior
  median, the literature constants).
* :func:`refit_candidates`: each candidate (or, in a forward step, the effects already chosen
  plus one more) refitted with the FE from the base point, all models in one batch per step.
  A refit that ends above its base (:attr:`~solderpyro.diagnose.decide.Refit.ok` false) is
  retried once from the base point with the candidate at "off"; if it still ends above, it is
  a failed fit.
* :func:`first_refits`: the screened candidates' refits from the base point; :func:`forward`:
  the forward steps from them (:func:`~solderpyro.diagnose.decide.forward_steps`); where the
  chosen effects' fit presses the faces, each next candidate also from the literature
  constants.
* :func:`global_refits`: where the base fit presses constants against the box's faces or no
  refit explains the misfit, every candidate (and the base model) refitted from several starts
  across the box (:func:`spread_starts`): the screen orders that work and never excludes a
  candidate from it. The starts are ranked and converged through the run's model at half its
  resolution (:func:`~solderpyro.config.compose.coarsened`, a fifth of the cost per run) and
  finished through the run's own FE.

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

from solderpyro.diagnose.decide import (
    APART_CHI2,
    MIN_PRESSED,
    REFIT_TOL,
    Floor,
    Judged,
    Refit,
    forward_step,
    forward_steps,
    judge,
    saturates,
)
from solderpyro.diagnose.faces import NEAR_SHARE, on_faces
from solderpyro.diagnose.stats import Score
from solderpyro.exact.fit import LMFit, LMOptions, lm_fit
from solderpyro.specimen import SpecimenModels

log = logging.getLogger("solderpyro")

#: the label of the global refits' start at the base fit
BASE_POINT = "the base point"
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
#: Latin-hypercube starts of the global refits, beside the literature constants
SPREAD_STARTS = 2
#: the share of a global refit's half-resolution chi-square held back as a margin when judging
#: whether it could still overtake the best at full resolution (:attr:`Reach.floor`)
REACH_REL = 0.1


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


def observed(fe: Any, meas: Any, lay: Layout) -> Any:
    """``rows (N, n_col) -> (N, n)`` the FE's predictions at the measured values (um; NaN rows
    where the model failed), every row through ``fe`` (the run store)."""
    from solderpyro.specimen import observation_index

    idx: dict[str, Any] = {}

    def run(rows: np.ndarray) -> np.ndarray:
        P = torch.tensor(rows, dtype=torch.float64)
        # each row with the run's effects and only the candidates it switches on
        res = fe.runs(P, lay.times, lay.field, lay.fx_all, keep=len(lay.run_effects))
        if "ti" not in idx:
            idx["ti"], idx["oi"] = observation_index(meas, res.times, res.names)
        V = res.V.numpy()[:, idx["ti"], idx["oi"]]
        V[~res.ok.numpy()] = np.nan
        return V

    return run


def chi2_at(lay: Layout, fe: Any, meas: Any, sigma: float, rows: np.ndarray) -> np.ndarray:
    """Chi-square ``(N,)`` of the rows ``(N, n_col)`` through ``fe`` (inf where it failed)."""
    V = observed(fe, meas, lay)(np.atleast_2d(rows))
    c2 = (((np.asarray(meas.value_um, float)[None] - V) / sigma) ** 2).sum(1)
    return np.where(np.isfinite(c2), c2, np.inf)


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
        iters, tol, rel: of :class:`~solderpyro.exact.fit.LMOptions`.
    Returns:
        name -> :class:`~solderpyro.exact.fit.LMFit` (``x`` a full row); empty for no models.
    """
    if not models:  # e.g. every scouted start already converged
        return {}
    y = np.asarray(meas.value_um, float)
    run = observed(fe, meas, lay)

    names = list(models)
    X0 = np.array([np.clip(models[m][1], lay.lo, lay.hi) for m in names])
    out = lm_fit(run, X0, lay.lo, lay.hi, y, sigma, [lay.free(models[m][0]) for m in names],
                 LMOptions(iters=iters, rel=rel, tol=tol))
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
                     base_chi2: float, chosen: tuple[str, ...], starts: dict[str, np.ndarray],
                     cheap: Any | None = None) -> list[Refit]:
    """Refit ``chosen + (c,)`` for each candidate ``c`` of ``starts`` (see the module docstring).

    Args:
        base_x: ``(n_col,)`` the base model's fit (``chosen`` on, the others off);
        base_chi2: its chi-square; chosen: effects already added (forward steps).
        starts: candidate -> start row ``(n_col,)`` (e.g. ``base_x`` with the candidate at its
            best ladder magnitude).
        cheap: a cheaper model of the same physics (the half-resolution one), or None. With
            it, every refit converges there first, and only those :func:`within_reach` of the
            best (or of the base) go on through ``fe``; the others are the base with the
            candidate at no gain, or the FE's chi-square at their cheap optimum where that is
            lower.
    Returns:
        one :class:`~solderpyro.diagnose.decide.Refit` per candidate, in the order of
        ``starts``; ``starts`` counts the retry.
    """
    if not starts:
        return []
    models = {c: (chosen + (c,), x) for c, x in starts.items()}
    if cheap is None:
        fits = fit_models(lay, fe, meas, sigma, models)
    else:
        pre = fit_models(lay, cheap, meas, sigma, models)
        names = list(pre)
        full, bounds = through_own_fe(lay, fe, meas, sigma, pre)
        reach = within_reach(bounds, {"base": base_chi2})
        fits = {c: f for c, f in full.items() if c not in reach}
        if fits:
            log.info("diagnose: refits left at their half-resolution optimum, too far behind "
                     "to matter: %s", ", ".join(f"+{c} {f.chi2:.1f}" for c, f in fits.items()))
            for c, f in fits.items():
                if f.chi2 > base_chi2:  # nested: the base (the candidate off) does as well
                    fits[c] = LMFit(base_x.copy(), base_chi2, f.free)
        fits.update(fit_models(lay, fe, meas, sigma,
                               {c: (models[c][0], pre[c].x) for c in names if c in reach}))
        fits = {c: fits[c] for c in starts}
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


def pick_draws(theta: np.ndarray, k: int, seed: int) -> np.ndarray:
    """``(k,)`` row indices of the draws ``theta (N, n_cal)``: the draw nearest the
    component-wise median (scaled), then ``k - 1`` random ones (``seed``)."""
    med = np.median(theta, 0)
    sc = theta.std(0) + 1e-300
    first = int(np.argmin((((theta - med) / sc) ** 2).sum(1)))
    rng = np.random.default_rng(seed)
    rest = rng.choice(np.delete(np.arange(len(theta)), first), size=max(k - 1, 0),
                      replace=False)
    return np.concatenate([[first], rest]).astype(int)



def starts(setup: Any, theta: np.ndarray, idx: np.ndarray, fe_ok: bool
           ) -> dict[str, np.ndarray]:
    """Starts of the base fit: the draw nearest the posterior median; where the FE check
    rejected the posterior, also the literature constants (the run's own effects at their
    posterior median) and the posterior draw farthest from the median in scaled units."""
    out = {"posterior median": theta[idx[0]]}
    if fe_ok:
        return out
    out["literature constants"] = literature_start(setup, np.median(theta, 0))
    z = (theta - np.median(theta, 0)) / (theta.std(0) + 1e-300)
    out["farthest posterior draw"] = theta[int(np.argmax((z**2).sum(1)))]
    return out



def first_refits(lay: Layout, fe: SpecimenModels, meas: Any, sigma: float,
                 base: dict[str, Any], scores: list[Score], screened: list[Score]
                 ) -> list[Refit]:
    """The screened candidates' refits from the base point (the first step).

    Args:
        lay: the row layout; fe: the diagnosis's FE (run store); meas: the data (n values);
        sigma: noise sd, um; base: the base fit (:func:`base_fit`: ``"x" (n_col,)``,
        ``"chi2"``); scores: every candidate's screen (a ladder magnitude starts its refit);
        screened: those to refit.
    Returns:
        one :class:`~solderpyro.diagnose.decide.Refit` per screened candidate.
    """
    ladder = ladder_values(scores)
    x_b = np.asarray(base["x"], float)
    starts = {}
    for sc in screened:
        x = x_b.copy()
        j = size_col(lay, sc.effect)
        if sc.effect in ladder and j is not None:
            x[j] = ladder[sc.effect]
        starts[sc.effect] = x
    first = refit_candidates(lay, fe, meas, sigma, x_b, base["chi2"], (), starts)
    log.info("diagnose: refits from the base point (chi2 %.1f): %s", base["chi2"], ", ".join(
        f"{r.name} {r.chi2:.1f}{'' if r.ok else ' (failed)'}" for r in first))
    return first


def ladder_values(scores: list[Score]) -> dict[str, float]:
    """Candidate -> the screen's best ladder magnitude, where the ladder found one."""
    return {sc.effect: sc.lr_value for sc in scores
            if sc.lr_value is not None and (sc.lr or 0.0) > 0.0}


def forward(lay: Layout, fe: SpecimenModels, meas: Any, sigma: float, first: list[Refit],
            floor: Floor, cheap: SpecimenModels | None = None
            ) -> tuple[list[list[Judged]], tuple[str, ...], list[str]]:
    """The forward steps from the first step's refits
    (:func:`~solderpyro.diagnose.decide.forward_steps`): each next candidate refitted with the
    chosen ones on, from the chosen model's fit with the candidate where its own refit put it
    (through ``cheap`` first where given: :func:`refit_candidates`). Where the chosen model's
    fit presses :data:`~solderpyro.diagnose.decide.MIN_PRESSED` or more Anand constants against
    the faces, each next candidate is also refitted from the literature constants
    (:func:`literature_start`) and the better of its two fits kept: residual stress beside a
    second-order lag, refitted only from the lag's fit at the faces, ended at chi-square 2,126,
    2,203 and 2,204 on the same data as the screen's steps changed, and was not selected; from
    the literature constants as well it was, with all seven true values inside the
    recalibration's intervals.

    Returns:
        ``(steps, chosen, tie)``: the judged refits per step; the effects added; the candidates
        that could not be told apart where the steps stopped (empty if none).
    """
    if not first:
        return [], (), []
    single = {r.name: r for r in first}
    space = lay.setup.space

    def refit_next(cur: Refit, chosen: tuple[str, ...], others: list[str]) -> list[Refit]:
        st = {}
        for c in others:
            x = cur.x.copy()
            x[lay.cols(c)] = single[c].x[lay.cols(c)]
            st[c] = x
        nxt = refit_candidates(lay, fe, meas, sigma, cur.x, cur.chi2, chosen, st, cheap)
        if len(faces_of(cur)) >= MIN_PRESSED:
            # from a fit that presses the faces a next candidate's signature can vanish (where
            # the solder barely creeps, a residual stress barely shows): each is also refitted
            # from the literature constants, and the better fit kept
            lit_starts = {c: literature_start(lay.setup, x) for c, x in st.items()}
            again = refit_candidates(lay, fe, meas, sigma, cur.x, cur.chi2, chosen,
                                     lit_starts, cheap)
            nxt = [b if b.ok and (not a.ok or b.chi2 < a.chi2) else a
                   for a, b in zip(nxt, again, strict=True)]
        log.info("diagnose: forward step, with %s on (chi2 %.1f): %s", " + ".join(chosen),
                 cur.chi2, ", ".join(f"+{r.name} {r.chi2:.1f}{'' if r.ok else ' (failed)'}"
                                     for r in nxt))
        return nxt

    def faces_of(r: Refit) -> tuple[str, ...]:
        return tuple(f.name for f in on_faces(r.x[:space.dim], space, NEAR_SHARE))

    return forward_steps(first, refit_next, len(meas.value_um), lay.n_cal, sigma, floor,
                         len(lay.candidates), faces_of)


def literature_start(setup: Any, x: np.ndarray) -> np.ndarray:
    """A copy of row ``x`` (any length from ``setup.space.dim`` on, physical units) with the
    Anand constants at the literature values (``setup.anand``), every other column as it is."""
    space = setup.space
    out = np.asarray(x, float).copy()
    out[:space.dim] = [setup.anand[nm] for nm in space.names]
    return out


def first_fits(base: dict[str, Any], first: list[Refit]) -> dict[str, dict[str, Any]]:
    """``{"baseline"|effect: {"chi2", "x"}}`` of the base and the first step's refits (for the
    fingerprints and the separation)."""
    fits: dict[str, dict[str, Any]] = {"baseline": {"chi2": base["chi2"],
                                                    "x": np.asarray(base["x"], float)}}
    fits.update({r.name: {"chi2": r.chi2, "x": r.x} for r in first})
    return fits


def spread_starts(lay: Layout, base_x: np.ndarray, k: int = SPREAD_STARTS, seed: int = 0
                  ) -> dict[str, np.ndarray]:
    """Starts of the global refits across the calibrated box, label -> ``(n_cal,)`` row.

    The literature constants (``setup.anand``), then ``k`` points of a Latin hypercube over
    the inner 70 % of the Anand constants' box (unit-cube scale, so log-scale constants
    spread in log); the run's own effects' parameters stay at ``base_x``'s.

    Args:
        lay: the layout (``lay.setup.space`` is the Anand constants' box).
        base_x: ``(n_col,)`` the base fit's row, physical units.
        k: Latin-hypercube starts; seed: their seed.
    """
    from scipy.stats import qmc

    space = lay.setup.space
    d = space.dim
    out: dict[str, np.ndarray] = {}
    out["literature constants"] = literature_start(lay.setup, base_x[:lay.n_cal])
    if k > 0:
        u = 0.15 + 0.7 * qmc.LatinHypercube(d=d, seed=seed).random(k)
        phys = space.from_unit(torch.as_tensor(u, dtype=torch.float64)).numpy()
        for i in range(k):
            x = np.asarray(base_x[:lay.n_cal], float).copy()
            x[:d] = phys[i]
            out[f"spread start {i + 1}"] = x
    return out


def effect_start(lay: Layout, effect: str, ladder: dict[str, float]) -> np.ndarray:
    """A candidate's parameters ``(n_p,)`` at a global start: the middle of its box, and the
    parameter that sizes it at its ladder magnitude where the screen found one."""
    cols = lay.cols(effect)
    x = 0.5 * (lay.lo[cols] + lay.hi[cols])
    j = size_col(lay, effect)
    if effect in ladder and j is not None:
        x[list(cols).index(j)] = ladder[effect]
    return x


def size_col(lay: Layout, effect: str) -> int | None:
    """The column of the parameter that sizes candidate ``effect``
    (:attr:`~solderpyro.effects.Effect.size_index`), or None when several do."""
    cols = lay.cols(effect)
    if len(cols) == 1:
        return int(cols[0])
    eff = (None if lay.fx_all is None else
           next((e for e in lay.fx_all.effects if e.name == effect), None))
    k = None if eff is None else eff.size_index
    return None if k is None else int(cols[k])


def global_refits(lay: Layout, fe: SpecimenModels, meas: Any, sigma: float,
                  base: dict[str, Any], scores: list[Score], local: list[Refit],
                  scout_fe: SpecimenModels | None = None) -> tuple[dict[str, Any], list[Refit]]:
    """Every candidate, and the base model itself, refitted from several starts.

    For the base model and each candidate that does not saturate the data: the starts of
    :func:`spread_starts` (and, for a candidate the screen left out, the base point), all
    models advancing together for :data:`SCOUT_ITERS` Levenberg-Marquardt iterations through
    ``scout_fe``, the cheap model that ranks the starts
    (:func:`~solderpyro.config.compose.coarsened`). The best start of each model goes on to
    convergence through the cheap model, then takes one iteration through the run's own FE;
    where it then beats the model's local refit from the base point (``local``), it goes on
    to convergence there. (A start ranked best after a few iterations can still be far from
    its optimum: held to the local refit at that point, the stress-free-temperature refit of
    the moderate residual-stress data stopped at chi2 2,341 where its optimum is 2,161.)
    A base model that ends lower than ``base`` replaces it, and every candidate's likelihood
    ratio is taken against the better base.

    Args:
        lay, fe, meas, sigma: as :func:`first_refits`.
        base: the base fit (``"x" (n_col,)``, ``"chi2"``, ...).
        scores: the screen (orders the work; its ladder magnitudes start the effects).
        local: the first step's refits from the base point (may be empty).
        scout_fe: the model the starts are ranked with (None: ``fe``).
    Returns:
        ``(base, first)``: the base fit (``base`` itself, or the better one with ``"start"``
        naming where it came from and ``"global": True``) and one
        :class:`~solderpyro.diagnose.decide.Refit` per candidate refitted, screen order.
    """
    ladder = ladder_values(scores)
    x_b = np.asarray(base["x"], float)
    free_dof = len(meas.value_um) - lay.n_cal
    order = [sc.effect for sc in sorted(scores, key=lambda s: -s.statistic)
             if not saturates(sc.dof, free_dof)]
    done = {r.name: r for r in local if r.ok}

    def free_of(name: str) -> tuple[str, ...]:
        return () if name == "baseline" else (name,)

    starts = spread_starts(lay, x_b)
    models: dict[str, tuple[tuple[str, ...], np.ndarray]] = {}
    for label, th in starts.items():
        models[f"baseline|{label}"] = ((), lay.row(th))
        for c in order:
            x = lay.row(th)
            x[lay.cols(c)] = effect_start(lay, c, ladder)
            models[f"{c}|{label}"] = ((c,), x)
    for c in order:
        if c not in done:  # never refitted from the base point: that start too
            x = x_b.copy()
            x[lay.cols(c)] = effect_start(lay, c, ladder)
            models[f"{c}|{BASE_POINT}"] = ((c,), x)
    log.info("diagnose: global refits: the base model and %d candidates from %d starts each "
             "(%d fits, %d iterations each%s before the best start of each goes on)",
             len(order), len(starts), len(models), SCOUT_ITERS,
             "" if scout_fe is None else " on the half-resolution model")
    scout = fit_models(lay, scout_fe or fe, meas, sigma, models, iters=SCOUT_ITERS)
    best: dict[str, tuple[str, LMFit]] = {}
    spread: dict[str, tuple[str, LMFit]] = {}  # each model's best start across the box
    for key, f in scout.items():
        name, label = key.split("|", 1)
        if name not in best or f.chi2 < best[name][1].chi2:
            best[name] = (label, f)
        if label != BASE_POINT and (name not in spread or f.chi2 < spread[name][1].chi2):
            spread[name] = (label, f)
    if scout_fe is not None:
        # each best start on to convergence through the cheap model, then evaluated through
        # the run's own FE (its chi-square is the one the local refit is held to); where the
        # base point led the scouting, the best start across the box goes on too (a base fit
        # already at the noise level leads any start still on its way after a few
        # iterations, and from it an effect the constants absorbed goes back to "off")
        away = {n: spread[n] for n, (lb, _) in best.items() if lb == BASE_POINT and n in spread}
        todo = {n: (free_of(n), f.x) for n, (_, f) in best.items() if not f.converged}
        todo.update({f"{n}|away": (free_of(n), f.x) for n, (_, f) in away.items()})
        on = fit_models(lay, scout_fe, meas, sigma, todo)
        for n, (lb, f) in away.items():
            here = on.get(n, best[n][1])
            if on[f"{n}|away"].chi2 < here.chi2:
                best[n] = (lb, f)
                on[n] = on[f"{n}|away"]
        log.info("diagnose: global refits' best starts, converged on the half-resolution "
                 "model: %s", ", ".join(f"{n} from {lb} {on[n].chi2 if n in on else f.chi2:.1f}"
                                        for n, (lb, f) in best.items()))
        cheap = {n: (on[n] if n in on else f) for n, (_, f) in best.items()}
        full, bounds = through_own_fe(lay, fe, meas, sigma, cheap)
        bounds.pop("baseline", None)
        best = {n: (lb, full[n]) for n, (lb, _) in best.items()}
        reach = within_reach(bounds, {n: r.chi2 for n, r in done.items()})
    else:
        reach = {n for n in best if n != "baseline"}
    go_on: dict[str, tuple[tuple[str, ...], np.ndarray]] = {}
    behind = []
    for name, (_, f) in best.items():
        held = done.get(name)
        if held is not None and held.chi2 <= f.chi2:
            continue  # the local refit is already better than any scout
        if name == "baseline" and f.chi2 >= base["chi2"]:
            continue
        if name != "baseline" and name not in reach:
            behind.append(f"{name} {f.chi2:.1f}")
            continue
        if not f.converged:
            go_on[name] = (free_of(name), f.x)
    if behind:
        log.info("diagnose: global refits left at their half-resolution optimum (chi2 "
                 "through the run's own FE there), too far behind the best to overtake it: %s",
                 ", ".join(behind))
    more = fit_models(lay, fe, meas, sigma, go_on) if go_on else {}
    fin = {name: (label, more.get(name, f)) for name, (label, f) in best.items()}
    nb = dict(base)
    lb, fb = fin["baseline"]
    if fb.chi2 < base["chi2"] - REFIT_TOL:
        log.info("diagnose: the base model refitted from %s: chi2 %.1f -> %.1f", lb,
                 base["chi2"], fb.chi2)
        nb.update({"x": fb.x, "chi2": float(fb.chi2), "start": f"{lb} (global refit)",
                   "history": [*base["history"], float(fb.chi2)], "global": True})
    n_starts = len(starts)
    first = []
    for c in order:
        label, f = fin[c]
        r = Refit((c,), float(f.chi2), len(lay.cols(c)), f.x, float(nb["chi2"]),
                  starts=n_starts + (0 if c in done else 1))
        held = done.get(c)
        if held is not None and held.chi2 <= r.chi2:
            r = dataclasses.replace(held, base_chi2=float(nb["chi2"]),
                                    starts=held.starts + n_starts)
        if not r.ok and (nb.get("global") or c not in reach):
            # nested in the (better) base: with the effect off it is that base (LR 0); a refit
            # left at its cheap optimum for being out of reach gains nothing more at best
            r = Refit((c,), float(nb["chi2"]), r.dof, lay.row(nb["x"][:lay.n_cal]),
                      float(nb["chi2"]), starts=r.starts)
        first.append(r)
    log.info("diagnose: global refits (base chi2 %.1f): %s", nb["chi2"], ", ".join(
        f"{r.name} {r.chi2:.1f}{'' if r.ok else ' (failed)'}" for r in first))
    return nb, first


@dataclass(frozen=True)
class Reach:
    """One global refit where its half-resolution stage ended (chi-squares against the noise).

    Attributes:
        cheap: at the cheap model's optimum, by the cheap model.
        gain: that fit's last iteration's gain (below ``LM_TOL`` where it converged; an
            unconverged fit may still gain about this much per iteration).
        full: the run's own FE at the same point (an upper bound of the model's optimum
            there).
    """

    cheap: float
    gain: float
    full: float

    @property
    def floor(self) -> float:
        """A lower bound of what the model could reach through the run's own FE in the
        :data:`LM_ITERS` iterations it would be given: the cheap optimum, less twice the
        resolution's change there (the FE's optimum cannot lie below the cheap model's by much
        more than the two models differ near it), less :data:`LM_ITERS` times the last gain,
        less :data:`REACH_REL` of it."""
        shift = abs(self.full - self.cheap)
        return (1.0 - REACH_REL) * self.cheap - 2.0 * shift - LM_ITERS * self.gain


def last_gain(f: LMFit) -> float:
    """The chi-square gained by a fit's last accepted iteration (0 without two)."""
    h = f.history
    return float(max(h[-2] - h[-1], 0.0)) if len(h) >= 2 else 0.0


def through_own_fe(lay: Layout, fe: Any, meas: Any, sigma: float, cheap: dict[str, LMFit]
                   ) -> tuple[dict[str, LMFit], dict[str, Reach]]:
    """Fits ended on the cheap model, each evaluated once through the run's own FE (one batched
    solve of one row per fit).

    Returns:
        ``(full, bounds)``: per name, the fit at its cheap optimum with the FE's chi-square
        (not converged there), and its :class:`Reach`.
    """
    names = list(cheap)
    there = chi2_at(lay, fe, meas, sigma, np.array([cheap[n].x for n in names]))
    full = {n: LMFit(cheap[n].x.copy(), float(c), cheap[n].free)
            for n, c in zip(names, there, strict=True)}
    bounds = {n: Reach(cheap[n].chi2, last_gain(cheap[n]), full[n].chi2) for n in names}
    return full, bounds


def within_reach(refits: dict[str, Reach], local: dict[str, float]) -> set[str]:
    """The candidates whose global refit goes on to convergence through the run's own FE.

    The lead is the best chi-square already reached through the FE (the candidates' cheap
    optima evaluated by it, their local refits ``local``). A candidate whose
    :attr:`Reach.floor` lies more than :data:`~solderpyro.diagnose.decide.APART_CHI2` (the tie
    margin) above the lead can neither overtake it nor tie with it: converging it would not
    change the verdict, and its reported chi-square (the FE's at its cheap optimum) is an
    upper bound.

    Args:
        refits: candidate -> its :class:`Reach`.
        local: candidate -> chi-square of its local refit from the base point.
    Returns:
        the names of ``refits`` within reach.
    """
    if not refits:
        return set()
    lead = min([r.full for r in refits.values()] + list(local.values()))
    return {n for n, r in refits.items() if r.floor <= lead + APART_CHI2}


def base_starts(setup: Any, info: Any, theta: np.ndarray, idx: np.ndarray, fe_ok: bool
                ) -> dict[str, np.ndarray]:
    """Starts of the base fit, name -> ``(n_cal,)`` row (physical units).

    Args:
        setup: the run's Setup; info: its :class:`~solderpyro.config.rundir.RunInfo` (the design's
            stop reason and FE best fit); theta: ``(N, n_cal)`` posterior draws; idx: the
            picked draws (:func:`pick_draws`); fe_ok: whether the FE check accepted the
            posterior.
    """
    design = info.design
    bf = design.best_fit.get("x") or {}
    names = list(info.parameters)
    has_bf = (bool(names) and all(nm in bf for nm in names)
              and len(names) == theta.shape[1])
    # where the design stopped because the model misfits, the posterior draws sit in
    # surrogate islands and are no starts (on the modulus-temperature field data they
    # scouted at chi2 1e5-3e5 against 1.7e4 from the best fit and the literature
    # constants): the calibration's own FE best fit and the literature constants
    islands = has_bf and design.reason == "misfit"
    out = starts(setup, theta, idx, fe_ok and not islands)
    if islands:
        # the calibration's best fit already started from the literature constants too (its
        # misfit test): no second scout from them
        scouted = "literature constants" in design.best_fit.get("starts", [])
        out = {} if scouted else {"literature constants": out["literature constants"]}
    if has_bf:
        out["the calibration's FE best fit"] = np.array([bf[nm] for nm in names])
    return out


def linearised_steps(scores: list[Score], base_chi2: float, n: int, n_cal: int, sigma: float,
                     floor: Floor, n_cand: int
                     ) -> tuple[list[list[Judged]], tuple[str, ...], list[str]]:
    """Without FE refits: the screen's linearised statistics stand in for them.

    Each score (ladder applied) becomes a refit to its ``chi2_after`` from ``base_chi2`` (the
    linearised misfit), judged as one step on ``n`` values. Returns ``(steps, chosen, tie)``
    as :func:`refit_steps`."""
    steps = [judge([Refit((sc.effect,), sc.chi2_after, max(sc.dof, 1), np.zeros(0), base_chi2)
                    for sc in scores], n, n_cal, sigma, floor, n_cand)]
    chosen, tie = forward_step(steps[0], ())
    return steps, chosen, tie
