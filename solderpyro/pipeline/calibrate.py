"""The specimen calibration end to end, as a short sequence of stages.

    problem (:mod:`.problem`) -> adaptive design: surrogate + posterior per round, FE runs
    placed by BoTorch until the FE confirms (:mod:`.adaptive`) -> FE check at posterior draws
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
from pathlib import Path
from typing import Any

import numpy as np
import torch

from solderpyro.calibration import predict_observation_model
from solderpyro.calibration.intervals import with_intervals
from solderpyro.calibration.mcmc import WarmStart, format_summary, thin_index, write_summary
from solderpyro.calibration.predictive import Bands
from solderpyro.configure import Setup
from solderpyro.design.loop import StageClock, spread_indices
from solderpyro.io.measurements import Measurements
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
    ranked,
)
from solderpyro.pipeline.fe_exact import SUMMARY, WEAK_SHARE, exact_rows, fe_exact, identifiability
from solderpyro.pipeline.outputs import SpecimenCalibration, posterior_draws, save_run
from solderpyro.pipeline.problem import CalibrationProblem
from solderpyro.rundir import Checks, DesignSummary, RunDir, RunInfo, SurrogateRecord
from solderpyro.settings import CalibrationSettings

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
    Moire offsets, 12 parameters on 8 values: more than 40 minutes in session 31).
    """
    if n_params - 1 < n_values:
        return None
    return (f"profile intervals not computed: {n_params} parameters on {n_values} values "
            "cannot be profiled (the other parameters fit the data at every value of each: "
            "flat profiles); measure more values or calibrate fewer parameters")


def calibrate_specimen(setup: Setup, meas: Measurements, out: str | Path,
                       settings: CalibrationSettings | None = None,
                       record: dict[str, Any] | None = None,
                       warm: WarmStart | None = None) -> SpecimenCalibration:
    """Calibrate ``setup.space`` (default s0, QR, xi, m; plus the parameters of switched-on
    effects) against ``meas``.

    Args:
        setup: the typed problem, parameter box and defaults (:mod:`solderpyro.configure`).
        meas: measurements; times and points must be model outputs (A, B, grid labels).
        out: the run directory (created).
        settings: every setting (:class:`CalibrationSettings`; default: the adaptive design
            with its default budget).
        record: how the run was asked for (e.g. ``{"overrides": [...], "data": path}``), kept in
            the run's record (:class:`~solderpyro.rundir.RunInfo`) so that ``solderpyro
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
        cp = cp.with_data(correct_discretization(cp, rounds.draws))
    loop = final_design_posterior(cp, s, out, rounds)
    clock("design")
    post, inp = loop.draws.posterior
    gp = loop.gp
    loo = gp.loo()
    problems = gp.check(loo)
    log.info(loop.message)
    if not loop.converged:
        log.warning(loop.message)
        problems = [*problems, loop.message]
    # the FE at a few posterior draws: does the exact model fit where the surrogate says so?
    pr = cp.priors
    sig_fe = pr.sigma_known or float(post.flat("sigma").median())
    draws = post.flat("t").detach().cpu().numpy()
    pick = spread_indices(len(draws), FE_CHECK_DRAWS)
    V_chk = cp.observed(draws[pick])
    chk = fe_check(V_chk, cp.y, sig_fe)
    clock("fe_check")
    log.info("FE check: best RMS residual of the FE over %d posterior draws %.4g um (%.2f "
             "noise sd)", chk["draws"], chk["rms_um"], chk["rms_over_sigma"])
    if not chk["ok"]:
        msg = (f"the FE itself misfits at every one of {chk['draws']} posterior draws: best "
               f"RMS residual {chk['rms_um']:.3g} um = {chk['rms_over_sigma']:.1f} noise sd "
               f"(chi2 {chk['chi2']:.0f} on {chk['n']} values): the model misses something "
               f"the data show (solderpyro diagnose names candidate effects)")
        log.warning(msg)
        problems = [*problems, msg]
    space = cp.space
    # the reported 95 % interval: central, or from a box face the posterior piles against
    rows = with_intervals(post.summary(), draws, space)
    order = list(setup.space.names) + ["sigma"] + list(space.names[setup.space.n_theta:])
    rows.sort(key=lambda r: order.index(r["parameter"]) if r["parameter"] in order else 99)
    n_draw = next(iter(post.samples.values())).shape[1]
    pick_pp = torch.as_tensor(thin_index(post.n_chains, n_draw, PREDICTIVE_DRAWS))
    bands = predict_observation_model(post, inp, None, seed=s.seed, index=pick_pp)
    # posterior.nc: the surrogate posterior with the data, the predictive and the pointwise
    # log-likelihood at the same draws (az.plot_ppc, az.loo, az.compare on the file)
    post.save(out / "posterior.nc", predictive={
        "y": cp.y.numpy(), "index": pick_pp.numpy(), "observed": bands.obs_draws.numpy(),
        "log_likelihood": bands.log_likelihood(cp.y).numpy()})
    # a model whose own FE best fit misfits (loop.reason "misfit") gets no FE-exact posterior
    full_exact = s.exact.mode == "on" or (
        s.exact.mode == "auto" and loop.reason == "budget" and not loop.rounds[-1].fe_ok)
    fit = None
    if loop.reason == "misfit":
        trust = _misfit_trust((loop.best_fit or {}).get("rms_over_sigma", float("nan")),
                              "so the design stopped refining its surrogate")
        if loop.best_fit and loop.best_fit.get("x"):
            fit, bands = _best_fit_stage(cp, s, loop.best_fit, sig_fe)
            # the design's record and figure show the fit that is reported (and diagnose
            # starts there)
            n_y = int(cp.y.numel())
            loop.best_fit.update({
                "x": dict(zip(space.names, map(float, fit.x), strict=True)),
                "chi2": fit.chi2, "rms_over_sigma": float(np.sqrt(fit.chi2 / n_y))})
            save_design(loop, cp.gp_box.names, out)
            write_summary(rows, out / "summary_surrogate.csv", SUMMARY)
            rows = [{**r, "r_hat": float("nan"), "ess_bulk": float("nan"),
                     "ess_tail": float("nan")} for r in fit.rows]
            trust += (f"; summary.csv is the FE's own best fit with its Laplace spread "
                      f"widened {fit.scale:.1f}x for the misfit (the surrogate's posterior, "
                      f"in summary_surrogate.csv, sits where only the surrogate fits)")
            clock("best_fit")
    elif loop.converged:
        trust = ("the surrogate posterior: the design converged and the FE confirms the "
                 "surrogate at posterior draws")
    else:
        trust = ("the surrogate posterior, with care: the design's budget ran out before the "
                 "FE confirmed the surrogate" + (" (the FE-exact posterior follows)"
                                                 if full_exact else ""))
    # the FE's own discretization error against what the data resolve (two FE runs)
    # at the FE's best fit where there is one, else at the best checked posterior draw (the
    # marginal medians can lie off a curved ridge: there the refined FE fitted the modulus
    # data 165 chi-square worse, a change of the point, not of the mesh)
    best_chk = chk["best"]
    x_disc = fit.x if fit is not None else draws[pick][best_chk]
    data = cp.data
    if data.delta is not None:  # the correction the final posterior used, kept with the run
        # whatever the check below does (compare needs it to see the measured data)
        np.savez(out / "discretization_correction.npz", delta=data.delta,
                 y_measured=data.y_measured.numpy())
    try:
        # a model that misfits: measured against its misfit-widened noise sd (the check's
        # shift is then noise beside the missing effect)
        disc = discretization_check(cp, x_disc, sig_fe if fit is None else float(fit.sigma[0]),
                                    V=None if fit is not None else V_chk[best_chk],
                                    delta=data.delta)
    except Exception as err:  # advisory: never lose the run over it
        log.warning("the discretization check failed", exc_info=True)
        disc = {"warn": False, "message": f"discretization check failed: {err!r}"}
    if data.delta is not None:
        disc["correction"] = dict(data.info)
    log.info(disc["message"])
    if disc["warn"]:
        problems = [*problems, disc["message"]]
    clock("discretization")
    rhat = max((float(r["r_hat"]) for r in rows if np.isfinite(float(r["r_hat"]))),
               default=float("nan"))
    if rhat > RHAT_OK:  # the surrogate may be right and its posterior still not sampled
        trust += (f"; but the chains disagree (R-hat up to {rhat:.2f} > {RHAT_OK}): the "
                  "intervals are not reliable until a longer run (--warmup, --draws) agrees")

    def write_all(rows: list[dict], bands: Any, problems: list[str], ex: Any = None,
                  ex_info: dict[str, Any] | None = None, ex_rows: list[dict] | None = None,
                  trust: str = trust) -> None:
        """summary.csv, draws.npz, the run's record and the report (the FE-exact posterior's where
        ``ex`` is reliable); written before the FE-exact step and again after it."""
        from solderpyro import report

        saved = (ex.theta, ex.sigma) if ex is not None and ex.reliable else None
        kind = "fe-exact" if saved is not None else "surrogate"
        if fit is not None:
            saved, kind = (fit.theta, fit.sigma), "fe-best-fit"
        write_summary(rows, out / "summary.csv", SUMMARY)
        sg = s.surrogate
        asked = dict(record or {})
        info = RunInfo(
            list(space.names), list(space.lower), list(space.upper), list(cp.effects),
            pr.sigma_known, [float(t) for t in meas.times()], list(meas.points()),
            overrides=list(asked.pop("overrides", [])), data=asked.pop("data", None),
            store=s.store, seed=s.seed, settings=s.as_dict(),
            surrogate=SurrogateRecord(sg.kernel, sg.ard, sg.mean, gp.output, sg.inputs,
                                      sg.inputs_T_C, sg.inputs_rate),
            n_runs=int(len(loop.X)), design=DesignSummary(loop.as_dict()),
            checks=Checks(chk, disc, float(loo.rmse_rel), float(loo.coverage95)),
            timing_s=clock.seconds, trust=trust, posterior=kind, exact=ex_info or None,
            extra=asked)
        run = save_run(out, meas, info,
                       posterior_draws(post, bands, space.names, cp.y, y_liu, saved), post.warm)
        last = loop.rounds[-1]
        notes = [f"**trust**: {trust}",
                 f"adaptive design: {len(loop.X)} FE runs in {len(loop.rounds)} rounds "
                 f"({loop.reason}): {loop.message} (design.png, design.csv)",
                 f"last round: code chi2 {last.code_chi2:.3g}, max |FE - surrogate| chi2 "
                 f"{last.fe_gap:.3g} (varying by {last.fe_spread:.2g} across the checked "
                 f"draws, tolerance {s.design.fe_spread:g}), tolerance {last.tolerance:.3g}",
                 f"FE check: the FE at {chk['draws']} posterior draws (one batched solve), "
                 f"best RMS residual {chk['rms_um']:.3g} um = {chk['rms_over_sigma']:.2f} "
                 f"noise sd (chi2 {chk['chi2']:.0f} on {chk['n']} values)",
                 disc["message"]]
        if saved is not None and ex_info:
            notes.insert(1, f"**posterior: FE-exact** (adaptive importance sampling with the FE "
                            f"in the likelihood, {ex_info['fe_runs']} FE runs, ESS "
                            f"{ex_info['ess']:.0f}, Pareto k-hat {ex_info['khat']:.2f}); the "
                            f"surrogate's is in summary_surrogate.csv")
        if fit is not None:
            notes.insert(1, f"**summary: the FE's own best fit** (chi2 {fit.chi2:.0f} on "
                            f"{cp.y.numel()} values), intervals from its Laplace covariance "
                            f"widened by sqrt(chi2 / (n - dim)) = {fit.scale:.2f}; the "
                            "surrogate's posterior is in summary_surrogate.csv")
        ident = (ex_info or {}).get("identifiability") or {}
        if saved is not None and ident.get("weak"):
            notes.append("weakly identified by these data (95 % interval over >= "
                         f"{WEAK_SHARE:.0%} of the prior box): "
                         + ", ".join(v["parameter"] for v in ident["weak"])
                         + "; see 'Identifiability' below for the measurement that would "
                         "narrow them")
        t = cp.tally  # every FE run of the calibration so far (Liu, design, checks, exact)
        report.write(report.CalibrationReport(
            run, meas, rows, post, loo, bands, y_liu.numpy(),
            report.FeRunCounts(t.n_ok, t.n_failed, t.n_reused, t.n_computed), problems, notes,
            None if ex is None or not ex_rows else report.ExactReport(ex, ex_rows, draws)))

    write_all(rows, bands, problems)  # the surrogate's results are safe before the FE-exact step
    clock("report")
    if full_exact:
        rows, bands, problems = _exact_stage(cp, s, out, loop, post, draws, pick, V_chk, rows,
                                             bands, problems, write_all)
        clock("exact")
    print(format_summary(rows))
    run = RunDir.read(out)
    run.info.timing_s = clock.seconds
    run.write()
    from solderpyro.index import write_index

    write_index(out)
    n_ok = int(loop.ok.sum())
    return SpecimenCalibration(out, post, rows, loo, n_ok, int(len(loop.ok)) - n_ok,
                               loop.as_dict())


def _best_fit_stage(cp: CalibrationProblem, s: CalibrationSettings, best: dict[str, Any],
                    noise_sd: float) -> tuple[Any, Bands]:
    """A model whose own FE best fit misfits: that best fit, with its misfit-scaled Laplace
    spread (:func:`~.fe_exact.best_fit_posterior`), and the FE's predictive at
    ``BEST_FIT_BAND_RUNS`` of its draws (one batched solve through the store)."""
    from solderpyro.coords import sampling_coords
    from solderpyro.pipeline.fe_exact import best_fit_posterior

    sg = s.surrogate
    coords = sampling_coords(cp.space, cp.setup.space.defaults, "auto", sg.inputs_T_C,
                             sg.inputs_rate)
    x = np.array([best["x"][nm] for nm in cp.space.names])
    y = cp.y.detach().cpu().numpy()
    fit = best_fit_posterior(cp.observed, coords, x, y, noise_sd, PREDICTIVE_DRAWS, s.seed)
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


def _exact_stage(cp: CalibrationProblem, s: CalibrationSettings, out: Path, loop: Any, post: Any,
                 draws: np.ndarray, pick: np.ndarray, V_chk: np.ndarray, rows: list[dict],
                 bands: Any, problems: list[str], write_all: Any
                 ) -> tuple[list[dict], Any, list[str]]:
    """The FE-exact posterior, identifiability and profile intervals; rewrites the outputs.
    Returns the rows, bands and problems to report."""
    ex_s = s.exact
    pr = cp.priors
    y = cp.y
    space = cp.space
    log.info("exact: the FE-exact posterior, %d rounds of %d FE runs after a best fit%s",
             ex_s.rounds, ex_s.runs, f" and a {ex_s.profile}-point profile"
             if ex_s.profile >= 2 else "")
    starts = draws[pick][ranked(V_chk, y.numpy())[:2]]
    from solderpyro.coords import sampling_coords

    sg = s.surrogate
    coords = sampling_coords(space, cp.setup.space.defaults, "auto", sg.inputs_T_C,
                             sg.inputs_rate)
    try:
        ex, ex_info = fe_exact(cp.observed, coords, y, pr, draws, starts, ex_s.runs,
                               ex_s.rounds, ex_s.profile, s.seed, len(draws),
                               stop_if_misfit=ex_s.mode == "auto",
                               noise_sd=pr.sigma_known or float(post.flat("sigma").median()))
    except RuntimeError as err:  # keep the surrogate's results (and the stored runs)
        log.warning("the FE-exact posterior failed: %s", err)
        problems = [*problems, f"the FE-exact posterior failed: {err}"]
        write_all(rows, bands, problems)
        return rows, bands, problems
    if ex is None:  # stopped at the FE's best fit: this model cannot fit the data
        problems = [*problems, ex_info["stopped"]]
        trust = _misfit_trust(ex_info["best_fit"]["rms_over_sigma"], "and the design's "
                              "budget ran out with the FE disagreeing with the surrogate")
        write_all(rows, bands, problems, None, ex_info, None, trust)
        return rows, bands, problems
    ex_rows = exact_rows(ex, rows)
    np.savez(out / "exact_samples.npz", w=ex.result.u, theta=ex.samples,
             log_target=ex.result.log_target, log_q=ex.result.log_q, round=ex.result.round,
             weights=ex.result.weights(), names=np.array(space.names))
    write_summary(ex_rows, out / "exact_posterior.csv", tuple(ex_rows[0]))
    if ex.reliable:
        write_summary(rows, out / "summary_surrogate.csv", SUMMARY)
        by = {r["parameter"]: r for r in ex.rows}
        rows = [{**by[r["parameter"]], "r_hat": float("nan"), "ess_bulk": ex_info["ess"],
                 "ess_tail": ex_info["ess"]} for r in rows]
        try:  # which parameters lie along a ridge, and what would narrow them
            ex_info["identifiability"] = identifiability(
                cp.setup, cp.effects, space, rows, ex, cp.meas,
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
                 "the surrogate" if not loop.converged else
                 f"the FE-exact posterior (ESS {ex_info['ess']:.0f})")
        log.info("exact: reliable: summary.csv, draws.npz and the predictive are the FE-exact "
                 "posterior's")
    else:
        msg = (f"the FE-exact posterior is not reliable (ESS {ex_info['ess']:.0f}, Pareto "
               f"k-hat {ex_info['khat']:.2f}; needs k-hat <= 0.7 and ESS >= 50): summary.csv "
               f"stays the surrogate's; a larger calibration.exact.runs or more rounds")
        log.warning(msg)
        problems = [*problems, msg]
        trust = ("neither posterior: the design's budget ran out with the FE "
                 "disagreeing, and the FE-exact posterior's weights are not reliable; raise "
                 "--budget; the profile intervals (profile_ci.csv) are the FE's own")
    write_all(rows, bands, problems, ex, ex_info, ex_rows, trust)
    skip = unprofilable(space.dim, len(y)) if ex_s.profile_ci else None
    if skip:
        log.warning(skip)
        problems = [*problems, skip]
        write_all(rows, bands, problems, ex, ex_info, ex_rows, trust)
    elif ex_s.profile_ci:
        sig_p = float(pr.sigma_known or np.median(ex.sigma))
        log.info("profile CI: 95 %% profile-likelihood intervals of %d parameters through the "
                 "FE (sigma %.4g um)", space.dim, sig_p)
        from solderpyro.exact import profile_intervals

        try:
            pci = profile_intervals(cp.observed, space, y.numpy(), sig_p, ex.samples,
                                    np.asarray(ex.result.extra["ssr"], float))
        except (RuntimeError, ValueError) as err:
            log.warning("the profile-likelihood intervals failed: %s", err)
            problems = [*problems, f"the profile-likelihood intervals failed: {err}"]
        else:
            ex_info["profile_ci"] = [p.as_dict() for p in pci]
            ex_info["profile_ci_sigma_um"] = sig_p
            by = {r["parameter"]: r for r in rows}
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
        write_all(rows, bands, problems, ex, ex_info, ex_rows, trust)
    return rows, bands, problems
