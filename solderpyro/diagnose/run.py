"""``solderpyro diagnose RUN_DIR``: does the calibrated model fit, and which effect is missing?

Data flow: the run directory of ``solderpyro calibrate`` (its record, ``data.csv``,
``draws.npz``) -> posterior predictive checks of the surrogate predictive (with code
uncertainty) -> the FE at a few posterior draws, with every candidate effect switched on at
"off", and finite-difference Jacobians w.r.t. the calibrated parameters and each effect's
parameters -> misfit chi-square after a linearised refit and a score test per effect
(:mod:`solderpyro.diagnose.stats`) -> ranking, confusions, verdict -> ``diagnosis.json``,
``diagnosis.md`` and figures.

This module only orders the stages; each is a module of its own: :mod:`~.load` (the run
directory), :mod:`~.refits` (the base fit and the candidates' refits), :mod:`~.screen` (FE
Jacobians, score tests, ladder), :mod:`~.verdict`, :mod:`~.ruleout`, :mod:`~.separation`,
:mod:`~.fingerprint`, :mod:`~.write`; :mod:`~.costs` keeps the stage clock.

Every FE run goes through the calibration's run store
(:class:`~solderpyro.compute.runstore.RunStore`, the run record's ``store``), registered with the
solver's problem, times, field flag, dtype and the effects switched on: each run is kept as soon as
its batch finishes, a rerun of the diagnosis reads every run back, and rows that several stages
share (the Jacobians' base and forward rows, the refits' first steps, a refit that did not move) are
solved once. Each stage's seconds and FE runs (computed, reused) are logged and written to
``diagnosis.json`` (``"timing"``) and ``diagnosis.md``.

The FE is exact (no code uncertainty), so the misfit and score statistics are measured against
the measurement noise alone: the noise the data file states (``sigma_um``) when there is one,
otherwise the posterior median of sigma.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from solderpyro.config.compose import build, coarsened, compose
from solderpyro.diagnose.costs import Costs
from solderpyro.diagnose.decide import (
    REFIT_TOL,
    Judged,
    load_floor,
    needs_global,
    remains,
    settled,
    to_refit,
)
from solderpyro.diagnose.diagnosis import Diagnosis
from solderpyro.diagnose.faces import Face, freeing, on_faces
from solderpyro.diagnose.fingerprint import Fingerprints, fingerprints
from solderpyro.diagnose.load import (
    candidate_effects,
    load_run,
    noise_sd,
    reported_intervals,
    run_store,
)
from solderpyro.diagnose.refits import (
    MAX_REFITS,
    base_fit,
    base_starts,
    first_fits,
    first_refits,
    forward,
    global_refits,
    layout,
    linearised_steps,
    pick_draws,
)
from solderpyro.diagnose.ruleout import Constants, admitting, cannot_rule_out
from solderpyro.diagnose.screen import (
    MIN_IDENTIFIABLE,
    apply_ladder,
    at_observations,
    fe_jacobians,
    group,
    score_tests,
)
from solderpyro.diagnose.separation import refit_predictions, separation
from solderpyro.diagnose.stats import Score, predictive_check
from solderpyro.diagnose.verdict import (
    VerdictInputs,
    add_cannot_rule_out,
    record_fits,
    verdict,
    where,
)
from solderpyro.diagnose.write import TOP, figures, write
from solderpyro.specimen import SpecimenModels

log = logging.getLogger("solderpyro")


def diagnose(run_dir: str | Path, candidates: tuple[str, ...] | None = None, n_draws: int = 3,
             seed: int = 0, progress: bool = True, refit: bool = True,
             batch_size: int = 64) -> Diagnosis:
    """Diagnose the calibration in ``run_dir``; writes diagnosis.json, diagnosis.md, figures.

    Every FE run goes through the calibration's run store
    (:func:`~solderpyro.diagnose.load.run_store`): a second diagnosis of the same run directory
    reads them all back. Each stage's cost (seconds, FE runs computed and reused) is logged and
    kept in :attr:`~solderpyro.diagnose.diagnosis.Diagnosis.timing`.

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
        :class:`~solderpyro.diagnose.diagnosis.Diagnosis`.
    """
    cost = Costs()
    d = Path(run_dir)
    with cost.stage("load"):
        run = load_run(d)
        info, setup, meas, dr = run["info"], run["setup"], run["meas"], run["draws"]
        run_effects = tuple(info.effects)
        candidates = candidate_effects(run_effects, candidates)
        store = run_store(info, d)
        cost.fe = fe = SpecimenModels(setup, store, batch_size)
        log.info("diagnose: FE runs kept in the run store %s", store.root)
    with cost.stage("predictive_check"):
        y = np.asarray(meas.value_um, float)
        sigma = noise_sd(info, dr["sigma"])
        pc = predictive_check(y, dr["process"], dr["sigma_pred"], seed=seed)
    lay = layout(setup, run_effects, candidates, meas)
    floor = load_floor("field" if lay.field else "points")
    # other posterior draws only where the FE check accepted the posterior: never a draw the
    # FE rejected
    fe_ok = info.checks.fe_ok
    idx = pick_draws(dr["theta"], n_draws if fe_ok else 1, seed)
    thetas = dr["theta"][idx].copy()
    base: dict[str, Any] | None = None
    if refit:
        with cost.stage("best_fit"):
            base = base_fit(lay, fe, meas, sigma,
                            base_starts(setup, info, dr["theta"], idx, fe_ok))
            thetas[0] = base["x"][:lay.n_cal]
            _log_base(base)
    with cost.stage("fe_jacobians"):
        fej = fe_jacobians(lay, thetas, fe, progress=progress)
    with cost.stage("score_tests"):
        V, J, lad = at_observations(fej, meas)
        mf, scores, per_draw = score_tests(y, V, J, fej["cols"], sigma)
    with cost.stage("ladder"):
        apply_ladder(mf, scores, y, J[0], fej["cols"], sigma, lad)
    base_chi2 = base["chi2"] if base is not None else mf.chi2
    n, n_cand = len(y), len(candidates)
    fits = None
    steps: list[list[Judged]] = []
    chosen: tuple[str, ...] = ()
    tie: list[str] = []
    faces: list[Face] = []
    freed: list[tuple[str, tuple[str, ...]]] = []
    screened = to_refit(scores, n_cand, remains(base_chi2, n, lay.n_cal), MAX_REFITS,
                        MIN_IDENTIFIABLE, n - lay.n_cal)
    if not refit:  # the linearised statistics stand in for the refits
        steps, chosen, tie = linearised_steps(scores, mf.chi2, n, lay.n_cal, sigma, floor,
                                              n_cand)
    elif base is not None:
        faces = on_faces(base["x"][:setup.space.dim], setup.space)
        first = []
        if faces:
            # the global refits come next in any case, and start every candidate from the
            # base point too: no local refits before them
            log.info("diagnose: the base fit presses %s against the box's faces: every "
                     "candidate is refitted from several starts", ", ".join(
                         f.name for f in faces))
        else:
            with cost.stage("profile_refits"):
                first = (first_refits(lay, fe, meas, sigma, base, scores, screened)
                         if screened else [])
                steps, chosen, tie = forward(lay, fe, meas, sigma, first, floor)
        if needs_global(bool(faces), base["chi2"], n, lay.n_cal,
                        settled(steps, chosen, tie, n, sigma, floor)):
            with cost.stage("global_refits"):
                scout = SpecimenModels(build(compose(coarsened(list(info.overrides)))),
                                       store, batch_size)
                cost.fe_also(scout)
                base, first = global_refits(lay, fe, meas, sigma, base, scores, first, scout)
                base_chi2 = base["chi2"]
                steps, chosen, tie = forward(lay, fe, meas, sigma, first, floor, scout)
            freed = freeing(first, base_chi2, setup.space, faces) if faces else []
        fits = first_fits(base, first)
    with cost.stage("verdict"):
        diag = verdict(VerdictInputs(mf, pc, scores, per_draw, sigma, steps, chosen, tie,
                                     base_chi2, lay.n_cal, floor, tuple(faces),
                                     tuple(freed)))
        record_fits(diag, steps, lay, base, fe_ok, fej["cols"].names)
    intervals = None
    if not diag.misfit and not diag.selected and lad:
        with cost.stage("cannot_rule_out"):
            intervals = reported_intervals(d)
            if intervals is not None:
                consts = Constants(list(fej["cols"].names[:lay.n_cal]), lay.lo[:lay.n_cal],
                                   lay.hi[:lay.n_cal], dr["theta"], intervals)
                found = cannot_rule_out(
                    y, V[0], J[0][:, group(fej["cols"], "theta")], sigma, lad, consts,
                    {e.name: float(e.off[k]) for e in lay.fx_all.effects
                     if (k := e.size_index) is not None})
                add_cannot_rule_out(diag, found, lay.fx_all)
                diag.admitting = {nm: list(iv) for nm, iv in admitting(consts, found).items()}
    if diag.indistinguishable and fits is not None:
        with cost.stage("separation"):
            diag.separation = separation(setup, run_effects, candidates, fits,
                                         diag.indistinguishable[0], meas, sigma, fe=fe)
            diag.suggestions.insert(0, diag.separation["advice"])
    with cost.stage("fingerprints"):
        preds = None if fits is None else {
            m: v for m, v in refit_predictions(setup, run_effects, candidates, fits, meas,
                                               fe).items()
            if m == "baseline" or fits[m]["chi2"] <= base_chi2 + REFIT_TOL}
        fp = _fingerprints(diag, meas, mf.residual, scores, sigma, preds, lay.field)
    with cost.stage("write"):
        figs = figures(d, diag, meas, fp, sigma, dr, setup)
    diag.timing = cost.table()
    tot = diag.timing["total"]
    log.info("diagnose: total %.1f s, %d FE runs computed, %d reused (store %s)",
             tot["seconds"], tot["fe_runs"], tot["fe_reused"], store.root)
    write(d, diag, pc, sigma, figs, intervals)
    from solderpyro.reporting.index import write_index

    write_index(d)
    return diag


def _log_base(base: dict[str, Any]) -> None:
    log.info("diagnose: FE best fit (start: %s%s), chi2 %s", base["start"],
             "" if not base["scouts"] else "; scouts " + ", ".join(
                 f"{k} {v:.1f}" for k, v in base["scouts"].items()),
             " -> ".join(f"{c:.1f}" for c in base["history"]))


def _fingerprints(diag: Diagnosis, meas: Any, residual: np.ndarray, scores: list[Score],
                  sigma: float, preds: dict[str, np.ndarray] | None, field: bool
                  ) -> Fingerprints:
    """The top candidates' fingerprints against the residual: exact from the refits'
    predictions ``preds`` where a candidate's refit did not fail (its shape would mislead),
    else linearised; recorded in ``diag``'s ranking, denoising and (unexplained) verdict."""
    top = tuple(r["effect"] for r in diag.ranking[:TOP])
    fp = fingerprints(meas, residual, scores, sigma, preds, field, top)
    for r in diag.ranking:
        r["fingerprint_correlation"] = round(fp.correlation[r["effect"]], 4)
        r["fingerprint"] = fp.source[r["effect"]]
    diag.denoise = fp.smooth.summary() if fp.smooth is not None else None
    if diag.explained is False:
        diag.verdict += "; " + where(meas, fp, sigma)
    return fp
