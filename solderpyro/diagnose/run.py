"""``solderpyro diagnose RUN_DIR``: does the calibrated model fit, and which effect is missing?

Data flow: the run directory of ``solderpyro calibrate`` (its record, ``data.csv``,
``draws.npz``) -> posterior predictive checks of the surrogate predictive (with code
uncertainty) -> the FE at a few posterior draws, with every candidate effect switched on at
"off", and finite-difference Jacobians w.r.t. the calibrated parameters and each effect's
parameters -> misfit chi-square after a linearised refit and a score test per effect
(:mod:`solderpyro.diagnose.stats`) -> ranking, confusions, verdict -> ``diagnosis.json``,
``diagnosis.md`` and figures.

Every FE run goes through the calibration's run store (:class:`~solderpyro.store.RunStore`,
the run record's ``store``), registered with the solver's problem, times, field flag, dtype and
the effects switched on: each run is kept as soon as its batch finishes, a rerun of the
diagnosis reads every run back, and rows that several stages share (the Jacobians' base and
forward rows, the refits' first steps, a refit that did not move) are solved once. Each
stage's seconds and FE runs (computed, reused) are logged and written to ``diagnosis.json``
(``"timing"``) and ``diagnosis.md``.

The FE is exact (no code uncertainty), so the misfit and score statistics are measured against
the measurement noise alone: the noise the data file states (``sigma_um``) when there is one,
otherwise the posterior median of sigma.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import logging
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch
from scipy.stats import chi2 as _chi2

from solderpyro.calibration.intervals import reported_interval
from solderpyro.diagnose.decide import (
    APART_CHI2,
    EXPLAINED_SD,
    REFIT_TOL,
    Floor,
    Judged,
    Refit,
    effect_size,
    explained,
    forward_step,
    forward_steps,
    judge,
    load_floor,
    remains,
    saturates,
    share_text,
    to_refit,
)
from solderpyro.diagnose.fingerprint import Fingerprints, fingerprints
from solderpyro.diagnose.refits import MAX_REFITS, Layout, base_fit, layout, refit_candidates
from solderpyro.diagnose.ruleout import cannot_rule_out, describe
from solderpyro.diagnose.stats import (
    Misfit,
    PredictiveCheck,
    Score,
    confusion,
    evidence,
    misfit,
    predictive_check,
    score_test,
)
from solderpyro.rundir import RunInfo
from solderpyro.specimen import SpecimenModels

log = logging.getLogger("solderpyro")

#: an effect whose signature the calibrated parameters mimic to within this share is not
#: flagged however large its statistic: below it the linearised projection (finite-difference
#: Jacobians, steps 1e-3 of the box) is not accurate enough to trust what is left
MIN_IDENTIFIABLE = 0.01
#: magnitudes (share of the way from "off" to the box's far edge) of the likelihood-ratio ladder
LADDER = (0.15, 0.4, 1.0)
#: candidates whose fingerprints are drawn (best first)
TOP = 3


@dataclass
class Diagnosis:
    """What :func:`diagnose` found (also written to ``diagnosis.json``)."""

    misfit: bool
    verdict: str
    ranking: list[dict]
    check: dict
    indistinguishable: list[list[str]]
    suggestions: list[str]
    separation: dict | None = None
    #: stage -> ``{"seconds", "fe_runs" (computed), "fe_reused" (read from the run store or
    #: shared with another row)}``, then ``"total"``
    timing: dict[str, dict[str, float | int]] = dataclasses.field(default_factory=dict)
    #: the denoised residual (full-field data): :meth:`~.denoise.Smooth.summary`
    denoise: dict | None = None
    #: the FE's best fit every statistic is taken at (start, chi2 history, parameters)
    base: dict | None = None
    #: candidates whose refit ended above its base after a retry: reported, never ranked
    failed: list[dict] = dataclasses.field(default_factory=list)
    #: effects the forward steps added, in order
    selected: list[str] = dataclasses.field(default_factory=list)
    #: True: the selected effects (or a tie) explain the misfit; False: none of the candidates
    #: does; None: no misfit
    explained: bool | None = None
    #: the discretization floor used (:class:`~solderpyro.diagnose.decide.Floor`)
    floor: dict | None = None
    #: per forward step, each refit judged (:func:`~solderpyro.diagnose.decide.judge`)
    steps: list[list[dict]] = dataclasses.field(default_factory=list)
    #: where the model fits: candidates the data do not reject that would move a constant
    #: outside its reported interval (:func:`~solderpyro.diagnose.ruleout.cannot_rule_out`)
    cannot_rule_out: list[dict] = dataclasses.field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {"misfit": self.misfit, "explained": self.explained, "verdict": self.verdict,
                "selected": self.selected, "ranking": self.ranking, "failed": self.failed,
                "check": self.check, "base": self.base, "floor": self.floor,
                "steps": self.steps, "indistinguishable": self.indistinguishable,
                "suggestions": self.suggestions, "separation": self.separation,
                "cannot_rule_out": self.cannot_rule_out,
                "denoise": self.denoise, "timing": self.timing}


#: stage -> its label in the log and in diagnosis.md
STAGES = {"load": "loading the run", "predictive_check": "posterior predictive check",
          "best_fit": "FE best fit (baseline refit)",
          "fe_jacobians": "FE Jacobians (+ ladder runs)", "score_tests": "score tests",
          "ladder": "likelihood-ratio ladder", "profile_refits": "profile refits",
          "verdict": "ranking and verdict", "cannot_rule_out": "what the data cannot rule out",
          "separation": "separation",
          "fingerprints": "fingerprints (refit predictions, denoising)",
          "write": "writing (figures)"}


class _Costs:
    """Seconds and FE runs (computed, reused) per stage of a diagnosis."""

    def __init__(self) -> None:
        self.t0 = time.perf_counter()
        self.fe: SpecimenModels | None = None
        self.stages: dict[str, dict[str, float | int]] = {}

    def _counts(self) -> tuple[int, int]:
        return (0, 0) if self.fe is None else (self.fe.computed, self.fe.reused)

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        t0, (c0, r0) = time.perf_counter(), self._counts()
        yield
        c1, r1 = self._counts()
        row = {"seconds": round(time.perf_counter() - t0, 3), "fe_runs": c1 - c0,
               "fe_reused": r1 - r0}
        self.stages[name] = row
        log.info("diagnose: %-30s %8.2f s, %4d FE runs computed, %4d reused", STAGES[name],
                 row["seconds"], row["fe_runs"], row["fe_reused"])

    def table(self) -> dict[str, dict[str, float | int]]:
        """The stages, then ``"total"`` (wall time since the start)."""
        total = {"seconds": round(time.perf_counter() - self.t0, 3),
                 "fe_runs": sum(int(r["fe_runs"]) for r in self.stages.values()),
                 "fe_reused": sum(int(r["fe_reused"]) for r in self.stages.values())}
        return {**self.stages, "total": total}


def run_store(info: RunInfo, run_dir: Path) -> Any:
    """The run store of the calibration (its record's ``store``; a relative path is taken
    from the working directory, as ``calibrate`` took it), else ``run_dir/fe_store``."""
    from solderpyro.store import RunStore

    root = info.store
    return RunStore(Path(root) if root else run_dir / "fe_store")


def load_run(run_dir: str | Path) -> dict[str, Any]:
    """Read what ``solderpyro calibrate`` left in ``run_dir`` for a diagnosis.

    Returns:
        dict with ``run`` (:class:`~solderpyro.rundir.RunDir`), ``info`` (its
        :class:`~solderpyro.rundir.RunInfo`), ``setup`` (:class:`~solderpyro.configure.Setup`),
        ``meas`` (measurements), ``draws`` (:meth:`~solderpyro.rundir.Draws.arrays`).
    Raises:
        FileNotFoundError naming the missing file; RunDirError naming the file and the key
        of a record this version cannot read.
    """
    from solderpyro.configure import build, compose
    from solderpyro.rundir import RUN_FILES, RunDir
    from solderpyro.specimen import output_points

    run = RunDir.read(run_dir, RUN_FILES)
    setup = build(compose(list(run.info.overrides)))
    meas = run.measurements(valid_points=output_points(setup.problem))
    return {"run": run, "info": run.info, "setup": setup, "meas": meas,
            "draws": run.draws().arrays()}


def _pick_draws(theta: np.ndarray, k: int, seed: int) -> np.ndarray:
    """Row indices: the draw nearest the component-wise median (scaled), then random ones."""
    med = np.median(theta, 0)
    sc = theta.std(0) + 1e-300
    first = int(np.argmin((((theta - med) / sc) ** 2).sum(1)))
    rng = np.random.default_rng(seed)
    rest = rng.choice(np.delete(np.arange(len(theta)), first), size=max(k - 1, 0),
                      replace=False)
    return np.concatenate([[first], rest]).astype(int)


@dataclass
class _Columns:
    """Finite-difference design: which FE member perturbs which parameter column."""

    names: list[str]  # every column: calibrated parameters, then candidates' parameters
    owner: list[str]  # "theta" or the effect's name
    step: np.ndarray  # physical step per column
    central: np.ndarray  # bool per column


def _fd_design(box_names, box_lo, box_hi, cands: dict[str, Any], rel: float) -> _Columns:
    names, owner, step, central = [], [], [], []
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
    return _Columns(names, owner, np.array(step), np.array(central))


def fe_jacobians(setup: Any, theta: np.ndarray, run_effects: tuple[str, ...],
                 candidates: tuple[str, ...], times: tuple[float, ...], field: bool,
                 rel: float = 1e-3, progress: bool = True, fe: SpecimenModels | None = None
                 ) -> dict[str, Any]:
    """FE outputs and finite-difference Jacobians at calibrated draws, candidates at "off".

    Args:
        setup: typed problem and parameter box; ``setup.space`` are the calibrated Anand
            constants.
        theta: ``(K, n_cal)`` calibrated parameter draws (Anand constants of ``setup.space``,
            then the run's own effects' parameters), physical units.
        run_effects: effects already on in the calibration; candidates: effects to test.
        times: output times, s; field: also the 31 x 18 grid.
        rel: step as a share of each parameter's box width (one-sided at a box edge).
        fe: the diagnosis's :class:`~solderpyro.specimen.SpecimenModels` (run store, models);
            None: solve directly.
    Returns:
        dict: ``V (K, n_time, n_out)`` at the draws (um), ``J (K, n_time, n_out, n_col)``
        (um per unit), ``cols`` (:class:`_Columns`), ``names`` (output labels), ``times``,
        ``ladder`` (per one-parameter candidate, its magnitudes and the FE there), ``n_ladder``
        (FE rows of the ladder). The draws' rows and the ladder's are one batched solve.
    """
    from solderpyro.effects import effect_set
    from solderpyro.specimen import calibration_box

    fe = fe if fe is not None else SpecimenModels(setup)

    fx_all = effect_set(tuple(run_effects) + tuple(candidates), times, setup.effect_bounds)
    cands = {e.name: e for e in fx_all.effects if e.name in candidates}
    cal = calibration_box(setup, effect_set(run_effects, times, setup.effect_bounds)
                          if run_effects else None)
    cols = _fd_design(list(cal.names), list(cal.lower), list(cal.upper), cands, rel)
    n_cal = cal.dim
    off = np.array([v for e in cands.values() for v in e.off], float)
    rows = []
    for th in theta:
        base = np.concatenate([th, off])
        rows.append(base)
        for c in range(len(cols.names)):
            e = np.zeros_like(base)
            e[c] = cols.step[c]
            rows.append(base + e)
            if cols.central[c]:
                rows.append(base - e)
    # a ladder of finite magnitudes per one-parameter candidate (first draw): the likelihood
    # ratio sees effects whose first derivative at "off" vanishes (thresholds, e.g. yielding)
    ladder: dict[str, np.ndarray] = {}
    base0 = np.concatenate([theta[0], off])
    for ename, eff in cands.items():
        if eff.n_params != 1:
            continue
        j = n_cal + int(np.flatnonzero(np.array(cols.owner[n_cal:]) == ename)[0])
        ladder[ename] = ladder_values(eff)
        for v in ladder[ename]:
            r = base0.copy()
            r[j] = v
            rows.append(r)
    P = torch.tensor(np.array(rows), dtype=torch.float64)
    n_lad = sum(len(v) for v in ladder.values())
    log.info("diagnose: %d FE rows (%d draws x %d Jacobian columns, %d ladder runs, "
             "candidates: %s)", len(rows), len(theta), len(cols.names), n_lad,
             ", ".join(candidates) or "none")
    res = fe.runs(P, times, field, fx_all, progress=progress)
    V = res.V.numpy()
    if not bool(res.ok.all()):
        bad = [r for r in res.reasons if r]
        raise RuntimeError(f"{len(bad)} FE runs of the diagnosis failed: {bad[:2]}")
    K = len(theta)
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
                J[k, ..., c] = (plus - V[i]) / (2 * cols.step[c])
                i += 1
            else:
                J[k, ..., c] = (plus - Vb[k]) / cols.step[c]
    VL = {}
    for ename, vals in ladder.items():
        VL[ename] = (vals, V[i:i + len(vals)])
        i += len(vals)
    return {"V": Vb, "J": J, "cols": cols, "names": list(res.names), "n_cal": n_cal,
            "fe": fe, "ladder": VL, "n_ladder": n_lad,
            "times": tuple(float(t) for t in res.times)}


def ladder_values(eff: Any) -> np.ndarray:
    """``(len(LADDER),)`` magnitudes of a one-parameter effect ``eff`` (bound
    :class:`~solderpyro.effects.Effect`): the shares :data:`LADDER` of the way from "off" to
    the farther edge of its box, in its own units."""
    b, o = eff.params, float(eff.off[0])
    far = b.upper[0] if b.upper[0] - o >= o - b.lower[0] else b.lower[0]
    return o + np.asarray(LADDER) * (far - o)


def _group(cols: _Columns, owner: str) -> np.ndarray:
    return np.array([j for j, o in enumerate(cols.owner) if o == owner], dtype=int)


def analyse(y: np.ndarray, V: np.ndarray, J: np.ndarray, cols: _Columns, sigma: float,
            ladder: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
            ) -> tuple[Misfit, list[Score], list[list[Score]]]:
    """Misfit and score tests at each draw.

    Args:
        y: ``(n,)`` data, um; V: ``(K, n)`` FE at the draws; J: ``(K, n, n_col)`` Jacobians;
        cols: columns; sigma: noise sd, um.
    Returns:
        ``(misfit at the first draw, scores at the first draw (one per candidate), scores per
        draw)``.
    """
    mf, scores, per_draw = score_tests(y, V, J, cols, sigma)
    apply_ladder(mf, scores, y, J[0], cols, sigma, ladder)
    return mf, scores, per_draw


def score_tests(y: np.ndarray, V: np.ndarray, J: np.ndarray, cols: _Columns, sigma: float
                ) -> tuple[Misfit, list[Score], list[list[Score]]]:
    """:func:`analyse` without the likelihood-ratio ladder: the misfit at the first draw and
    the score tests at each draw."""
    w = np.full(len(y), 1.0 / sigma**2)
    th = _group(cols, "theta")
    effects = [o for o in dict.fromkeys(cols.owner) if o != "theta"]
    per_draw = []
    for k in range(V.shape[0]):
        r = y - V[k]
        per_draw.append([score_test(e, r, J[k][:, th], J[k][:, _group(cols, e)], w)
                         for e in effects])
    mf = misfit(y - V[0], J[0][:, th], w)
    return mf, per_draw[0], per_draw


def apply_ladder(mf: Misfit, scores: list[Score], y: np.ndarray, J0: np.ndarray,
                 cols: _Columns, sigma: float,
                 ladder: dict[str, tuple[np.ndarray, np.ndarray]] | None) -> None:
    """The likelihood ratio of each one-parameter candidate over its ladder of magnitudes
    (first draw, ``J0 (n, n_col)``); where it is the larger statistic it replaces the score's
    (``scores`` are changed in place)."""
    w = np.full(len(y), 1.0 / sigma**2)
    th = _group(cols, "theta")
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


def diagnose(run_dir: str | Path, candidates: tuple[str, ...] | None = None, n_draws: int = 3,
             seed: int = 0, progress: bool = True, refit: bool = True,
             batch_size: int = 64) -> Diagnosis:
    """Diagnose the calibration in ``run_dir``; writes diagnosis.json, diagnosis.md, figures.

    Every FE run goes through the calibration's run store (:func:`run_store`): a second
    diagnosis of the same run directory reads them all back. Each stage's cost (seconds, FE
    runs computed and reused) is logged and kept in :attr:`Diagnosis.timing`.

    Args:
        run_dir: a directory written by ``solderpyro calibrate``.
        candidates: effect names to test (default: every registered effect that the run did
            not switch on).
        n_draws: posterior draws at which the FE and its Jacobians are evaluated when the FE
            check accepted the posterior (the first is the FE's best fit from the draw nearest
            the posterior median; the ranking uses it, the others show how stable the screen
            is over the posterior); one, the best fit, when the FE check rejected it.
        refit: take every statistic at the FE's own best fit
            (:func:`~solderpyro.diagnose.refits.base_fit`) and let the FE refits with each
            screened candidate decide (:mod:`solderpyro.diagnose.decide`); False: at the
            posterior draw, the linearised statistics standing in for the refits.
        batch_size: FE runs per batched solve (each batch is stored as soon as it finishes).
    Returns:
        :class:`Diagnosis`.
    """
    from solderpyro.effects import EFFECTS
    from solderpyro.specimen import observation_index

    cost = _Costs()
    d = Path(run_dir)
    with cost.stage("load"):
        run = load_run(d)
        info, setup, meas, dr = run["info"], run["setup"], run["meas"], run["draws"]
        run_effects = tuple(info.effects)
        if candidates is None:
            candidates = tuple(n for n in EFFECTS if n not in run_effects)
        unknown = [c for c in candidates if c not in EFFECTS]
        if unknown:
            raise ValueError(f"unknown effect(s) {unknown}; valid: {', '.join(EFFECTS)}")
        store = run_store(info, d)
        cost.fe = fe = SpecimenModels(setup, store, batch_size)
        log.info("diagnose: FE runs kept in the run store %s", store.root)
    with cost.stage("predictive_check"):
        y = np.asarray(meas.value_um, float)
        sigma_draws = dr["sigma"]
        sig_known = info.sigma_known
        sigma = float(sig_known) if sig_known else float(np.median(sigma_draws))
        pc = predictive_check(y, dr["process"], dr["sigma_pred"], seed=seed)
    n = len(y)
    lay = layout(setup, run_effects, candidates, meas)
    field, times = lay.field, lay.times
    floor = load_floor("field" if field else "points")
    # other posterior draws only where the FE check accepted the posterior (issue 20: never a
    # draw the FE rejected)
    fe_ok = info.checks.fe_ok
    idx = _pick_draws(dr["theta"], n_draws if fe_ok else 1, seed)
    thetas = dr["theta"][idx].copy()
    base: dict[str, Any] | None = None
    if refit:
        with cost.stage("best_fit"):
            design = info.design
            bf = design.best_fit.get("x") or {}
            names = list(info.parameters)
            has_bf = (bool(names) and all(nm in bf for nm in names)
                      and len(names) == dr["theta"].shape[1])
            # where the design stopped because the model misfits, the posterior draws sit in
            # surrogate islands and are no starts (on the modulus-temperature field data they
            # scouted at chi2 1e5-3e5 against 1.7e4 from the best fit and the literature
            # constants): the calibration's own FE best fit and the literature constants
            islands = has_bf and design.reason == "misfit"
            starts = _starts(setup, dr["theta"], idx, fe_ok and not islands)
            if islands:
                # the calibration's best fit already started from the literature constants
                # too (its misfit test, since session 29): no second scout from them
                scouted = "literature constants" in design.best_fit.get("starts", [])
                starts = {} if scouted else {
                    "literature constants": starts["literature constants"]}
            if has_bf:
                starts["the calibration's FE best fit"] = np.array([bf[nm] for nm in names])
            base = base_fit(lay, fe, meas, sigma, starts)
            thetas[0] = base["x"][:lay.n_cal]
            log.info("diagnose: FE best fit (start: %s%s), chi2 %s", base["start"],
                     "" if not base["scouts"] else "; scouts " + ", ".join(
                         f"{k} {v:.1f}" for k, v in base["scouts"].items()),
                     " -> ".join(f"{c:.1f}" for c in base["history"]))
    with cost.stage("fe_jacobians"):
        fej = fe_jacobians(setup, thetas, run_effects, candidates, times, field,
                           progress=progress, fe=fe)
    with cost.stage("score_tests"):
        ti, oi = observation_index(meas, fej["times"], tuple(fej["names"]))
        V = fej["V"][:, ti, oi]
        J = fej["J"][:, ti, oi, :]
        mf, scores, per_draw = score_tests(y, V, J, fej["cols"], sigma)
    with cost.stage("ladder"):
        lad = {k: (v, VL[:, ti, oi]) for k, (v, VL) in fej["ladder"].items()}
        apply_ladder(mf, scores, y, J[0], fej["cols"], sigma, lad)
    base_chi2 = base["chi2"] if base is not None else mf.chi2
    fits = None
    steps: list[list[Judged]] = []
    chosen: tuple[str, ...] = ()
    tie: list[str] = []
    screened = to_refit(scores, len(candidates), remains(base_chi2, n, lay.n_cal), MAX_REFITS,
                        MIN_IDENTIFIABLE, n - lay.n_cal)
    if not refit:  # the linearised statistics stand in for the refits
        steps = [judge([Refit((sc.effect,), sc.chi2_after, max(sc.dof, 1), np.zeros(0),
                              mf.chi2) for sc in scores], n, lay.n_cal, sigma, floor,
                       len(candidates))]
        chosen, tie = forward_step(steps[0], ())
    elif base is not None and screened:
        with cost.stage("profile_refits"):
            fits, steps, chosen, tie = _refit_steps(lay, fe, meas, sigma, base, scores,
                                                   screened, floor,
                                                   len(candidates))
    with cost.stage("verdict"):
        diag = _verdict(mf, pc, scores, per_draw, sigma, steps, chosen, tie, base_chi2,
                        lay.n_cal, floor)
        for recs, st in zip(diag.steps, steps, strict=True):  # where each refit ended
            for rec, j in zip(recs, st, strict=True):
                if len(j.refit.x) == len(lay.names):
                    rec["x"] = lay.named(j.refit.x, j.refit.effects)
        diag.base = None if base is None else {
            "chi2": base["chi2"], "start": base["start"], "scouts": base["scouts"],
            "history": base["history"], "converged": base["converged"],
            "fe_check_ok": fe_ok, "x": {nm: float(v) for nm, v in zip(
                fej["cols"].names[:lay.n_cal], base["x"][:lay.n_cal], strict=True)}}
    if not diag.misfit and not diag.selected and lad:
        with cost.stage("cannot_rule_out"):
            _rule_out(diag, d, lay, fej, y, V[0], J[0][:, _group(fej["cols"], "theta")],
                      sigma, lad, dr["theta"])
    if diag.indistinguishable and fits is not None:
        with cost.stage("separation"):
            group = diag.indistinguishable[0]
            diag.separation = separation(setup, run_effects, candidates, fits, group, meas,
                                         sigma, fe=fe)
            diag.suggestions.insert(0, diag.separation["advice"])
    with cost.stage("fingerprints"):
        preds = None
        if fits is not None:
            # exact fingerprints from the refits, except where a candidate's refit failed
            # (it stopped short: its shape would mislead)
            preds = {m: v for m, v in refit_predictions(setup, run_effects, candidates, fits,
                                                        meas, fe).items()
                     if m == "baseline" or fits[m]["chi2"] <= base_chi2 + REFIT_TOL}
        top = tuple(r["effect"] for r in diag.ranking[:TOP])
        fp = fingerprints(meas, mf.residual, scores, sigma, preds, field, top)
        for r in diag.ranking:
            r["fingerprint_correlation"] = round(fp.correlation[r["effect"]], 4)
            r["fingerprint"] = fp.source[r["effect"]]
        diag.denoise = fp.smooth.summary() if fp.smooth is not None else None
        if diag.explained is False:
            diag.verdict += "; " + _where(meas, fp, sigma)
    with cost.stage("write"):
        figs = _figures(d, diag, meas, pc, fp, sigma, dr, setup)
    diag.timing = cost.table()
    tot = diag.timing["total"]
    log.info("diagnose: total %.1f s, %d FE runs computed, %d reused (store %s)",
             tot["seconds"], tot["fe_runs"], tot["fe_reused"], store.root)
    _write(d, diag, mf, pc, sigma, figs)
    from solderpyro.index import write_index

    write_index(d)
    return diag


def _rule_out(diag: Diagnosis, d: Path, lay: Layout, fej: dict[str, Any], y: np.ndarray,
              v0: np.ndarray, j_theta: np.ndarray, sigma: float,
              lad: dict[str, tuple[np.ndarray, np.ndarray]], draws: np.ndarray) -> None:
    """Fill ``diag.cannot_rule_out`` (and its verdict and suggestions) against the run's
    reported intervals (summary.csv); ``v0 (n,)``, ``j_theta (n, n_cal)`` at the best fit,
    ``draws (N, n_cal)`` the posterior's."""
    summ = d / "summary.csv"
    if not summ.exists():
        return
    with summ.open() as f:
        intervals = {r["parameter"]: reported_interval(r) for r in csv.DictReader(f)}
    names = list(fej["cols"].names[:lay.n_cal])
    found = cannot_rule_out(y, v0, j_theta, sigma, lad, draws, names, lay.lo[:lay.n_cal],
                            lay.hi[:lay.n_cal], intervals)
    params = {e.name: (e.params.names[0], (e.params.units or ("",))[0])
              for e in lay.fx_all.effects if e.n_params == 1}
    for r in found:
        r["text"] = describe(r, *params.get(r["effect"], ("value", "")))
    diag.cannot_rule_out = found
    if found:
        diag.verdict += ("; but the data cannot rule out " + ", ".join(
            r["effect"] for r in found) + ", which would move " + ", ".join(
            dict.fromkeys(nm for r in found for nm in r["outside"]))
            + " outside the reported intervals (see 'What the data cannot rule out')")
        diag.suggestions.append(
            "recalibrate with " + " and with ".join(f"effects=[{r['effect']}]" for r in found)
            + " to see the constants' intervals if it is present: these data cannot tell")


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
    res = fe.runs(X, times, field, fx_all)
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
        mask = np.zeros(V.shape[1:], dtype=bool)
        for i, t in enumerate(times):
            if any(abs(t - s) < 1e-6 for s in ts):
                mask[i] = cols
        for i, t in enumerate(times):
            for j, n in enumerate(out_names):
                if (t, n) in measured:
                    mask[i, j] = False
        if not mask.any() or any(np.array_equal(mask, m) for m in seen):
            continue  # nothing new, or the same values as an option already listed
        seen.append(mask)
        worst: dict[str, Any] | None = None
        for a in range(len(X)):
            for b in range(a + 1, len(X)):
                dV = np.where(mask, V[a] - V[b], 0.0)
                c2 = float((dV**2).sum() / sigma**2)
                if worst is None or c2 < worst["chi2_apart"]:
                    ti, oj = (int(v) for v in np.unravel_index(int(np.argmax(np.abs(dV))),
                                                                dV.shape))
                    worst = {"measurement": label, "n_new": int(mask.sum()),
                             "pair": [labels[a], labels[b]],
                             "rms_diff_um": float(np.sqrt((dV[mask] ** 2).mean())),
                             "max_diff_um": float(np.abs(dV[ti, oj])), "time_s": times[ti],
                             "point": out_names[oj], "xy_mm": list(xy.get(out_names[oj], ())),
                             "chi2_apart": c2}
        if worst is not None:
            options.append(worst)
    options.sort(key=lambda o: -o["chi2_apart"])
    return options, None


def _starts(setup: Any, theta: np.ndarray, idx: np.ndarray, fe_ok: bool
            ) -> dict[str, np.ndarray]:
    """Starts of the base fit: the draw nearest the posterior median; where the FE check
    rejected the posterior, also the literature constants (the run's own effects at their
    posterior median) and the posterior draw farthest from the median in scaled units."""
    out = {"posterior median": theta[idx[0]]}
    if fe_ok:
        return out
    lit = np.median(theta, 0)
    lit[:setup.space.dim] = [setup.anand[nm] for nm in setup.space.names]
    out["literature constants"] = lit
    z = (theta - np.median(theta, 0)) / (theta.std(0) + 1e-300)
    out["farthest posterior draw"] = theta[int(np.argmax((z**2).sum(1)))]
    return out


def _refit_steps(lay: Any, fe: SpecimenModels, meas: Any, sigma: float, base: dict[str, Any],
                 scores: list[Score], screened: list[Score], floor: Floor, n_cand: int
                 ) -> tuple[dict[str, dict[str, Any]], list[list[Judged]], tuple[str, ...],
                            list[str]]:
    """The refits of the screened candidates from the base point, then the forward steps.

    Returns:
        ``(fits, steps, chosen, tie)``: ``fits`` ``{"baseline"|effect: {"chi2", "x"}}`` of the
        first step (for fingerprints and separation); ``steps`` the judged refits per step;
        ``chosen`` the effects added; ``tie`` the candidates that could not be told apart where
        the steps stopped (empty if none).
    """
    n = len(meas.value_um)
    ladder = {sc.effect: sc.lr_value for sc in scores
              if sc.lr_value is not None and (sc.lr or 0.0) > 0.0}
    x_b = np.asarray(base["x"], float)
    starts = {}
    for sc in screened:
        x = x_b.copy()
        if sc.effect in ladder and len(lay.cols(sc.effect)) == 1:
            x[lay.cols(sc.effect)] = ladder[sc.effect]
        starts[sc.effect] = x
    first = refit_candidates(lay, fe, meas, sigma, x_b, base["chi2"], (), starts)
    log.info("diagnose: refits from the base point (chi2 %.1f): %s", base["chi2"], ", ".join(
        f"{r.name} {r.chi2:.1f}{'' if r.ok else ' (failed)'}" for r in first))
    fits: dict[str, dict[str, Any]] = {"baseline": {"chi2": base["chi2"], "x": x_b}}
    fits.update({r.name: {"chi2": r.chi2, "x": r.x} for r in first})
    single = {r.name: r for r in first}

    def refit_next(cur: Refit, chosen: tuple[str, ...], others: list[str]) -> list[Refit]:
        st = {}
        for c in others:  # from the chosen model's fit, c where its own refit put it
            x = cur.x.copy()
            x[lay.cols(c)] = single[c].x[lay.cols(c)]
            st[c] = x
        nxt = refit_candidates(lay, fe, meas, sigma, cur.x, cur.chi2, chosen, st)
        log.info("diagnose: forward step, with %s on (chi2 %.1f): %s", " + ".join(chosen),
                 cur.chi2, ", ".join(f"+{r.name} {r.chi2:.1f}{'' if r.ok else ' (failed)'}"
                                     for r in nxt))
        return nxt

    steps, chosen, tie = forward_steps(first, refit_next, n, lay.n_cal, sigma, floor, n_cand)
    return fits, steps, chosen, tie


def _verdict(mf: Misfit, pc: PredictiveCheck, scores: list[Score],
             per_draw: list[list[Score]], sigma: float, steps: list[list[Judged]],
             chosen: tuple[str, ...], tie: list[str], base_chi2: float, n_cal: int,
             floor: Floor) -> Diagnosis:
    """Ranking and verdict from the judged refits (:mod:`solderpyro.diagnose.decide`'s rules)."""
    n = len(mf.residual)
    first = {j.refit.name: j for j in steps[0]} if steps else {}
    bad_global = remains(base_chi2, n, n_cal)
    any_flag = any(j.flagged for j in first.values())
    bad = bool(bad_global or any_flag)
    entries: list[tuple[dict[str, Any], Score]] = []
    failed: list[tuple[dict[str, Any], Score]] = []
    for i, s in enumerate(scores):
        j = first.get(s.effect)
        ev_draws = [pd[i].evidence for pd in per_draw]
        e: dict[str, Any] = {
            "effect": s.effect, "identifiable": float(s.identifiable),
            "score_statistic": float(s.statistic), "score_dof": s.dof,
            "score_p_value": float(s.p_value), "delta": [float(v) for v in s.delta],
            "likelihood_ratio": s.lr, "best_magnitude": s.lr_value,
            "evidence_over_draws": [round(float(v), 3) for v in ev_draws]}
        if j is not None:
            stat, dof = j.refit.lr, j.refit.dof
            sz = j.size
            e.update({"refit": "converged" if j.refit.ok else "failed",
                      "refit_starts": j.refit.starts, "profile_chi2": j.refit.chi2,
                      "statistic": float(stat), "dof": dof, "p_value": j.p_value,
                      "evidence": round(evidence(stat, dof) if j.refit.ok else 0.0, 4),
                      "chi2_after": j.refit.chi2, **sz.to_json(),
                      "floor_um2": j.floor_um2, "clears_floor": j.clears_floor,
                      "flagged": bool(j.flagged)})
        else:
            # the screen's statistic is a linearised chi-square drop: its size is measured
            # against the base fit's chi-square, as a refit's would be
            after = max(base_chi2 - float(s.statistic), 0.0)
            sz = effect_size(base_chi2, after, n, n_cal, sigma)
            why = (f"{s.dof} parameters the data cannot test: with the calibrated ones they "
                   f"fit any {n} values" if saturates(s.dof, n - n_cal)
                   else f"screen p = {s.p_value:.2g}")
            e.update({"refit": f"not run ({why})", "refit_starts": 0,
                      "profile_chi2": None, "statistic": float(s.statistic), "dof": s.dof,
                      "p_value": float(s.p_value), "evidence": round(float(s.evidence), 4),
                      "chi2_after": after, **sz.to_json(),
                      "floor_um2": floor.of(s.effect), "clears_floor": False, "flagged": False})
        e["explained_share"] = e["systematic_share"]
        (failed if e["refit"] == "failed" else entries).append((e, s))
    # refitted candidates by likelihood ratio, then the screened-out ones by their screen
    entries.sort(key=lambda es: (es[0]["refit"] != "converged", -es[0]["statistic"]))
    ranking = [e for e, _ in entries]
    if entries:
        corr_top = entries[0][1]
        for e, s in entries + failed:
            e["correlation_with_top"] = round(confusion(corr_top, s), 4)
    failed_list = [e for e, _ in failed]
    last = next((j.refit for j in steps[-1] if chosen and j.refit.name == chosen[-1]), None) \
        if steps else None
    chi2_final = last.chi2 if last is not None else base_chi2
    ok_expl = bool(chosen) and not tie and explained(chi2_final, n, sigma, floor)
    ok_tie = bool(tie) and explained(min(j.refit.chi2 for j in steps[-1]
                                         if j.refit.name in tie), n, sigma, floor)
    head = (f"chi2 = {base_chi2:.1f} on {n - n_cal} dof at the FE's best fit; RMS "
            f"{np.sqrt(base_chi2 / n) * sigma:.3g} um = {np.sqrt(base_chi2 / n):.2f} noise sd "
            f"(noise {sigma:.3g} um)")
    suggestions: list[str] = []
    groups = [tie] if tie else []
    explained_flag: bool | None = None
    if not bad:
        verdict = f"the model fits: {head}; no effect clears the discretization floor"
    elif ok_expl:
        explained_flag = True
        fin = np.sqrt(chi2_final / n)
        names = " + ".join(chosen)
        j0 = first[chosen[0]]
        share = effect_size(base_chi2, chi2_final, n, n_cal, sigma).systematic_share
        verdict = (f"misfit ({head}). Best explanation: {names}: the RMS falls to "
                   f"{fin * sigma:.3g} um = {fin:.2f} noise sd, "
                   + (f"removing {share:.0%} of the systematic misfit" if share is not None
                      else "though the global chi-square is within the noise")
                   + f" (likelihood ratio {j0.refit.lr:.1f} on {j0.refit.dof} dof for "
                   f"{chosen[0]})")
        if len(chosen) > 1:
            verdict += "; found in forward steps: " + " then ".join(chosen)
        suggestions.append("recalibrate with it: solderpyro calibrate ... effects=["
                           + ",".join(chosen) + "]")
    elif ok_tie:
        explained_flag = True
        pre = f"with {' + '.join(chosen)} on, " if chosen else ""
        verdict = (f"misfit ({head}). {pre}the data cannot tell apart: {', '.join(tie)} "
                   f"(their refits differ by less than chi2 {APART_CHI2:.1f}, a likelihood "
                   "ratio of 20; each explains it); do not pick one on these data")
        suggestions.append("measure where the candidates differ (see 'separation' in "
                           "diagnosis.json): the full-field V or more times")
    else:
        explained_flag = False
        if chosen or tie:
            best = np.sqrt(min(j.refit.chi2 for st in steps for j in st if j.refit.ok) / n)
            part = (f"; the candidates' best refit leaves {best:.2f} noise sd, above the "
                    f"{EXPLAINED_SD} that would explain it")
        else:
            part = "; no candidate's refit clears the discretization floor"
        verdict = (f"misfit ({head}): the model is missing something none of the candidates "
                   f"describes{part}")
        for e in ranking:
            e["flagged"] = False
    if chosen and ok_expl and remains(chi2_final, n, n_cal + sum(
            first[c].refit.dof for c in chosen if c in first)):
        verdict += (" (a misfit within the noise-sd bound remains significant on "
                    f"{n} values)")
    untestable = [s.effect for s in scores if saturates(s.dof, n - n_cal)]
    if bad and untestable:  # the verdict covers the candidates these data can test, only
        verdict += ("; not testable on these data (with the calibrated parameters they would "
                    f"fit any {n} values): {', '.join(untestable)}")
    confounded = [e["effect"] for e in ranking if bad and e["identifiable"] < MIN_IDENTIFIABLE]
    if confounded:
        suggestions.append(f"not identifiable from these data (confounded with the calibrated "
                           f"parameters): {', '.join(confounded)}")
    if failed_list:
        suggestions.append("refits that ended above the base fit after a retry (failed, not "
                           "ranked): " + ", ".join(e["effect"] for e in failed_list))
    check = {"chi2": base_chi2, "dof": n - n_cal, "p_value": float(_chi2.sf(base_chi2,
                                                                          max(n - n_cal, 1))),
             "rms_um": float(np.sqrt(base_chi2 / n) * sigma), "noise_um": sigma,
             "ppc_p_value": pc.p_value, "max_abs_z": float(np.abs(pc.z).max()),
             "chi2_linearised": mf.chi2}
    diag = Diagnosis(bad, verdict, ranking, check, groups, suggestions)
    diag.failed = failed_list
    diag.selected = list(chosen) if ok_expl else []  # an unexplained misfit names nothing
    diag.explained = explained_flag
    diag.floor = floor.to_json()
    diag.steps = [[{"effects": list(j.refit.effects), "chi2": j.refit.chi2,
                    "base_chi2": j.refit.base_chi2, "lr": j.refit.lr, "dof": j.refit.dof,
                    "p_value": j.p_value, "ok": j.refit.ok, "flagged": j.flagged,
                    **j.size.to_json()} for j in st] for st in steps]
    return diag


def _where(meas: Any, fp: Fingerprints, sigma: float) -> str:
    """Where the misfit is largest: the denoised residual's peak (field data) or the largest
    standardized residual (point data), in words."""
    if fp.smooth is not None:
        m = np.asarray(fp.smooth.mean)
        k = int(np.argmax(np.abs(m)))
        return (f"it is largest at t = {meas.time_s[k]:g} s, x = {meas.x_mm[k]:.1f} mm, "
                f"y = {meas.y_mm[k]:.1f} mm ({m[k]:+.3g} um denoised, "
                f"{fp.smooth.share_above_band:.0%} of the values outside the noise band; see "
                "diagnosis_residuals.png)")
    r = np.asarray(fp.residual)
    k = int(np.argmax(np.abs(r)))
    return (f"it is largest at point {meas.point[k]}, t = {meas.time_s[k]:g} s "
            f"({r[k] / sigma:+.1f} noise sd; see diagnosis_residuals.png)")


def _figures(d: Path, diag: Diagnosis, meas: Any, pc: PredictiveCheck, fp: Fingerprints,
             sigma: float, dr: dict[str, np.ndarray], setup: Any) -> tuple[str, str, str]:
    """The residual, fingerprint and ranking figures; returns their file names.

    Full-field data: maps (raw and denoised residual; per top candidate its fingerprint and
    the denoised residual after adding it). Point data: residuals against time with the
    predictive band, and each top candidate's signature, the cycle's temperature beside."""
    from solderpyro.diagnose import plots

    top = [r["effect"] for r in diag.ranking[:TOP]]
    corr = {r["effect"]: r["fingerprint_correlation"] for r in diag.ranking}
    cyc, t_end = setup.problem.cycle, float(setup.problem.cycle.end)
    if fp.smooth is not None:
        sm = fp.smooth
        f1 = plots.plot_maps(meas, [("residual", fp.residual, None),
                                    ("denoised residual", sm.mean, sm.z)], sigma,
                             d / "diagnosis_residuals.png",
                             "Where the model misses the data: residual (data - FE at its best "
                             "fit) and its GP-denoised part (dotted: inside its 95 % band, "
                             "noise could have made it)")
        rows: list[Any] = [("denoised residual", sm.mean, sm.z)]
        for e in top:
            rows.append((f"{e} fingerprint (r = {corr[e]:.2f})", fp.signature[e], None))
            if e in fp.smooth_after:
                rows.append((f"denoised residual after {e}", fp.smooth_after[e].mean,
                             fp.smooth_after[e].z))
        f2 = plots.plot_maps(meas, rows, sigma, d / "diagnosis_fingerprints.png",
                             "Which effect's fingerprint matches the residual (r: shape "
                             "correlation with the denoised residual)")
    else:
        f1 = plots.plot_point_residuals(meas, dr["observed"], fp.residual, sigma,
                                        d / "diagnosis_residuals.png", cyc, t_end)
        f2 = plots.plot_point_fingerprints(
            meas, fp.residual, [(e, fp.signature[e], fp.after[e], corr[e]) for e in top],
            sigma, d / "diagnosis_fingerprints.png", cyc, t_end)
    del pc
    by = {s: corr[s] for s in corr}
    f3 = plots.plot_ranking([SimpleNamespace(effect=r["effect"], evidence=r["evidence"])
                             for r in diag.ranking], by, d / "diagnosis_ranking.png")
    return f1, f2, f3


def _cost_lines(timing: dict[str, dict[str, float | int]]) -> list[str]:
    """The ``timing`` table of :class:`Diagnosis` as markdown lines."""
    lines = ["## Cost per stage", "",
             "| stage | seconds | FE runs computed | FE runs reused |", "|---|---|---|---|"]
    for k, r in timing.items():
        lab = "**total**" if k == "total" else STAGES.get(k, k)
        lines.append(f"| {lab} | {float(r['seconds']):.2f} | {int(r['fe_runs'])} | "
                     f"{int(r['fe_reused'])} |")
    return lines + ["", "(reused: read back from the run store, or shared by several rows of "
                    "one batch)"]


def _write(d: Path, diag: Diagnosis, mf: Misfit, pc: PredictiveCheck, sigma: float,
           figs: tuple[str, str, str]) -> None:
    f1, f2, f3 = figs
    (d / "diagnosis.json").write_text(json.dumps(diag.to_json(), indent=2) + "\n")
    lines = ["# solderpyro diagnosis", "", f"**Verdict:** {diag.verdict}.", "",
             f"- at the FE's best fit ({(diag.base or {}).get('start', 'the posterior draw')}"
             f"): chi2 {diag.check['chi2']:.2f} on {diag.check['dof']} dof (p = "
             f"{diag.check['p_value']:.3g}); RMS residual {diag.check['rms_um']:.4g} um, noise "
             f"{sigma:.4g} um",
             f"- discretization floor: {(diag.floor or {}).get('source', 'none')}",
             f"- posterior predictive p-value {pc.p_value:.3g}; largest |z| "
             f"{np.abs(pc.z).max():.2f}", "",
             "## Candidate effects (best first)", "",
             "Refitted candidates by their likelihood ratio through the FE, then those the "
             "screen (score test) left out; failed refits last, not ranked.", "",
             "| effect | FE refit | LR (or screen) | dof | evidence (-log10 p) | RMS after "
             "(um / noise sd) | systematic misfit removed | above the floor | identifiable | "
             "fingerprint r | flagged |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in diag.ranking + diag.failed:
        lines.append(f"| {r['effect']} | {r['refit']} | {r['statistic']:.1f} | {r['dof']} | "
                     f"{r['evidence']:.2f} | {r['rms_after_um']:.3g} / "
                     f"{r['rms_after_sd']:.2f} | "
                     f"{share_text(r['systematic_share'])} | "
                     f"{'yes' if r['clears_floor'] else 'no'} | {r['identifiable']:.2f} | "
                     f"{r.get('fingerprint_correlation', 0):.2f} | "
                     f"{'yes' if r['flagged'] else ''} |")
    lines += ["", "Fingerprint r: shape correlation (Pearson, every value) of what the effect "
              "changes with the " + ("GP-denoised residual" if diag.denoise else "residual")
              + "; the change is exact (the FE refitted with the effect on, minus refitted "
              "without) where the refits ran, the baseline's refit is about as good as the "
              "linearised one and the effect's refit no worse than the baseline's, else "
              "linearised at off after the calibrated parameters took their share "
              "(`fingerprint` in diagnosis.json says which)."]
    if diag.denoise:
        dn = diag.denoise
        lines.append(f"Denoised residual: RMS {dn['rms_um']:.3g} um against noise "
                     f"{dn['noise_um']:.3g} um; {dn['share_above_band']:.0%} of the values "
                     f"outside its 95 % band (length scales {dn['lengthscale_mm'][0]:.3g} x "
                     f"{dn['lengthscale_mm'][1]:.3g} mm).")
    if diag.indistinguishable:
        lines += ["", "Cannot be told apart from these data: "
                  + "; ".join(", ".join(g) for g in diag.indistinguishable)]
    if diag.cannot_rule_out:
        lines += ["", "## What the data cannot rule out", "",
                  "The model fits, yet these effects fit as well at the magnitudes named "
                  "(the constants refitted, linearised): the intervals assume they are "
                  "absent.", ""] + [f"- {r['text']}." for r in diag.cannot_rule_out]
    lines += ["", "## Suggestions", ""] + ([f"- {s}" for s in diag.suggestions] or ["- none"])
    if diag.timing:
        lines += [""] + _cost_lines(diag.timing)
    lines += ["", "## Figures", "", f"![where the model misses the data]({f1})", "",
              f"![fingerprints of the best candidates beside the residual]({f2})", "",
              f"![evidence per candidate]({f3})", ""]
    (d / "diagnosis.md").write_text("\n".join(lines) + "\n")
    from solderpyro.report import write_html

    write_html(lines, d / "diagnosis.html", "solderpyro diagnosis")
