"""Writing a diagnosis: ``diagnosis.json``, ``diagnosis.md`` (and its HTML) and the figures."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from solderpyro.diagnose.costs import STAGES
from solderpyro.diagnose.decide import share_text
from solderpyro.diagnose.diagnosis import Diagnosis
from solderpyro.diagnose.fingerprint import Fingerprints
from solderpyro.diagnose.stats import PredictiveCheck

#: candidates whose fingerprints are drawn (best first)
TOP = 3


def figures(d: Path, diag: Diagnosis, meas: Any, fp: Fingerprints, sigma: float,
            dr: dict[str, np.ndarray], setup: Any) -> tuple[str, str, str]:
    """The residual, fingerprint and ranking figures in ``d``; returns their file names.

    ``sigma``: noise sd, um; ``dr``: the run's draws (``"observed"`` the predictive band).

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
    by = {s: corr[s] for s in corr}
    f3 = plots.plot_ranking([SimpleNamespace(effect=r["effect"], evidence=r["evidence"])
                             for r in diag.ranking], by, d / "diagnosis_ranking.png",
                            {r["effect"]: r["rms_after_sd"] for r in diag.ranking
                             if r.get("rms_after_sd") is not None},
                            diag.selected, [r["effect"] for r in diag.cannot_rule_out])
    return f1, f2, f3


def admitting_lines(admitting: dict[str, list[float]],
                    reported: Mapping[str, tuple[float, float]]) -> list[str]:
    """The intervals that admit what the data cannot rule out beside the ``reported`` ones
    (name -> 95 % interval, physical units), as markdown lines."""
    return ["", "The 95 % intervals that hold whether or not these effects are present (each "
            "interval stretched by what the effect would move it; `intervals_admitting.csv`):",
            "", "| constant | reported 95 % | admitting what the data cannot rule out |",
            "|---|---|---|"] + [
        f"| {nm} | {reported[nm][0]:.4g} - {reported[nm][1]:.4g} | {lo:.4g} - {hi:.4g} |"
        for nm, (lo, hi) in admitting.items()]


def write_admitting(d: Path, admitting: dict[str, list[float]],
                    reported: Mapping[str, tuple[float, float]]) -> None:
    """``intervals_admitting.csv`` in ``d``: ``parameter``, ``lo95``, ``hi95``,
    ``reported_lo95``, ``reported_hi95`` (physical units)."""
    import csv

    with (d / "intervals_admitting.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["parameter", "lo95", "hi95", "reported_lo95", "reported_hi95"])
        for nm, (lo, hi) in admitting.items():
            w.writerow([nm, f"{lo:.6g}", f"{hi:.6g}", *(f"{v:.6g}" for v in reported[nm])])


def cost_lines(timing: dict[str, dict[str, float | int]]) -> list[str]:
    """The ``timing`` table of :class:`Diagnosis` as markdown lines."""
    lines = ["## Cost per stage", "",
             "| stage | seconds | FE runs computed | FE runs reused |", "|---|---|---|---|"]
    for k, r in timing.items():
        lab = "**total**" if k == "total" else STAGES.get(k, k)
        lines.append(f"| {lab} | {float(r['seconds']):.2f} | {int(r['fe_runs'])} | "
                     f"{int(r['fe_reused'])} |")
    return lines + ["", "(reused: read back from the run store, or shared by several rows of "
                    "one batch)"]


def write(d: Path, diag: Diagnosis, pc: PredictiveCheck, sigma: float,
          figs: tuple[str, str, str],
          reported: Mapping[str, tuple[float, float]] | None = None) -> None:
    """Write ``diagnosis.json``, ``diagnosis.md`` and ``diagnosis.html`` in ``d`` (and
    ``intervals_admitting.csv`` where the data cannot rule an effect out; an earlier
    diagnosis's is removed where they can).

    Args:
        diag: the diagnosis; pc: its posterior predictive check; sigma: noise sd, um;
        figs: the figure file names (:func:`figures`); reported: the run's reported 95 %
            intervals ``{parameter: (lo, hi)}`` (summary.csv, physical units) where the
            admitting intervals were computed from them, else None.
    """
    f1, f2, f3 = figs
    (d / "intervals_admitting.csv").unlink(missing_ok=True)
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
        intro = ("The selected effects explain the misfit, yet these fit as well with them "
                 "on (FE refits): the constants their refit leaves on the box's faces assume "
                 "they are absent." if diag.selected else
                 "The model fits, yet these effects fit as well at the magnitudes named "
                 "(the constants refitted, linearised): the intervals assume they are absent.")
        lines += ["", "## What the data cannot rule out", "", intro, ""] + [
            f"- {r['text']}." for r in diag.cannot_rule_out]
        if diag.admitting:
            write_admitting(d, diag.admitting, reported or {})
            lines += admitting_lines(diag.admitting, reported or {})
    lines += ["", "## Suggestions", ""] + ([f"- {s}" for s in diag.suggestions] or ["- none"])
    if diag.timing:
        lines += [""] + cost_lines(diag.timing)
    lines += ["", "## Figures", "", f"![where the model misses the data]({f1})", "",
              f"![fingerprints of the best candidates beside the residual]({f2})", "",
              f"![evidence per candidate]({f3})", ""]
    (d / "diagnosis.md").write_text("\n".join(lines) + "\n")
    from solderpyro.reporting.report import write_html

    write_html(lines, d / "diagnosis.html", "solderpyro diagnosis")
