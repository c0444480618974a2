"""The specimen calibration end to end, as a short sequence of stages.

    problem (:mod:`.problem`) -> adaptive design: surrogate + posterior per round, FE runs
    at the posterior draws where the log-likelihood's code variance falls most (chosen greedily
    in closed form) until the FE confirms (:mod:`.adaptive`) -> FE check at posterior draws
    (:mod:`.fe_check`) -> outputs (:mod:`.outputs`) -> the FE-exact posterior and profile
    intervals when the design ran out of budget with the FE still disagreeing
    (:mod:`.fe_exact`) -> outputs again.

Data flow is one-directional: measurements -> observed model outputs -> FE runs (run store) ->
surrogate -> posterior per round -> discretization correction (corrected data, a new value) ->
final posterior, FE check and report on the corrected data. Every setting is in
:class:`~.settings.CalibrationSettings`.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from solderpyro.calibration import predict_observation_model
from solderpyro.calibration.intervals import (
    MODEL_FORM,
    PROFILE,
    likelihood_hull,
    profile_hull,
    with_intervals,
)
from solderpyro.calibration.mcmc import WarmStart, format_summary, thin_index, write_summary
from solderpyro.calibration.predictive import Bands
from solderpyro.config.compose import Setup
from solderpyro.config.rundir import (
    AlloyRecord,
    Checks,
    DesignSummary,
    RunDir,
    RunInfo,
    SurrogateRecord,
)
from solderpyro.config.settings import CalibrationSettings
from solderpyro.design.loop import StageClock, spread_indices
from solderpyro.effects import EffectSet
from solderpyro.io.measurements import Measurements
from solderpyro.params import Box
from solderpyro.pipeline.adaptive import (
    adaptive_design,
    correct_discretization,
    final_design_posterior,
    save_design,
)
from solderpyro.pipeline.fe_check import (
    FE_CHECK_DRAWS,
    discretization_check,
    fe_check,
    misfit_remains,
    misses,
    ranked,
)
from solderpyro.pipeline.fe_exact import (
    SUMMARY,
    WEAK_SHARE,
    BestFitPosterior,
    ExactRun,
    exact_rows,
    fe_exact,
    identifiability,
)
from solderpyro.pipeline.model_form import model_form_stage
from solderpyro.pipeline.outputs import (
    SpecimenCalibration,
    log_likelihoods,
    observation_coords,
    posterior_draws,
    save_run,
)
from solderpyro.pipeline.problem import CalibrationProblem

log = logging.getLogger("solderpyro")
#: chains that agree to this R-hat are taken as converged (the report warns above it)
RHAT_OK = 1.01
#: posterior draws (the same ones of every chain) in the predictive, draws.npz and the
#: posterior_predictive / log_likelihood groups of posterior.nc
PREDICTIVE_DRAWS = 1000
#: FE runs at draws of the best fit's Laplace spread that make the predictive of a model that
#: misfits (its summary is the FE's own best fit: :func:`~.fe_exact.best_fit_posterior`)
BEST_FIT_BAND_RUNS = 48


def unprofilable(n_params: int, n_values: int) -> str | None:
    """Why profile-likelihood intervals of ``n_params`` parameters cannot come from
    ``n_values`` data values, or None when they can.

    Each profile refits the other ``n_params - 1`` parameters at fixed values of one: when they
    are at least as many as the values they fit the data at every fixed value, the profile is
    flat and its interval is the box, found after thousands of FE runs (point data with the
    Moire offsets, 12 parameters on 8 values: more than 40 minutes).
    """
    if n_params - 1 < n_values:
        return None
    return (f"profile intervals not computed: {n_params} parameters on {n_values} values "
            "cannot be profiled (the other parameters fit the data at every value of each: "
            "flat profiles); measure more values or calibrate fewer parameters")


#: the most calibrated parameters whose profile intervals ``calibration.exact.profile_ci=auto``
#: computes (:data:`PROFILE_RUNS` FE runs each): past it the profiles take longer than the rest
#: of the calibration many times over (16 parameters, three effects with the Moire offsets, on
#: the forms benchmark: about 7,200 FE runs, an hour on 2 cores)
PROFILE_AUTO_MAX = 8
#: FE runs a parameter's profile takes, about (docs/calibration.md)
PROFILE_RUNS = 450


def raise_budget(budget: int | None) -> str:
    """The trust lines' advice to allow the design more FE runs, with the ``budget`` it ran
    out at where known."""
    return "raise --budget" + ("" if budget is None else f" (it was {budget} FE runs)")


def unreliable_trust(costly: str, profile_ci: str, budget: int | None = None) -> str:
    """The trust line where the design's budget ran out and the FE-exact posterior's weights
    are not reliable: what to do, and what the profile intervals are (``costly``: why they
    are not computed, :func:`too_costly_to_profile`, or ""; ``profile_ci``: the setting;
    ``budget``: the FE runs the design was allowed, said with the advice where known)."""
    if costly:
        profiles = costly
    elif profile_ci == "off":
        profiles = "the profile intervals are not computed (calibration.exact.profile_ci=off)"
    else:
        profiles = ("the 95 % intervals are widened to hold the FE's own profile intervals "
                    "(profile_ci.csv)")
    return ("neither posterior: the design's budget ran out with the FE disagreeing, and the "
            f"FE-exact posterior's weights are not reliable; {raise_budget(budget)}; "
            + profiles)


def too_costly_to_profile(n_params: int, model_form: bool = False,
                          best_fit: bool = False) -> str:
    """Why ``profile_ci=auto`` computes no profile intervals of ``n_params`` parameters, or ""
    where it does: more than :data:`PROFILE_AUTO_MAX` of them, or a misfit remains and the
    reported intervals are widened for it (``model_form``): the profiles of a model that
    misfits are narrower than those, and on the forms benchmark's two-effect recalibration
    (8 parameters, FE-exact ESS 1) they cost about 3,600 FE runs and came out as points; or
    the FE's own best fit with its Laplace spread is reported (``best_fit``,
    :func:`unconfirmed_stage`), whose profiles would cost as many."""
    if best_fit:
        return ("the profile intervals were not computed: the FE's own best fit with its "
                "Laplace spread is reported (calibration.exact.profile_ci=on or --profile-ci "
                "computes them)")
    if model_form:
        return ("the profile intervals were not computed: a misfit remains and the reported "
                "intervals are widened for it (calibration.exact.profile_ci=on or "
                "--profile-ci computes them)")
    if n_params <= PROFILE_AUTO_MAX:
        return ""
    return (f"the profile intervals were not computed: {n_params} parameters would take about "
            f"{PROFILE_RUNS * n_params:,} FE runs (calibration.exact.profile_ci=on or "
            "--profile-ci computes them)")


@dataclass
class Reported:
    """What a calibration reports at one stage: its summary rows, predictive, problems and
    trust line.

    Attributes:
        rows: summary rows (``SUMMARY`` keys; physical units, sigma in um).
        bands: the predictive (:class:`~solderpyro.calibration.predictive.Bands`, um).
        problems: the report's warnings.
        trust: the report's line on which posterior to trust.
    """

    rows: list[dict]
    bands: Any
    problems: list[str]
    trust: str


@dataclass
class FeChecked:
    """The FE at a few posterior draws (:func:`~.fe_check.fe_check`).

    Attributes:
        noise_sd: um, the known noise sd or the posterior's median sigma.
        draws: ``(N, dim)`` the surrogate posterior's draws, physical units.
        pick: ``(FE_CHECK_DRAWS,)`` indices into ``draws`` of the checked ones.
        V: ``(len(pick), n)`` um, the FE's observed outputs at them.
        result: :func:`~.fe_check.fe_check`'s record (``ok``, ``best``, ``rms_um``, ...).
    """

    noise_sd: float
    draws: np.ndarray
    pick: np.ndarray
    V: np.ndarray
    result: dict[str, Any]


@dataclass
class RunOutputs:
    """Everything a calibration's outputs (summary.csv, draws.npz, run.json, the report) are
    written from, apart from what each stage reports (:class:`Reported`).

    Attributes:
        setup, meas, out, settings, record: the calibration's inputs
            (:func:`calibrate_specimen`).
        cp: the problem, on the data the final posterior used.
        loop: the adaptive design's final state (:func:`~.adaptive.final_design_posterior`).
        loo: the surrogate's leave-one-out check.
        y_liu: ``(n,)`` um, the literature parameters' outputs.
        checked: the FE check at posterior draws.
        disc: the discretization check's record.
        fit: the FE's own best fit of a model that misfits, else None.
        clock: the stages' seconds.
    """

    setup: Setup
    meas: Measurements
    out: Path
    settings: CalibrationSettings
    record: dict[str, Any] | None
    cp: CalibrationProblem
    loop: Any
    loo: Any
    y_liu: torch.Tensor
    checked: FeChecked
    disc: dict[str, Any]
    fit: BestFitPosterior | None
    clock: StageClock

    def run_info(self, trust: str, kind: str, ex_info: dict[str, Any] | None) -> RunInfo:
        """The run's record with the report's ``trust`` line, the ``kind`` of posterior in
        summary.csv and the FE-exact step's record ``ex_info`` (None before it)."""
        s, cp, loop = self.settings, self.cp, self.loop
        space, sg = cp.space, s.surrogate
        asked = dict(self.record or {})
        alloy = self.setup.alloy
        return RunInfo(
            list(space.names), list(space.lower), list(space.upper), list(cp.effects),
            cp.priors.sigma_known, [float(t) for t in self.meas.times()],
            list(self.meas.points()),
            overrides=list(asked.pop("overrides", [])), data=asked.pop("data", None),
            store=s.store, seed=s.seed, settings=s.as_dict(),
            surrogate=SurrogateRecord(sg.kernel, sg.ard, sg.mean, loop.gp.output, sg.inputs,
                                      sg.inputs_T_C, sg.inputs_rate),
            n_runs=int(len(loop.X)), design=DesignSummary(loop.as_dict()),
            checks=Checks(self.checked.result, self.disc, float(self.loo.rmse_rel),
                          float(self.loo.coverage95)),
            timing_s=self.clock.seconds, trust=trust, posterior=kind, exact=ex_info or None,
            alloy=None if alloy is None else AlloyRecord(alloy.name, alloy.source), extra=asked)

    def notes(self, trust: str, exact: bool, ex_info: dict[str, Any] | None) -> list[str]:
        """The report's notes: ``trust``, the design, the FE and discretization checks, and
        the FE-exact posterior's or best fit's line (``exact``: summary.csv is the FE-exact
        posterior's)."""
        s, loop, chk, fit = self.settings, self.loop, self.checked.result, self.fit
        last = loop.rounds[-1]
        notes = [f"**trust**: {trust}",
                 f"adaptive design: {len(loop.X)} FE runs in {len(loop.rounds)} rounds "
                 f"({loop.reason}): {loop.message} (design.png, design.csv); "
                 f"{acquisition_text(s.design)}",
                 f"last round: code chi2 {last.code_chi2:.3g}, max |FE - surrogate| chi2 "
                 f"{last.fe_gap:.3g} (varying by {last.fe_spread:.2g} across the checked "
                 f"draws, tolerance {s.design.fe_spread:g}), tolerance {last.tolerance:.3g}",
                 f"FE check: the FE at {chk['draws']} posterior draws (one batched solve), "
                 f"best RMS residual {chk['rms_um']:.3g} um = {chk['rms_over_sigma']:.2f} "
                 f"noise sd (chi2 {chk['chi2']:.0f} on {chk['n']} values)",
                 self.disc["message"]]
        if exact and ex_info:
            notes.insert(1, f"**posterior: FE-exact** (adaptive importance sampling with the FE "
                            f"in the likelihood, {ex_info['fe_runs']} FE runs, ESS "
                            f"{ex_info['ess']:.0f}, Pareto k-hat {ex_info['khat']:.2f}); the "
                            f"surrogate's is in summary_surrogate.csv")
        if fit is not None:
            notes.insert(1, f"**summary: the FE's own best fit** (chi2 {fit.chi2:.0f} on "
                            f"{self.cp.y.numel()} values), intervals from its Laplace covariance "
                            f"widened by sqrt(chi2 / (n - dim)) = {fit.scale:.2f}; the "
                            "surrogate's posterior is in summary_surrogate.csv")
        ident = (ex_info or {}).get("identifiability") or {}
        if exact and ident.get("weak"):
            notes.append("weakly identified by these data (95 % interval over >= "
                         f"{WEAK_SHARE:.0%} of the prior box): "
                         + ", ".join(v["parameter"] for v in ident["weak"])
                         + "; see 'Identifiability' below for the measurement that would "
                         "narrow them")
        return notes

    def write(self, rep: Reported, ex: Any = None, ex_info: dict[str, Any] | None = None,
              ex_rows: list[dict] | None = None) -> None:
        """summary.csv, draws.npz, the run's record and the report of ``rep`` (the FE-exact
        posterior ``ex``'s where it is reliable, with its record ``ex_info`` and summary rows
        ``ex_rows``); written before the FE-exact step and again after it."""
        from solderpyro.reporting import report

        cp, fit, out = self.cp, self.fit, self.out
        post = self.loop.draws.posterior[0]
        saved = (ex.theta, ex.sigma) if ex is not None and ex.reliable else None
        kind = "fe-exact" if saved is not None else "surrogate"
        if fit is not None:
            saved, kind = (fit.theta, fit.sigma), "fe-best-fit"
        trust = rep.trust
        faces = pressed_faces(rep.rows, self.setup.space)
        if faces:  # first, in the trust line and the notes
            trust = (f"{', '.join(faces)} press against their prior box: likely a missing "
                     f"effect the constants compensate (run solderpyro diagnose); {trust}")
        notes = self.notes(trust, kind == "fe-exact", ex_info)
        if faces:
            notes.insert(0, f"**constants on the box's faces**: {pressed_text(faces)}")
        write_summary(rep.rows, out / "summary.csv", SUMMARY)
        run = save_run(out, self.meas, self.run_info(trust, kind, ex_info),
                       posterior_draws(post, rep.bands, cp.space.names, cp.y, self.y_liu, saved),
                       post.warm)
        t = cp.tally  # every FE run of the calibration so far (Liu, design, checks, exact)
        report.write(report.CalibrationReport(
            run, self.meas, rep.rows, post, self.loo, rep.bands, self.y_liu.numpy(),
            report.FeRunCounts(t.n_ok, t.n_failed, t.n_reused, t.n_computed), rep.problems,
            notes,
            None if ex is None or not ex_rows
            else report.ExactReport(ex, ex_rows, self.checked.draws)))


#: this many material constants pressed against faces make a finding: one alone can be a
#: physical limit (a copper that yields at the lowest stress the box allows)
PRESSED_MIN = 2
#: a constant is pressed against a face when its 95 % interval reaches within this share of
#: the box of the face (unit scale) ...
PRESSED_NEAR = 0.02
#: ... and spans at most this share of the box: a posterior spread over most of the box
#: touches a face without pressing against it
PRESSED_WIDTH = 0.25


def acquisition_text(design: Any) -> str:
    """What chose a run's acquired FE runs, as its report says it (``design``: the
    :class:`~solderpyro.design.loop.LoopSettings` that ran)."""
    what = ("the code variance of the log-likelihood" if design.criterion == "loglik" else
            "the surrogate's integrated variance at the observed outputs")
    how = ("greedily in closed form among the posterior draws" if design.optimizer == "draws"
           else "by BoTorch's optimize_acqf over the box")
    return (f"each round's runs went where {what} falls most, chosen {how} "
            f"(calibration.design.criterion={design.criterion}, "
            f"optimizer={design.optimizer})")


def pressed_faces(rows: list[dict], box: Box) -> list[str]:
    """``"s0 (upper face)"`` for each material constant of ``box`` whose reported 95 % interval
    (``lo95``, ``hi95``) reaches within :data:`PRESSED_NEAR` of a face and spans at most
    :data:`PRESSED_WIDTH` of the box, both on its unit scale (log where flagged), where at
    least :data:`PRESSED_MIN` of them do; else empty.

    Measured on every benchmark run on disk: the base calibrations of data with E(T), a
    thermal lag or residual stress press 3 constants (intervals over 1-21 % of their boxes,
    ending within 0.3 % of a face), whether their intervals start at the face or, from an
    FE-exact posterior, just short of it; the clean data and every recalibration with the
    right effect none; the short demo's weakly identified posterior touches faces with wide
    intervals."""
    faces = []
    for r in rows:
        if r["parameter"] not in box.names:
            continue
        i = box.names.index(r["parameter"])
        ends = np.tile(np.asarray(box.lower, float), (2, 1))
        ends[:, i] = float(r["lo95"]), float(r["hi95"])
        lo, hi = (float(v) for v in box.to_unit(torch.as_tensor(ends, dtype=torch.float64))[:, i])
        if hi - lo <= PRESSED_WIDTH and min(lo, 1.0 - hi) <= PRESSED_NEAR:
            faces.append(f"{r['parameter']} ({'lower' if lo <= 1.0 - hi else 'upper'} face)")
    return faces if len(faces) >= PRESSED_MIN else []


def pressed_text(faces: list[str]) -> str:
    """The report's lead on the constants :func:`pressed_faces` found."""
    return (f"{', '.join(faces)} press against their prior box. Constants that pile against "
            "the box's faces are what a model that lacks a physical effect looks like when "
            "its constants absorb what they can of it, even where the fit is at the noise "
            "level; the constants are then likely wrong. Run solderpyro diagnose on this run: "
            "it refits every candidate effect from several starts across the box")


def pressed_constants(rows: list[dict], box: Box) -> str:
    """:func:`pressed_text` of :func:`pressed_faces`, or "" where no constants are pressed."""
    faces = pressed_faces(rows, box)
    return pressed_text(faces) if faces else ""


def calibrate_specimen(setup: Setup, meas: Measurements, out: str | Path,
                       settings: CalibrationSettings | None = None,
                       record: dict[str, Any] | None = None,
                       warm: WarmStart | None = None) -> SpecimenCalibration:
    """Calibrate ``setup.space`` (default s0, QR, xi, m; plus the parameters of switched-on
    effects) against ``meas``.

    Args:
        setup: the typed problem, parameter box and defaults (:mod:`solderpyro.config.compose`).
        meas: measurements; times and points must be model outputs (A, B, grid labels).
        out: the run directory (created).
        settings: every setting (:class:`CalibrationSettings`; default: the adaptive design
            with its default budget).
        record: how the run was asked for (e.g. ``{"overrides": [...], "data": path}``), kept in
            the run's record (:class:`~solderpyro.config.rundir.RunInfo`) so that ``solderpyro
            diagnose`` can rebuild the model.
        warm: a related run's sampler state (``--warm-from``) for the first posterior.

    Returns:
        :class:`SpecimenCalibration`; writes summary.csv, posterior.nc, design.csv/.png,
        figures and report.md/.html into ``out``.
    """
    s = settings or CalibrationSettings()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    clock = StageClock(log_each=True)
    cp, loop, y_liu = design_stage(setup, meas, s, out, warm, clock)
    post, inp = loop.draws.posterior
    loo = loop.gp.loo()
    problems = design_problems(loop, loo)
    checked = fe_check_stage(cp, post)
    clock("fe_check")
    if not checked.result["ok"]:
        problems = [*problems, fe_misfit_message(checked.result)]
    bands, pick, loglik = save_posterior(cp, post, inp, s.seed, out)
    rows = likelihood_hull(summary_rows(post, checked.draws, setup, cp.space),
                           checked.draws[pick], loglik, cp.space)
    # a model whose own FE best fit misfits (loop.reason "misfit") gets no FE-exact posterior
    full_exact = s.exact.mode == "on" or (
        s.exact.mode == "auto" and loop.reason == "budget" and not loop.rounds[-1].fe_ok)
    fit = None
    if loop.reason == "misfit":
        fit, rep = misfit_stage(cp, s, out, loop, Reported(rows, bands, problems, ""),
                                checked.noise_sd)
        if fit is not None:
            clock("best_fit")
    else:
        rep = Reported(rows, bands, problems, surrogate_trust(loop.converged, full_exact))
        left = remaining_misfit(checked.result.get("rms_over_sigma"), len(cp.y), cp.space.dim)
        if left:  # at the best checked posterior draw, the FE check within its bound
            best = checked.draws[checked.pick][ranked(checked.V, cp.y.numpy())[0]]
            rows, why = model_form_stage(cp, rows, best, out, s.seed)
            rep = Reported(rows, bands, [*problems, left],
                           rep.trust + f", with care: {left}; {why}")
            clock("model_form")
    disc = discretization_stage(cp, out, fit, checked)
    if disc["warn"]:
        rep.problems = [*rep.problems, disc["message"]]
    clock("discretization")
    rep.trust += chains_caveat(rep.rows)
    outputs = RunOutputs(setup, meas, out, s, record, cp, loop, loo, y_liu, checked, disc, fit,
                         clock)
    outputs.write(rep)  # the surrogate's results are safe before the FE-exact step
    clock("report")
    if full_exact:
        rep = exact_stage(outputs, rep)
        clock("exact")
    pressed = pressed_constants(rep.rows, setup.space)
    if pressed:
        log.warning("%s", pressed)
    print(format_summary(rep.rows))
    run = RunDir.read(out)
    run.info.timing_s = clock.seconds
    run.write()
    from solderpyro.reporting.index import write_index

    write_index(out)
    n_ok = int(loop.ok.sum())
    return SpecimenCalibration(out, post, rep.rows, loo, n_ok, int(len(loop.ok)) - n_ok,
                               loop.as_dict())


def design_stage(setup: Setup, meas: Measurements, s: CalibrationSettings, out: Path,
                 warm: WarmStart | None, clock: StageClock
                 ) -> tuple[CalibrationProblem, Any, torch.Tensor]:
    """The problem and the adaptive design to its final posterior (:mod:`.adaptive`), with
    the discretization correction where ``s`` asks for it.

    Returns:
        the problem (on the corrected data where corrected), the design's final state and the
        ``(n,)`` um outputs at the literature parameters; ``clock`` gets "problem" and "design".
    """
    cp = CalibrationProblem.build(setup, meas, s.store, s.batch, s.progress)
    s.validate(cp.n_fe)
    y_liu = cp.literature()
    refit = warm.point if warm is not None else None  # the diagnosis's FE refit, if any
    if warm is not None:  # chains at the diagnosis's FE refit of this model, where there is one
        warm = warm.placed(cp.space, cp.priors.sigma_known is not None, seed=s.seed)
    clock("problem")
    rounds = adaptive_design(cp, s, out, warm, refit)
    if s.discretization == "correct" and rounds.reason != "misfit":
        # the data every later stage uses: the final posterior, the FE check, the outputs
        cp = cp.with_data(correct_discretization(cp, rounds.draws, rounds.best_fit))
    loop = final_design_posterior(cp, s, out, rounds)
    clock("design")
    return cp, loop, y_liu


def design_problems(loop: Any, loo: Any) -> list[str]:
    """The surrogate's own check against its leave-one-out ``loo`` and, where the design did
    not converge, its message (logged)."""
    problems = loop.gp.check(loo)
    log.info(loop.message)
    if not loop.converged:
        log.warning(loop.message)
        problems = [*problems, loop.message]
    return problems


def fe_check_stage(cp: CalibrationProblem, post: Any) -> FeChecked:
    """The FE at ``FE_CHECK_DRAWS`` spread draws of the surrogate posterior ``post`` (one
    batched solve): does the exact model fit where the surrogate says so?"""
    sig_fe = cp.priors.sigma_known or float(post.flat("sigma").median())
    draws = post.flat("t").detach().cpu().numpy()
    pick = spread_indices(len(draws), FE_CHECK_DRAWS)
    V_chk = cp.observed(draws[pick])
    chk = fe_check(V_chk, cp.y, sig_fe)
    log.info("FE check: best RMS residual of the FE over %d posterior draws %.4g um (%.2f "
             "noise sd)", chk["draws"], chk["rms_um"], chk["rms_over_sigma"])
    return FeChecked(sig_fe, draws, pick, V_chk, chk)


def fe_misfit_message(chk: dict[str, Any]) -> str:
    """The report's problem line (logged) for an FE check ``chk`` that misfits at every
    checked draw."""
    msg = (f"the FE itself misfits at every one of {chk['draws']} posterior draws: best "
           f"RMS residual {chk['rms_um']:.3g} um = {chk['rms_over_sigma']:.1f} noise sd "
           f"(chi2 {chk['chi2']:.0f} on {chk['n']} values): the model misses something "
           f"the data show (solderpyro diagnose names candidate effects)")
    log.warning(msg)
    return msg


def summary_rows(post: Any, draws: np.ndarray, setup: Setup, space: Any) -> list[dict]:
    """The surrogate posterior's summary rows, the 95 % interval central or from a box face
    the posterior piles against; the setup's parameters first, then sigma, then the
    effects'. ``draws``: ``(N, dim)`` physical units."""
    rows = with_intervals(post.summary(), draws, space)
    order = list(setup.space.names) + ["sigma"] + list(space.names[setup.space.n_theta:])
    rows.sort(key=lambda r: order.index(r["parameter"]) if r["parameter"] in order else 99)
    return rows


def save_posterior(cp: CalibrationProblem, post: Any, inp: Any, seed: int, out: Path
                   ) -> tuple[Bands, np.ndarray, np.ndarray]:
    """posterior.nc: the surrogate posterior with the data, the predictive and the pointwise
    log-likelihood at the same ``PREDICTIVE_DRAWS`` draws (az.plot_ppc, az.loo, az.compare on
    the file).

    Returns:
        the predictive (um); the draws' flat indices into ``(chain, draw)`` ``(k,)``; the
        data's joint log-likelihood there ``(k,)`` nats (:func:`~.outputs.log_likelihoods`).
    """
    n_draw = next(iter(post.samples.values())).shape[1]
    pick_pp = torch.as_tensor(thin_index(post.n_chains, n_draw, PREDICTIVE_DRAWS))
    bands = predict_observation_model(post, inp, None, seed=seed, index=pick_pp)
    loo, joint = log_likelihoods(post, inp, pick_pp)
    post.save(out / "posterior.nc", predictive={
        "y": cp.y.numpy(), "index": pick_pp.numpy(), "observed": bands.obs_draws.numpy(),
        "log_likelihood": loo.numpy(),
        "coords": observation_coords(cp.meas, cp.y.shape[0])})
    return bands, pick_pp.numpy(), joint.numpy()


def misfit_stage(cp: CalibrationProblem, s: CalibrationSettings, out: Path, loop: Any,
                 rep: Reported, noise_sd: float) -> tuple[BestFitPosterior | None, Reported]:
    """A design stopped because the model misfits: the FE's own best fit (where the design
    found one) replaces the surrogate's summary and predictive (the surrogate's summary goes
    to summary_surrogate.csv; the design's record and figure show the reported fit, and
    diagnose starts there). Returns the fit (or None) and what to report, with its trust line.
    """
    trust = _misfit_trust((loop.best_fit or {}).get("rms_over_sigma", float("nan")),
                          "so the design stopped refining its surrogate")
    x = cp.space.row((loop.best_fit or {}).get("x"))
    if x is None:
        return None, Reported(rep.rows, rep.bands, rep.problems, trust)
    fit, bands = _best_fit_stage(cp, s, x, noise_sd)
    n_y = int(cp.y.numel())
    loop.best_fit.update({
        "x": dict(zip(cp.space.names, map(float, fit.x), strict=True)),
        "chi2": fit.chi2, "rms_over_sigma": float(np.sqrt(fit.chi2 / n_y))})
    save_design(loop, cp.gp_box.names, out)
    write_summary(rep.rows, out / "summary_surrogate.csv", SUMMARY)
    rows = best_fit_rows(fit)
    trust += (f"; summary.csv is the FE's own best fit with its Laplace spread "
              f"widened {fit.scale:.1f}x for the misfit (the surrogate's posterior, "
              f"in summary_surrogate.csv, sits where only the surrogate fits)")
    # the misfit is correlated where physics is missing: the discrepancy's intervals too
    rows, why = model_form_stage(cp, rows, np.asarray(fit.x, float), out, s.seed)
    return fit, Reported(rows, bands, rep.problems, f"{trust}; {why}")


def best_fit_rows(fit: BestFitPosterior) -> list[dict]:
    """The summary rows of the FE's own best fit ``fit`` (no chains: R-hat and ESS NaN)."""
    return [{**r, "r_hat": float("nan"), "ess_bulk": float("nan"), "ess_tail": float("nan")}
            for r in fit.rows]


def surrogate_trust(converged: bool, full_exact: bool) -> str:
    """The report's trust line for the surrogate posterior: the design ``converged``, or
    not (``full_exact``: the FE-exact posterior follows)."""
    if converged:
        return ("the surrogate posterior: the design converged and the FE confirms the "
                "surrogate at posterior draws")
    return ("the surrogate posterior, with care: the design's budget ran out before the "
            "FE confirmed the surrogate" + (" (the FE-exact posterior follows)"
                                            if full_exact else ""))


def discretization_stage(cp: CalibrationProblem, out: Path, fit: BestFitPosterior | None,
                         checked: FeChecked) -> dict[str, Any]:
    """The FE's own discretization error against what the data resolve (two FE runs), at the
    FE's best fit ``fit`` where there is one, else at the best checked posterior draw (the
    marginal medians can lie off a curved ridge: there the refined FE fitted the modulus data
    165 chi-square worse, a change of the point, not of the mesh). Advisory: a failure is its
    message. Keeps the correction the final posterior used in
    discretization_correction.npz. Returns the check's record (``warn``, ``message``, ...).
    """
    best_chk = checked.result["best"]
    x_disc = fit.x if fit is not None else checked.draws[checked.pick][best_chk]
    data = cp.data
    if data.delta is not None:  # the correction the final posterior used, kept with the run
        # whatever the check below does (compare needs it to see the measured data)
        np.savez(out / "discretization_correction.npz", delta=data.delta,
                 y_measured=data.y_measured.numpy())
    try:
        # a model that misfits: measured against its misfit-widened noise sd (the check's
        # shift is then noise beside the missing effect)
        disc = discretization_check(
            cp, x_disc, checked.noise_sd if fit is None else float(fit.sigma[0]),
            V=None if fit is not None else checked.V[best_chk], delta=data.delta)
    except Exception as err:  # advisory: never lose the run over it
        log.warning("the discretization check failed", exc_info=True)
        disc = {"warn": False, "message": f"discretization check failed: {err!r}"}
    if data.delta is not None:
        disc["correction"] = dict(data.info)
    log.info(disc["message"])
    return disc


def chains_caveat(rows: list[dict]) -> str:
    """The trust line's caveat where the chains of the summary ``rows`` disagree (R-hat over
    ``RHAT_OK``): the surrogate may be right and its posterior still not sampled; else ""."""
    rhat = max((float(r["r_hat"]) for r in rows if np.isfinite(float(r["r_hat"]))),
               default=float("nan"))
    if rhat > RHAT_OK:
        return (f"; but the chains disagree (R-hat up to {rhat:.2f} > {RHAT_OK}): the "
                "intervals are not reliable until a longer run (--warmup, --draws) agrees")
    return ""


def _best_fit_stage(cp: CalibrationProblem, s: CalibrationSettings, x: np.ndarray,
                    noise_sd: float) -> tuple[Any, Bands]:
    """A model whose own FE best fit misfits: that best fit, refined from ``x`` (``(dim,)``
    physical units, ``cp.space``'s order), with its misfit-scaled Laplace spread
    (:func:`~.fe_exact.best_fit_posterior`), and the FE's predictive at
    ``BEST_FIT_BAND_RUNS`` of its draws (one batched solve through the store)."""
    from solderpyro.exact.coords import sampling_coords
    from solderpyro.pipeline.fe_exact import BestFitOptions, best_fit_posterior

    sg = s.surrogate
    coords = sampling_coords(cp.space, cp.setup.space.defaults, "auto", sg.inputs_T_C,
                             sg.inputs_rate)
    y = cp.y.detach().cpu().numpy()
    fit = best_fit_posterior(cp.observed, coords, x, y, noise_sd,
                             BestFitOptions(PREDICTIVE_DRAWS, s.seed))
    log.info("the FE's own best fit (chi2 %.0f, spread widened %.2fx for the misfit) is the "
             "reported result: %s", fit.chi2, fit.scale, ", ".join(
                 f"{r['parameter']}={r['median']:.4g} [{r['q2.5']:.4g}, {r['q97.5']:.4g}]"
                 for r in fit.rows))
    pick = spread_indices(len(fit.theta), BEST_FIT_BAND_RUNS)
    V = torch.as_tensor(cp.observed(np.vstack([fit.x[None], fit.theta[pick]])))  # one solve
    ok = torch.isfinite(V).all(1)
    V = V[ok]
    st = torch.full((len(V),), float(fit.sigma[0]), dtype=V.dtype)
    gen = torch.Generator().manual_seed(s.seed)
    bands = Bands(V, V + st[:, None] * torch.randn(V.shape, generator=gen, dtype=V.dtype), st)
    return fit, bands


def _misfit_trust(rms_sd: float, why: str) -> str:
    """The report's trust line for a model whose own FE best fit (``rms_sd`` noise sd off)
    misfits the data; ``why`` says what the calibration did about it."""
    return (f"neither posterior: the model misses something the data show (the FE's own best "
            f"fit is {rms_sd:.1f} noise sd off), {why}; run solderpyro diagnose")


def exact_stage(w: RunOutputs, rep: Reported) -> Reported:
    """The FE-exact posterior, identifiability and profile intervals after the surrogate's
    outputs ``rep`` (:func:`~.fe_exact.fe_exact`); rewrites the outputs through ``w``.
    Returns what is reported at the end."""
    cp, s = w.cp, w.settings
    ex_s = s.exact
    log.info("exact: the FE-exact posterior, %d rounds of %d FE runs (up to %d more while its "
             "weights are not reliable) after a best fit%s", ex_s.rounds, ex_s.runs,
             ex_s.extra_rounds, f" and a {ex_s.profile}-point profile"
             if ex_s.profile >= 2 else "")
    try:
        ex, ex_info = run_fe_exact(cp, s, w.loop.draws.posterior[0], w.checked,
                                   w.loop.best_fit)
    except RuntimeError as err:  # keep the surrogate's results (and the stored runs)
        log.warning("the FE-exact posterior failed: %s", err)
        rep = replace(rep, problems=[*rep.problems, f"the FE-exact posterior failed: {err}"])
        w.write(rep)
        return rep
    if ex is None:  # stopped at the FE's best fit: this model cannot fit the data
        rep = replace(rep, problems=[*rep.problems, ex_info["stopped"]], trust=_misfit_trust(
            ex_info["best_fit"]["rms_over_sigma"], "and the design's budget ran out with the "
            "FE disagreeing with the surrogate"))
        w.write(rep, None, ex_info, None)
        return rep
    ex_rows = exact_rows(ex, rep.rows)
    save_exact(w.out, ex, ex_rows, cp.space.names)
    unconfirmed = not ex.reliable and misses_best_fit(w.checked.result, ex_info["best_fit"],
                                                      cp.space.dim)
    if unconfirmed:  # neither posterior holds: the FE's own best fit is reported
        w, rep = unconfirmed_stage(w, rep, ex, ex_info)
    costly = (too_costly_to_profile(cp.space.dim, any(
        r.get("interval") == MODEL_FORM for r in rep.rows), unconfirmed)
              if ex_s.profile_ci == "auto" and not ex.reliable else "")
    if ex.reliable:
        rep = adopt_exact(w, rep, ex, ex_info)
    else:
        msg = (f"the FE-exact posterior is not reliable (ESS {ex_info['ess']:.0f}, Pareto "
               f"k-hat {ex_info['khat']:.2f} after {len(ex_info['rounds'])} rounds; needs k-hat "
               f"<= 0.7 and ESS >= 50): summary.csv is "
               + ("the FE's own best fit" if unconfirmed else "the surrogate's")
               + "; a larger calibration.exact.runs or extra_rounds")
        log.warning(msg)
        if costly:
            log.warning("exact: %s", costly)
        rep = replace(rep, problems=[*rep.problems, msg, *([costly] if costly else [])],
                      trust=rep.trust if unconfirmed else
                      unreliable_trust(costly, ex_s.profile_ci, w.loop.budget))
    w.write(rep, ex, ex_info, ex_rows)
    if ex_s.profile_ci == "off" or costly:
        return rep
    params = None  # every parameter
    if ex_s.profile_ci == "auto" and ex.reliable:
        weak = [v["parameter"] for v in ex_info["identifiability"]["weak"]]
        params = (form_open_parameters(cp.fx, weak) if cp.space.dim <= PROFILE_AUTO_MAX
                  and not ex_info.get("misfit_remains") else [])
        if not params:
            log.info("exact: profile intervals not computed: the FE-exact posterior is "
                     "reliable (calibration.exact.profile_ci=on computes them)")
            return rep
        log.info("exact: the data leave the form of an effect open (weakly identified: %s): "
                 "the FE's profile intervals of %s", ", ".join(weak), ", ".join(params))
    skip = unprofilable(cp.space.dim, len(cp.y))
    if skip:
        log.warning(skip)
        rep = replace(rep, problems=[*rep.problems, skip])
    else:
        rep = profile_stage(cp, w.out, rep, ex, ex_info, params)
    w.write(rep, ex, ex_info, ex_rows)
    return rep


def misses_best_fit(checked: dict[str, Any], best_fit: dict[str, Any], dim: int) -> bool:
    """Does the surrogate's posterior miss where the FE fits best? Its best checked draw (the
    FE check's record ``checked``: ``ok``, ``n``, ``rms_over_sigma``) misfits, or fits worse
    than the FE's own best fit (``best_fit``'s ``rms_over_sigma``, noise units) by more than
    the :data:`~.fe_check.MISSES_QUANTILE` point of chi2(``dim``)
    (:func:`~.fe_check.misses`). On the forms benchmark's linear modulus with a second-order
    lag the best checked draw was 1.46 noise sd off (inside the misfit rule) and the FE's best
    fit 1.11: chi-squares 4,775 and 2,770 on 2,240 values, against 26."""
    if not checked.get("ok", True):
        return True
    n = int(checked["n"])
    c2_draw = float(checked["rms_over_sigma"]) ** 2 * n
    c2_fit = float(best_fit.get("rms_over_sigma", np.inf)) ** 2 * n
    return misses(c2_draw, c2_fit, dim)


def unconfirmed_stage(w: RunOutputs, rep: Reported, ex: Any, ex_info: dict[str, Any]
                      ) -> tuple[RunOutputs, Reported]:
    """Neither posterior holds: the design's budget ran out with the surrogate's posterior
    away from where the FE fits best (:func:`misses_best_fit`), and the FE-exact posterior
    ``ex``'s weights are not reliable. The FE's own best fit with its misfit-scaled Laplace spread
    (:func:`_best_fit_stage`), from the better of the FE-exact step's best fit and its best
    importance sample, replaces the surrogate's summary (kept in summary_surrogate.csv) and
    predictive, widened for the model-form error where a misfit remains at it.

    Why: on the forms benchmark's linear modulus with a second-order lag (8 parameters) the
    surrogate's posterior was 1.46-3.47 noise sd off by the FE (two runs) and its FE-exact
    weights had ESS 1-2, while the FE fitted at 1.11 noise sd: the report gave the
    surrogate's summary.

    Returns:
        the outputs with the fit (their ``fit``) and what to report.
    """
    cp, s = w.cp, w.settings
    x = np.asarray(ex_info["best_fit"]["x"], float)
    ssr = np.asarray(ex.result.extra["ssr"], float)
    ssr = np.where(np.isfinite(ssr), ssr, np.inf)
    if len(ssr) and ssr.min() < ex_info["best_fit"].get("ssr_um2", np.inf):
        x = np.asarray(ex.samples[int(np.argmin(ssr))], float)
    fit, bands = _best_fit_stage(cp, s, x, w.checked.noise_sd)
    write_summary(rep.rows, w.out / "summary_surrogate.csv", SUMMARY)
    n = int(cp.y.numel())
    rms = float(np.sqrt(fit.chi2 / n))
    # the misfit the surrogate's outputs found at its best checked draw is not this fit's
    stale = remaining_misfit(w.checked.result.get("rms_over_sigma"), n, cp.space.dim)
    rows, problems = best_fit_rows(fit), [p for p in rep.problems if p != stale]
    (w.out / "model_form.json").unlink(missing_ok=True)
    trust = (f"the FE's own best fit ({rms:.2f} noise sd) with its Laplace spread widened "
             f"{fit.scale:.1f}x: the design's budget ran out before the FE confirmed the "
             f"surrogate, the surrogate's posterior misses it "
             f"({w.checked.result['rms_over_sigma']:.2f} noise sd at its best checked draw) "
             "and the FE-exact posterior's weights are not reliable; "
             f"{raise_budget(w.loop.budget)} for a posterior")
    left = remaining_misfit(rms, n, cp.space.dim)
    if left:
        rows, why = model_form_stage(cp, rows, np.asarray(fit.x, float), w.out, s.seed)
        trust += f", with care: {left}; {why}"
        problems.append(left)
    log.warning("exact: %s", trust)
    return replace(w, fit=fit), Reported(rows, bands, problems, trust)


def run_fe_exact(cp: CalibrationProblem, s: CalibrationSettings, post: Any,
                 checked: FeChecked, design_fit: dict[str, Any] | None = None
                 ) -> tuple[Any, dict[str, Any]]:
    """:func:`~.fe_exact.fe_exact` from the two best checked draws and the design's own FE
    best fit (``design_fit``, the loop's ``best_fit`` record, where there is one), with the
    surrogate posterior ``post``'s draws as the first proposal. Returns its posterior (None
    where it stopped at a best fit that misfits) and record; raises RuntimeError where it
    fails.

    Why the design's fit: where the surrogate was never confirmed its posterior draws can
    sit far from where the FE fits (the forms benchmark's linear modulus with a second-order
    lag: the best checked draw 3.47 noise sd off, the design's own FE fit 1.12), and four
    Levenberg-Marquardt steps from the draws alone ended at 1.37."""
    from solderpyro.exact.coords import sampling_coords

    ex_s, pr, y, sg = s.exact, cp.priors, cp.y, s.surrogate
    draws = checked.draws
    starts = draws[checked.pick][ranked(checked.V, y.numpy())[:2]]
    x_fit = cp.space.row((design_fit or {}).get("x"))
    if x_fit is not None:
        starts = np.vstack([starts, np.clip(x_fit, cp.space.lower, cp.space.upper)])
    coords = sampling_coords(cp.space, cp.setup.space.defaults, "auto", sg.inputs_T_C,
                             sg.inputs_rate)
    return fe_exact(cp.observed, coords, y, pr, draws, starts, ExactRun(
        ex_s.runs, ex_s.rounds, ex_s.profile, s.seed, len(draws),
        stop_if_misfit=ex_s.mode == "auto",
        noise_sd=pr.sigma_known or float(post.flat("sigma").median()),
        extra_rounds=ex_s.extra_rounds))


def save_exact(out: Path, ex: Any, ex_rows: list[dict], names: Any) -> None:
    """exact_samples.npz (the importance samples, their weights and rounds) and
    exact_posterior.csv (``ex_rows``) of the FE-exact posterior ``ex``."""
    np.savez(out / "exact_samples.npz", w=ex.result.u, theta=ex.samples,
             log_target=ex.result.log_target, log_q=ex.result.log_q, round=ex.result.round,
             weights=ex.result.weights(), names=np.array(names))
    write_summary(ex_rows, out / "exact_posterior.csv", tuple(ex_rows[0]))


def adopt_exact(w: RunOutputs, rep: Reported, ex: Any, ex_info: dict[str, Any]) -> Reported:
    """A reliable FE-exact posterior ``ex`` replaces the surrogate's summary (kept in
    summary_surrogate.csv) and predictive; adds its identifiability to ``ex_info``."""
    cp, s = w.cp, w.settings
    pr = cp.priors
    write_summary(rep.rows, w.out / "summary_surrogate.csv", SUMMARY)
    by = {r["parameter"]: r for r in ex.rows}
    rows = [{**by[r["parameter"]], "r_hat": float("nan"), "ess_bulk": ex_info["ess"],
             "ess_tail": ex_info["ess"]} for r in rep.rows]
    try:  # which parameters lie along a ridge, and what would narrow them
        ex_info["identifiability"] = identifiability(
            cp.setup, cp.effects, cp.space, rows, ex, cp.meas,
            float(pr.sigma_known or np.median(ex.sigma)))
    except Exception as err:  # advisory: never lose the run's files over it
        log.warning("identifiability not computed", exc_info=True)
        ex_info["identifiability"] = {"weak": [], "advice": "identifiability not "
                                      f"computed: {err!r}"}
    log.info("identifiability: %s", ex_info["identifiability"]["advice"])
    gen = torch.Generator().manual_seed(s.seed)
    Vt, st = torch.as_tensor(ex.V), torch.as_tensor(ex.sigma)
    bands = Bands(Vt, Vt + st[:, None] * torch.randn(Vt.shape, generator=gen,
                                                     dtype=Vt.dtype), st)
    trust = (f"the FE-exact posterior (ESS {ex_info['ess']:.0f}, Pareto k-hat "
             f"{ex_info['khat']:.2f}): the design's budget ran out before the FE confirmed "
             "the surrogate" if not w.loop.converged else
             f"the FE-exact posterior (ESS {ex_info['ess']:.0f})")
    problems = list(rep.problems)
    left = remaining_misfit((ex_info.get("best_fit") or {}).get("rms_over_sigma"),
                            len(cp.y), cp.space.dim)
    ex_info["misfit_remains"] = bool(left)
    if left:
        rows, why = model_form_stage(cp, rows, np.asarray(ex_info["best_fit"]["x"]), w.out,
                                     s.seed)
        trust += f", with care: {left}; {why}"
        problems.append(left)
    log.info("exact: reliable: summary.csv, draws.npz and the predictive are the FE-exact "
             "posterior's")
    return Reported(rows, bands, problems, trust)


def remaining_misfit(rms_sd: float | None, n: int, p: int) -> str:
    """What the trust line must say where a misfit remains at a best fit ``rms_sd`` noise sd
    off on ``n`` values with ``p`` parameters
    (:func:`~solderpyro.pipeline.fe_check.misfit_remains`), else ""."""
    if rms_sd is None or n <= p:
        return ""
    c2 = float(rms_sd) ** 2 * n
    left, q = misfit_remains(c2, n, p)
    if not left:
        return ""
    return (f"a misfit remains at the FE's best fit (chi2 {c2:.0f} on {n - p} dof, above its "
            f"99 % point {q:.0f}; RMS {float(rms_sd):.2f} noise sd): the model still misses "
            "part of the physics and the constants absorb what they can of it (run "
            "solderpyro diagnose on this run)")


def form_open_parameters(fx: EffectSet | None, weak: Sequence[str]) -> list[str]:
    """The parameters that size an effect of ``fx`` whose form the data leave open: one of
    its :attr:`~solderpyro.effects.base.Effect.nuisance` parameters is among ``weak`` (names
    the FE-exact posterior's identifiability found weakly identified). In ``fx``'s order.

    Why: a flat prior over an open form's box is no physical statement, yet it decides the
    interval of the parameters the form acts with. On the forms benchmark's slow (Newton)
    cool-down from 150 degC near the box's faces the cool-down's shape spanned its box, the
    reliable FE-exact posterior put T_sf at 97-129 degC (no sample above 135 among 256), and
    the FE's profile of T_sf, the shape and duration refitted, held 150 in 3 of 4 noise seeds
    (91.5-175.7 degC on the benchmark's own)."""
    out: list[str] = []
    for e in (fx.effects if fx is not None else ()):
        if set(e.nuisance) & set(weak):
            out += e.sized
    return out


def profile_stage(cp: CalibrationProblem, out: Path, rep: Reported, ex: Any,
                  ex_info: dict[str, Any], params: Sequence[str] | None = None) -> Reported:
    """95 % profile-likelihood intervals through the FE of ``params`` (default every
    parameter; :func:`~solderpyro.exact.posterior.profile_intervals`, from the FE-exact
    posterior ``ex``'s samples): profile_ci.csv and ``ex_info["profile_ci"]``; a failure is a
    problem. Where ``ex``'s weights are not reliable, or ``params`` are named (an effect's
    parameters whose form the data leave open, :func:`form_open_parameters`), the reported
    intervals are widened to hold the profile intervals
    (:func:`~solderpyro.calibration.intervals.profile_hull`)."""
    from solderpyro.exact.posterior import profile_intervals

    space, y = cp.space, cp.y
    cols = None if params is None else [list(space.names).index(p) for p in params]
    sig_p = float(cp.priors.sigma_known or np.median(ex.sigma))
    log.info("profile CI: 95 %% profile-likelihood intervals of %d parameters through the "
             "FE (sigma %.4g um)", space.dim if cols is None else len(cols), sig_p)
    try:
        pci = profile_intervals(cp.observed, space, y.numpy(), sig_p, ex.samples,
                                np.asarray(ex.result.extra["ssr"], float), cols)
    except (RuntimeError, ValueError) as err:
        log.warning("the profile-likelihood intervals failed: %s", err)
        return replace(rep, problems=[*rep.problems,
                                      f"the profile-likelihood intervals failed: {err}"])
    ex_info["profile_ci"] = [p.as_dict() for p in pci]
    ex_info["profile_ci_sigma_um"] = sig_p
    by = {r["parameter"]: r for r in rep.rows}
    pci_rows = [{"parameter": p.parameter, "lower": p.lower, "upper": p.upper,
                 "at_lower_bound": str(p.at_lower_bound).lower(),
                 "at_upper_bound": str(p.at_upper_bound).lower(),
                 "truncated": str(p.truncated).lower(),
                 "posterior_q2.5": by[p.parameter]["q2.5"],
                 "posterior_q97.5": by[p.parameter]["q97.5"]} for p in pci]
    write_summary(pci_rows, out / "profile_ci.csv", tuple(pci_rows[0]))
    for p in pci:
        log.info("profile CI: %s in [%.4g, %.4g]%s", p.parameter, p.lower, p.upper,
                 " (reaches the box's bound)"
                 if p.at_lower_bound or p.at_upper_bound else "")
    if ex.reliable and params is None:
        return rep
    rows = profile_hull(rep.rows, {p.parameter: (p.lower, p.upper) for p in pci})
    widened = [r["parameter"] for r in rows if r.get("interval") == PROFILE]
    if not widened:
        return replace(rep, rows=rows)
    why = ("the data leave the form it acts with open" if ex.reliable else
           "the FE-exact posterior is not reliable")
    log.info("profile CI: %s, so the reported 95 %% intervals of %s are widened to hold the "
             "FE's profile intervals", why, ", ".join(widened))
    trust = rep.trust
    if ex.reliable:
        trust += (f"; the intervals of {', '.join(widened)} hold the FE's profile intervals "
                  "(the data leave the form of the effect open: profile_ci.csv)")
    return replace(rep, rows=rows, trust=trust)
