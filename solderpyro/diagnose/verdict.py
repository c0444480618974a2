"""The verdict of a diagnosis: the candidates ranked, the misfit explained or not, in words.

:func:`verdict` takes the screen's statistics and the judged FE refits
(:class:`VerdictInputs`; :mod:`solderpyro.diagnose.decide`'s rules) and returns the
:class:`~solderpyro.diagnose.diagnosis.Diagnosis`. :func:`where` says where an unexplained
misfit is largest; :func:`add_cannot_rule_out` adds what the data cannot rule out where the
model fits.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.stats import chi2 as _chi2

from solderpyro.diagnose.decide import (
    APART_CHI2,
    EXPLAINED_SD,
    LATER_SHARE,
    Floor,
    Judged,
    chosen_refit,
    effect_size,
    explained,
    remains,
    saturates,
)
from solderpyro.diagnose.diagnosis import Diagnosis
from solderpyro.diagnose.faces import Face, faces_text
from solderpyro.diagnose.fingerprint import Fingerprints
from solderpyro.diagnose.ruleout import describe
from solderpyro.diagnose.screen import MIN_IDENTIFIABLE
from solderpyro.diagnose.stats import Misfit, PredictiveCheck, Score, confusion, evidence


@dataclass
class VerdictInputs:
    """What the verdict is taken from.

    Attributes:
        mf: the misfit at the first draw (linearised refit of the calibrated parameters);
            ``mf.residual`` is ``(n,)``, um.
        pc: the posterior predictive check.
        scores: one score test per candidate at the first draw (ladder applied);
            per_draw: the score tests at each draw ``[K][n_cand]``.
        sigma: noise sd, um.
        steps: per forward step, the judged refits (the first step: one per refitted
            candidate); empty without refits.
        chosen: the effects the forward steps added; tie: the candidates that could not be
            told apart where the steps stopped.
        base_chi2: chi-square at the FE's best fit (or the linearised misfit without refits).
        n_cal: calibrated parameters; floor: the discretization floor.
        faces, freeing: see the attributes' comments (empty without refits).
    """

    mf: Misfit
    pc: PredictiveCheck
    scores: list[Score]
    per_draw: list[list[Score]]
    sigma: float
    steps: list[list[Judged]]
    chosen: tuple[str, ...]
    tie: list[str]
    base_chi2: float
    n_cal: int
    floor: Floor
    #: the Anand constants the base fit presses against the box's faces
    faces: tuple[Face, ...] = ()
    #: candidates that, refitted, fit as well with fewer constants on faces, each with the
    #: constants it moves off them (:func:`~solderpyro.diagnose.faces.freeing`)
    freeing: tuple[tuple[str, tuple[str, ...]], ...] = ()

    @property
    def n(self) -> int:
        """Number of data values."""
        return len(self.mf.residual)

    @property
    def first(self) -> dict[str, Judged]:
        """The first step's judged refits by candidate."""
        return {j.refit.name: j for j in self.steps[0]} if self.steps else {}


def candidate_entry(v: VerdictInputs, i: int) -> dict[str, Any]:
    """The ranking row of candidate ``v.scores[i]``: its screen, and its FE refit where one
    ran (else the screen's linearised chi-square drop standing in)."""
    s, n, sigma = v.scores[i], v.n, v.sigma
    j = v.first.get(s.effect)
    ev_draws = [pd[i].evidence for pd in v.per_draw]
    e: dict[str, Any] = {
        "effect": s.effect, "identifiable": float(s.identifiable),
        "score_statistic": float(s.statistic), "score_dof": s.dof,
        "score_p_value": float(s.p_value), "delta": [float(x) for x in s.delta],
        "likelihood_ratio": s.lr, "best_magnitude": s.lr_value,
        "evidence_over_draws": [round(float(x), 3) for x in ev_draws]}
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
        after = max(v.base_chi2 - float(s.statistic), 0.0)
        sz = effect_size(v.base_chi2, after, n, v.n_cal, sigma)
        why = (f"{s.dof} parameters the data cannot test: with the calibrated ones they "
               f"fit any {n} values" if saturates(s.dof, n - v.n_cal)
               else f"screen p = {s.p_value:.2g}")
        e.update({"refit": f"not run ({why})", "refit_starts": 0,
                  "profile_chi2": None, "statistic": float(s.statistic), "dof": s.dof,
                  "p_value": float(s.p_value), "evidence": round(float(s.evidence), 4),
                  "chi2_after": after, **sz.to_json(),
                  "floor_um2": v.floor.of(s.effect), "clears_floor": False, "flagged": False})
    e["explained_share"] = e["systematic_share"]
    return e


def rank_candidates(v: VerdictInputs) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """``(ranking, failed)``: refitted candidates by likelihood ratio, then the screened-out
    ones by their screen; failed refits apart. Each row gets its correlation with the top."""
    entries: list[tuple[dict[str, Any], Score]] = []
    failed: list[tuple[dict[str, Any], Score]] = []
    for i, s in enumerate(v.scores):
        e = candidate_entry(v, i)
        (failed if e["refit"] == "failed" else entries).append((e, s))
    entries.sort(key=lambda es: (es[0]["refit"] != "converged", -es[0]["statistic"]))
    if entries:
        corr_top = entries[0][1]
        for e, s in entries + failed:
            e["correlation_with_top"] = round(confusion(corr_top, s), 4)
    return [e for e, _ in entries], [e for e, _ in failed]


def headline(v: VerdictInputs) -> str:
    """The misfit at the FE's best fit in words (chi-square, dof, RMS in um and noise sd)."""
    n, sigma, c = v.n, v.sigma, v.base_chi2
    return (f"chi2 = {c:.1f} on {n - v.n_cal} dof at the FE's best fit; RMS "
            f"{np.sqrt(c / n) * sigma:.3g} um = {np.sqrt(c / n):.2f} noise sd "
            f"(noise {sigma:.3g} um)")


def final_chi2(v: VerdictInputs) -> float:
    """Chi-square of the refit that added the last chosen effect (the base's if none)."""
    last = chosen_refit(v.steps, v.chosen)
    return last.chi2 if last is not None else v.base_chi2


def explained_text(v: VerdictInputs, head: str) -> tuple[str, list[str]]:
    """Verdict and suggestion where the chosen effects explain the misfit."""
    n, sigma, chosen = v.n, v.sigma, v.chosen
    c = final_chi2(v)
    fin = np.sqrt(c / n)
    j0 = v.first[chosen[0]]
    share = effect_size(v.base_chi2, c, n, v.n_cal, sigma).systematic_share
    text = (f"misfit ({head}). Best explanation: {' + '.join(chosen)}: the RMS falls to "
            f"{fin * sigma:.3g} um = {fin:.2f} noise sd, "
            + (f"removing {share:.0%} of the systematic misfit" if share is not None
               else "though the global chi-square is within the noise")
            + f" (likelihood ratio {j0.refit.lr:.1f} on {j0.refit.dof} dof for "
            f"{chosen[0]})")
    if len(chosen) > 1:
        text += "; found in forward steps: " + " then ".join(chosen)
    suggestions = ["recalibrate with it: solderpyro calibrate ... effects=[" + ",".join(chosen)
                   + "]"]
    freeing = still_freeing(v)
    if freeing:
        text += (f"; but with {' + '.join(chosen)} on, constants still press the faces of the "
                 "prior box, and " + "; ".join(
                     f"{j.refit.name} fits as well (chi2 {j.refit.chi2 - c:+.1f}) and moves "
                     f"{', '.join(j.frees)} off them" for j in freeing)
                 + ": the data cannot tell whether it is present too")
        suggestions += ["recalibrate with effects=[" + ",".join((*chosen, j.refit.name))
                        + "] too: its intervals admit it" for j in freeing]
    return text, suggestions


def partial_absorber(v: VerdictInputs) -> Judged | None:
    """The flagged candidate of the step after the chosen effects that took up most of what
    they left, where none took up enough to be added
    (:func:`~solderpyro.diagnose.decide.takes_up_what_remains`); None otherwise."""
    if not v.chosen or not v.steps or v.tie:
        return None
    last = v.steps[-1]
    if any(j.refit.name == v.chosen[-1] or j.frees for j in last):
        return None
    fl = [j for j in last if j.flagged and j.size.systematic_share is not None]
    return max(fl, key=lambda j: j.refit.lr) if fl else None


def still_freeing(v: VerdictInputs) -> list[Judged]:
    """The candidates that, refitted with the chosen effects on, fit as well and move off the
    faces constants the chosen effects' refit leaves on them
    (:func:`~solderpyro.diagnose.decide.mark_freeing`), best fit first."""
    if not v.chosen or not v.steps:
        return []
    return sorted((j for j in v.steps[-1] if j.frees and j.refit.name not in v.chosen),
                  key=lambda j: j.refit.chi2)


def tie_text(v: VerdictInputs, head: str) -> tuple[str, list[str]]:
    """Verdict and suggestions where tied candidates each explain the misfit (with the chosen
    effects on, where a forward step tied: those are the selection, the tie is about what
    remains after them)."""
    measure = ("measure where the candidates differ (see 'separation' in diagnosis.json): "
               "the full-field V or more times")
    if not v.chosen:
        return (f"misfit ({head}). The data cannot tell apart: {', '.join(v.tie)} (their "
                f"refits differ by less than chi2 {APART_CHI2:.1f}, a likelihood ratio of "
                "20; each explains it); do not pick one on these data"), [measure]
    on = " + ".join(v.chosen)
    fin = np.sqrt(final_chi2(v) / v.n)
    text = (f"misfit ({head}). Best explanation: {on}: the RMS falls to {fin * v.sigma:.3g} "
            f"um = {fin:.2f} noise sd. What remains with it on, the data cannot attribute: "
            f"{', '.join(v.tie)} each take it up (their refits differ by less than chi2 "
            f"{APART_CHI2:.1f}); a remainder this small may be {on}'s form differing from "
            "the library's rather than another effect")
    return text, ["recalibrate with it: solderpyro calibrate ... effects=[" + ",".join(v.chosen)
                  + "]", measure]


def unexplained_text(v: VerdictInputs, head: str) -> str:
    """Verdict where no candidate explains the misfit."""
    # a refit with as many parameters as the data leave fits anything: it is no "best refit"
    testable = [j.refit.chi2 for st in v.steps for j in st
                if j.refit.ok and not saturates(j.refit.dof, v.n - v.n_cal)]
    if (v.chosen or v.tie) and testable:
        best = np.sqrt(min(testable) / v.n)
        part = (f"; the candidates' best refit leaves {best:.2f} noise sd, above the "
                f"{EXPLAINED_SD} that would explain it" if best > EXPLAINED_SD else
                f"; the candidates' best refit leaves {best:.2f} noise sd but was not "
                "selected (its steps are in diagnosis.json)")
    else:
        part = "; no candidate's refit clears the discretization floor"
    return (f"misfit ({head}): the model is missing something none of the candidates "
            f"describes{part}")


def outcome(v: VerdictInputs, bad: bool, ranking: list[dict[str, Any]]
            ) -> tuple[str, list[str], bool | None, bool]:
    """``(verdict, suggestions, explained, ok_explained)``: the verdict in words; explained
    True where the chosen effects (or a tie) explain the misfit, False where none does (every
    ranking row is then unflagged, in place), None without a misfit."""
    n, sigma, floor = v.n, v.sigma, v.floor
    ok_expl = bool(v.chosen) and not v.tie and explained(final_chi2(v), n, sigma, floor)
    ok_tie = bool(v.tie) and explained(min(j.refit.chi2 for j in v.steps[-1]
                                           if j.refit.name in v.tie), n, sigma, floor)
    head = headline(v)
    suggestions: list[str] = []
    flag: bool | None = None
    if not bad:
        text = f"the model fits: {head}; no effect clears the discretization floor"
    elif ok_expl:
        flag = True
        text, suggestions = explained_text(v, head)
    elif ok_tie:
        flag = True
        text, suggestions = tie_text(v, head)
    else:
        flag = False
        text = unexplained_text(v, head)
        for e in ranking:
            e["flagged"] = False
    if v.chosen and ok_expl and remains(final_chi2(v), n, v.n_cal + sum(
            v.first[c].refit.dof for c in v.chosen if c in v.first)):
        text += (" (a misfit within the noise-sd bound remains significant on "
                 f"{n} values)")
        partial = partial_absorber(v)
        if partial is not None:
            text += (f"; the best further candidate, {partial.refit.name}, takes up only "
                     f"{partial.size.systematic_share:.0%} of it (a second effect that is "
                     f"present takes up at least {LATER_SHARE:.0%}): what remains may be "
                     f"the form of {' or '.join(v.chosen)} differing from the library's")
    untestable = [s.effect for s in v.scores if saturates(s.dof, n - v.n_cal)]
    if bad and untestable:  # the verdict covers the candidates these data can test, only
        text += ("; not testable on these data (with the calibrated parameters they would "
                 f"fit any {n} values): {', '.join(untestable)}")
    return text, suggestions, flag, ok_expl


def check(v: VerdictInputs) -> dict[str, float | int]:
    """The global check: chi-square, dof and p at the FE's best fit, RMS and noise (um), the
    predictive check's p-value and largest |z|, the linearised chi-square."""
    n, c = v.n, v.base_chi2
    return {"chi2": c, "dof": n - v.n_cal,
            "p_value": float(_chi2.sf(c, max(n - v.n_cal, 1))),
            "rms_um": float(np.sqrt(c / n) * v.sigma), "noise_um": v.sigma,
            "ppc_p_value": v.pc.p_value, "max_abs_z": float(np.abs(v.pc.z).max()),
            "chi2_linearised": v.mf.chi2}


def verdict(v: VerdictInputs) -> Diagnosis:
    """Ranking and verdict from the judged refits (:mod:`solderpyro.diagnose.decide`'s rules)."""
    bad = bool(remains(v.base_chi2, v.n, v.n_cal)
               or any(j.flagged for j in v.first.values()))
    ranking, failed = rank_candidates(v)
    text, suggestions, flag, ok_expl = outcome(v, bad, ranking)
    confounded = [e["effect"] for e in ranking if bad and e["identifiable"] < MIN_IDENTIFIABLE]
    if confounded:
        suggestions.append(f"not identifiable from these data (confounded with the calibrated "
                           f"parameters): {', '.join(confounded)}")
    if failed:
        suggestions.append("refits that ended above the base fit after a retry (failed, not "
                           "ranked): " + ", ".join(e["effect"] for e in failed))
    if v.faces:  # the finding comes first: the fit's quality hides it
        text = (faces_text(list(v.faces), not remains(v.base_chi2, v.n, v.n_cal)) + "; "
                + text)
        if v.freeing:
            text += "; at a fit as good or better, " + "; ".join(
                f"refitted with {c}, {', '.join(freed)} "
                f"leave{'s' if len(freed) == 1 else ''} the faces" for c, freed in v.freeing)
            suggestions += [f"recalibrate with effects=[{c}] to see the constants if it is "
                            "present" for c, _ in v.freeing if c not in v.chosen]
        else:
            suggestions.append("no candidate frees the constants: widen the prior box where "
                               "the physics allows, or suspect physics outside the library")
    diag = Diagnosis(bad, text, ranking, check(v), [v.tie] if v.tie else [], suggestions)
    diag.faces = [f.to_json() for f in v.faces]
    diag.failed = failed
    # an unexplained misfit names nothing; a tie after chosen effects keeps them when they
    # explain the misfit on their own
    keep = ok_expl or (bool(v.chosen) and flag is True
                       and explained(final_chi2(v), v.n, v.sigma, v.floor))
    diag.selected = list(v.chosen) if keep else []
    diag.explained = flag
    diag.floor = v.floor.to_json()
    diag.steps = [[{"effects": list(j.refit.effects), "chi2": j.refit.chi2,
                    "base_chi2": j.refit.base_chi2, "lr": j.refit.lr, "dof": j.refit.dof,
                    "p_value": j.p_value, "ok": j.refit.ok, "flagged": j.flagged,
                    "frees": list(j.frees), **j.size.to_json()} for j in st]
                  for st in v.steps]
    if ok_expl:
        diag.cannot_rule_out = freeing_caveats(v)
    return diag


def freeing_caveats(v: VerdictInputs) -> list[dict[str, Any]]:
    """``cannot_rule_out`` entries of the candidates that free the faces after the chosen
    effects (:func:`still_freeing`): ``effect``, ``with`` (the chosen), ``frees`` and
    ``outside`` (the constants it moves off the faces), ``chi2_rise`` against the chosen
    effects' refit, ``text``."""
    on, c = " + ".join(v.chosen), final_chi2(v)
    return [{"effect": j.refit.name, "with": list(v.chosen), "frees": list(j.frees),
             "chi2_rise": j.refit.chi2 - c, "outside": list(j.frees),
             "text": (f"{j.refit.name}, refitted with {on} on, fits the data as well (chi2 "
                      f"{j.refit.chi2 - c:+.1f}) and moves {', '.join(j.frees)} off the faces "
                      f"of the prior box where {on} alone leaves "
                      f"{'it' if len(j.frees) == 1 else 'them'}: the constants at the faces "
                      f"hold only if {j.refit.name} is absent")}
            for j in still_freeing(v)]


def where(meas: Any, fp: Fingerprints, sigma: float) -> str:
    """Where the misfit is largest: the denoised residual's peak (field data) or the largest
    standardized residual (point data), in words; ``sigma`` noise sd, um."""
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


def add_cannot_rule_out(diag: Diagnosis, found: list[dict], fx_all: Any) -> None:
    """Put ``found`` (:func:`~solderpyro.diagnose.ruleout.cannot_rule_out`) in ``diag``: each
    in words (the effect's parameter and unit from ``fx_all``, an EffectSet), and where there
    are any, in the verdict and the suggestions (``diag`` is changed in place)."""
    params = {e.name: (e.params.names[k], (e.params.units or ("",) * e.n_params)[k])
              for e in fx_all.effects if (k := e.size_index) is not None}
    for r in found:
        r["text"] = describe(r, *params.get(r["effect"], ("value", "")))
    diag.cannot_rule_out = found
    if found:
        diag.verdict += ("; but the data cannot rule out " + ", ".join(
            r["effect"] for r in found) + ", which would move " + ", ".join(
            dict.fromkeys(nm for r in found for nm in r["outside"]))
            + " outside the reported intervals (see 'What the data cannot rule out' for the "
            "intervals that admit them)")
        diag.suggestions.append(
            "recalibrate with " + " and with ".join(f"effects=[{r['effect']}]" for r in found)
            + " to see the constants' intervals if it is present: these data cannot tell")


def record_fits(diag: Diagnosis, steps: list[list[Judged]], lay: Any,
                base: dict[str, Any] | None, fe_ok: bool, names: list[str]) -> None:
    """Put in ``diag`` where each refit ended (its free parameters by name, from ``lay``, a
    :class:`~solderpyro.diagnose.refits.Layout`) and the base fit (``names``: the calibrated
    parameters'; ``fe_ok``: whether the FE check accepted the posterior); in place."""
    for recs, st in zip(diag.steps, steps, strict=True):
        for rec, j in zip(recs, st, strict=True):
            if len(j.refit.x) == len(lay.names):
                rec["x"] = lay.named(j.refit.x, j.refit.effects)
    diag.base = None if base is None else {
        "chi2": base["chi2"], "start": base["start"], "scouts": base["scouts"],
        "history": base["history"], "converged": base["converged"],
        "fe_check_ok": fe_ok, "x": {nm: float(v) for nm, v in zip(
            names[:lay.n_cal], base["x"][:lay.n_cal], strict=True)}}
