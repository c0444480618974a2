"""The calibration's figures, ``report.md`` and ``report.html`` (the same report as HTML).

Both are the calibration's detail; the run directory's entry page is ``index.html``
(:mod:`solderpyro.reporting.index`), which links them.
"""

from __future__ import annotations

import html
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np

from solderpyro.calibration.intervals import (
    CENTRAL,
    LIKELIHOOD,
    LOWER_FACE,
    MODEL_FORM,
    PROFILE,
    UPPER_FACE,
    WIDENED,
)
from solderpyro.config.rundir import RunDir
from solderpyro.io.measurements import Measurements
from solderpyro.reporting.plots import plot_traces, plot_validation


def _by_point(meas: Measurements) -> dict[str, np.ndarray]:
    return {p: np.flatnonzero(meas.point == p) for p in meas.points()}


def plot_model_vs_data(meas: Measurements, curves: dict[str, tuple[Any, Any, Any]],
                       title: str):
    """Measured V (error bars) against model curves, per point over time (<= 4 points) or as
    a measured-vs-model scatter (full field).

    Args:
        curves: label -> ``(mid (n_obs,), lo (n_obs,) | None, hi (n_obs,) | None)`` in um,
            row for row with ``meas``.
    Returns:
        the matplotlib Figure.
    """
    groups = _by_point(meas)
    err = np.where(np.isfinite(meas.sigma_um), meas.sigma_um, 0.0)
    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    if len(groups) <= 4:
        for k, (p, rows) in enumerate(groups.items()):
            t = meas.time_s[rows] / 60
            ax.errorbar(t, meas.value_um[rows], yerr=2 * err[rows], fmt="ks", ms=4,
                        label="measured" if k == 0 else None)
            for j, (lab, (mid, lo, hi)) in enumerate(curves.items()):
                ax.plot(t, mid[rows], "o-", color=f"C{j}", label=f"{lab} ({p})")
                if lo is not None and hi is not None:
                    ax.fill_between(t, lo[rows], hi[rows], color=f"C{j}", alpha=0.25)
            ax.annotate(p, (t[-1], meas.value_um[rows][-1]), textcoords="offset points",
                        xytext=(6, 0))
        ax.set_xlabel("time (min)")
        ax.set_ylabel("V relative to O (um)")
    else:
        for j, (lab, (mid, lo, hi)) in enumerate(curves.items()):
            yerr = None if lo is None or hi is None else np.abs(np.stack([mid - lo, hi - mid]))
            ax.errorbar(meas.value_um, mid, yerr=yerr, fmt=".", color=f"C{j}", label=lab,
                        alpha=0.6)
        lim = [float(meas.value_um.min()), float(meas.value_um.max())]
        ax.plot(lim, lim, "k--", lw=0.8)
        ax.set_xlabel("measured V (um)")
        ax.set_ylabel("model V (um)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title)
    fig.tight_layout()
    return fig


def _interval_cell(r: dict) -> str:
    """A summary row's reported 95 % interval, marked where it starts at a box face."""
    if "lo95" not in r:
        return "–"
    mark = {LOWER_FACE: " (from the lower face)", UPPER_FACE: " (to the upper face)",
            **{k: f" ({v})" for k, v in WIDENED.items()}}
    return (f"[{float(r['lo95']):.4g}, {float(r['hi95']):.4g}]"
            f"{mark.get(str(r.get('interval')), '')}")


@dataclass
class FeRunCounts:
    """Every FE run of a calibration (Liu constants, design, checks, FE-exact step): converged,
    failed, read back from the run store and computed."""

    ok: int
    failed: int
    reused: int
    computed: int


@dataclass
class ExactReport:
    """The FE-exact posterior's section (:func:`solderpyro.pipeline.fe_exact.fe_exact`; its
    record is the run's ``exact``).

    Attributes:
        posterior: the ExactPosterior (``samples (n_s, dim)``, ``result.weights()``).
        rows: its summary rows beside the surrogate's (``q2.5``, ``median``, ``q97.5``,
            ``surrogate_q2.5``, ...). surrogate_draws: ``(n, dim)`` the surrogate posterior's
            draws, physical units.
    """

    posterior: Any
    rows: list[dict]
    surrogate_draws: np.ndarray


@dataclass
class CalibrationReport:
    """What ``report.md`` and its figures show of a calibration.

    Attributes:
        run: the run directory just written (its path; its record: the sampler's lengths, the
            parameter names, the FE-exact step's record).
        meas: the measurements (n_obs rows). rows: the reported summary rows. post: the
            surrogate posterior (NUTS: traces, divergences, seconds). loo: the surrogate's
            leave-one-out check. bands: the reported predictive (``median``, ``obs_lo``,
            ``obs_hi``: ``(n_obs,)`` um). y_liu: ``(n_obs,)`` the model with the literature
            constants, um. fe_runs: :class:`FeRunCounts`. problems: warnings. notes: more
            lines for the report's opening list (e.g. the FE check). exact: the FE-exact
            section, or None.
    """

    run: RunDir
    meas: Measurements
    rows: list[dict]
    post: Any
    loo: Any
    bands: Any
    y_liu: np.ndarray
    fe_runs: FeRunCounts
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    exact: ExactReport | None = None


def write(rep: CalibrationReport) -> Path:
    """Write the figures, ``report.md`` and ``report.html`` into ``rep.run.path``; returns the
    path of ``report.md``."""
    out, meas, post, loo, bands = rep.run.path, rep.meas, rep.post, rep.loo, rep.bands
    rows, doe, nuts = rep.rows, rep.fe_runs, rep.run.info.sampler

    def save(fig, name: str) -> str:
        fig.savefig(out / name, dpi=120)
        plt.close(fig)
        return name

    liu = np.asarray(rep.y_liu)
    f8 = save(plot_model_vs_data(meas, {"Liu 2008 (seed Table IV)": (liu, None, None)},
                                 "Model with literature constants vs measurement (seed Fig. 8)"),
              "fig8_literature.png")
    f9 = save(plot_traces(post), "fig9_posterior.png")
    f10 = save(plot_model_vs_data(meas, {"posterior predictive": (
        bands.median.numpy(), bands.obs_lo.numpy(), bands.obs_hi.numpy())},
        "Posterior predictive, 95 % band of a new measurement (seed Fig. 10)"),
        "fig10_predictive.png")
    fl = save(plot_validation(loo, "surrogate leave-one-out"), "surrogate_loo.png")
    rmse_liu = float(np.sqrt(np.mean((liu - meas.value_um) ** 2)))
    rmse_post = float(np.sqrt(np.mean((bands.median.numpy() - meas.value_um) ** 2)))
    inside = float(np.mean((bands.obs_lo.numpy() <= meas.value_um)
                           & (meas.value_um <= bands.obs_hi.numpy())))
    lines = ["# solderpyro calibration report", "",
             "The run directory's entry page is `index.html` (verdicts, figures, diagnosis, "
             "comparison, every file); this is the calibration's detail.", "",
             f"- data: {len(meas)} values at {len(meas.points())} point(s) x "
             f"{len(meas.times())} time(s)",
             f"- FE runs: {doe.ok} converged, {doe.failed} failed "
             f"({doe.reused} reused from the run store, {doe.computed} computed)",
             f"- NUTS: {sampled_text(post, nuts)}; divergences per chain {post.divergences}; "
             f"{post.seconds:.0f} s",
             f"- RMSE model vs data: Liu 2008 constants {rmse_liu:.3g} um -> posterior "
             f"median {rmse_post:.3g} um; {inside:.0%} of the measurements inside the 95 % "
             "predictive band", *[f"- {n}" for n in rep.notes], "",
             "## Posterior (seed Table V layout)", "",
             "| parameter | 2.5 % | median | mean | 97.5 % | 95 % interval | R-hat | ESS |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['parameter']} | {float(r['q2.5']):.4g} | {float(r['median']):.4g} "
                     f"| {float(r['mean']):.4g} | {float(r['q97.5']):.4g} | "
                     f"{_interval_cell(r)} | "
                     f"{_num(r['r_hat'], '.3f')} | {float(r['ess_bulk']):.0f} |")
    faces = [r for r in rows if r.get("interval", CENTRAL) in (LOWER_FACE, UPPER_FACE)]
    if faces:
        lines += ["", "The 95 % interval is the central one (2.5 % to 97.5 %) unless the "
                  "posterior piles against a face of the prior box (its densest half reaches "
                  "the face): then it starts at the face, where the density is highest, and "
                  "holds 95 % as well ("
                  + "; ".join(f"{r['parameter']} from its {r['interval']}" for r in faces)
                  + "). A face that is a physical limit is a result; one that is only the "
                  "box's edge says the box may be too narrow."]
    ridge = [r["parameter"] for r in rows if r.get("interval") == LIKELIHOOD]
    if ridge:
        lines += ["", "The 95 % intervals of " + ", ".join(ridge) + " are widened to every "
                  "posterior draw the likelihood does not reject (its log-likelihood within "
                  "1.92 of the best draw's, the 95 % profile-likelihood bound): along a ridge "
                  "the data leave open, the prior box's volume, not the data, ends the "
                  "credible interval. The columns 2.5 % to 97.5 % are the posterior's own."]
    widened = [r["parameter"] for r in rows if r.get("interval") == MODEL_FORM]
    if widened:
        lines += ["", "A misfit remains at the FE's best fit, so the 95 % intervals of "
                  + ", ".join(widened) + " are widened for the model-form error: each is the "
                  "hull of the posterior's own interval and the one a Kennedy-O'Hagan "
                  "discrepancy over (time, x, y), fitted to the residual, leaves "
                  "(model_form.json). The columns 2.5 % to 97.5 % are the posterior's own."]
    profiled = [r["parameter"] for r in rows if r.get("interval") == PROFILE]
    if profiled and (rep.run.info.exact or {}).get("reliable"):
        lines += ["", "The data leave the form of an effect open (one of its form parameters "
                  "is weakly identified), and a flat prior over that form decides the "
                  "posterior's interval of what the effect acts with, so the 95 % intervals "
                  "of " + ", ".join(profiled) + " are widened to hold the FE's own "
                  "profile-likelihood intervals (profile_ci.csv), every other parameter, the "
                  "form's included, refitted: each is the hull of the FE-exact posterior's "
                  "interval and the profile's. The columns 2.5 % to 97.5 % are the "
                  "posterior's own."]
    elif profiled:
        lines += ["", "The FE-exact posterior's weights are not reliable, so the 95 % intervals "
                  "of " + ", ".join(profiled) + " are widened to hold the FE's own "
                  "profile-likelihood intervals (profile_ci.csv): each is the hull of the "
                  "surrogate posterior's interval and the profile's. The columns 2.5 % to "
                  "97.5 % are the surrogate posterior's own."]
    warn = list(rep.problems)
    warn += [f"R-hat of {r['parameter']} is {float(r['r_hat']):.3f} (> 1.01): chains disagree"
             for r in rows if float(r["r_hat"]) > 1.01]
    if sum(post.divergences):
        warn.append(f"{sum(post.divergences)} divergent transitions")
    lines += ["", "## Warnings", ""] + ([f"- {w}" for w in warn] or ["- none"])
    ex_info = rep.run.info.exact
    if rep.exact is not None and rep.exact.rows and ex_info:
        lines += _exact_section(rep.exact, ex_info, rep.run.info.parameters, save,
                                _truth(meas), rep.run.info.posterior)
    lines += ["", "## Figures", ""]
    if (out / "design.png").exists():  # the adaptive design's rounds (solderpyro.design)
        lines += ["![adaptive design: marginals per round, stopping rule, where the runs went]"
                  "(design.png)", ""]
    lines += [f"![literature constants vs data]({f8})", "",
              f"![the surrogate posterior's NUTS traces and marginals]({f9})", "",
              "The traces are the NUTS chains of the surrogate posterior, whichever result "
              "summary.csv reports (the trust line says which).", "",
              f"![posterior predictive]({f10})", "",
              f"![surrogate validation]({fl})", "",
              f"Surrogate leave-one-out: 95 % coverage {loo.coverage95:.0%}, RMSE "
              f"{loo.rmse_rel:.3f} of the output spread.", "",
              "Files: `summary.csv` (parameter, q2.5, median, mean, q97.5), `posterior.nc` "
              "(ArviZ InferenceData)."]
    p = out / "report.md"
    p.write_text("\n".join(lines) + "\n")
    write_html(lines, out / "report.html", "solderpyro calibration report")
    return p


def sampled_text(post: Any, settings: dict[str, int]) -> str:
    """What the final NUTS run kept, read from its draws: ``"4 chains x 2250 draws kept after
    500 warm-up (1500 asked; the chains ran on for 750 more)"``.

    Args:
        post: the posterior; ``post.samples``: site -> ``(chain, draw, ...)``.
        settings: the run's ``chains``, ``draws`` and ``warmup`` as asked
            (:attr:`~solderpyro.config.rundir.RunInfo.sampler`; keys may be missing).
    Returns:
        one line of the report.
    """
    n_chain, n_draw = (int(n) for n in next(iter(post.samples.values())).shape[:2])
    txt = f"{n_chain} chains x {n_draw} draws kept"
    if "warmup" in settings:
        txt += f" after {settings['warmup']} warm-up"
    asked = settings.get("draws")
    if asked is not None and asked != n_draw:
        more = n_draw - asked
        txt += (f" ({asked} asked; the chains ran on for {more} more)" if more > 0
                else f" ({asked} asked)")
    return txt


def _num(v: Any, fmt: str) -> str:
    """``v`` formatted, or an en dash when it is NaN (an R-hat of importance samples)."""
    return "–" if not np.isfinite(float(v)) else format(float(v), fmt)


def _truth(meas: Measurements) -> dict[str, float] | None:
    """The true parameters a synthetic dataset's metadata state (``truth`` and
    ``hidden_values``, as :func:`solderpyro.diagnose.hidden.make_dataset` writes), or None."""
    import ast

    out: dict[str, float] = {}
    for key in ("truth", "hidden_values"):
        try:
            out.update(ast.literal_eval(meas.meta.get(key, "{}")))
        except (ValueError, SyntaxError):
            return None
    return out or None


def _exact_section(exact: ExactReport, info: dict[str, Any], names: list[str], save: Any,
                   truth: dict[str, float] | None = None, reported: str = "surrogate"
                   ) -> list[str]:
    """The report's lines on the FE-exact posterior (``info``: the run's FE-exact record;
    ``names``: the parameters), and its figure (``save(fig, name)``); ``truth``: true values
    drawn in the figure (synthetic data); ``reported``: the kind of summary.csv
    (:attr:`~solderpyro.config.rundir.RunInfo.posterior`)."""
    from solderpyro.reporting.plots import plot_exact

    ex, rows = exact.posterior, exact.rows
    prof = info.get("profile")
    fig = save(plot_exact(list(names), ex.samples, ex.result.weights(), exact.surrogate_draws,
                          None if prof is None else (prof["parameter"], prof["values"],
                                                     prof["chi2"]), truth),
               "exact_posterior.png")
    how = (f"{info['fe_runs']} FE runs: the FE's best fit (chi2 {info['best_fit']['chi2']:.1f})"
           + (f", the chi-square profiled along {prof['parameter']} at {len(prof['values'])} "
              "values" if prof else "")
           + f", then {len(info['rounds'])} rounds of adaptive importance sampling "
           f"({info['samples']} samples in {info['coordinates']} coordinates, FE in the "
           "likelihood, no surrogate).")
    verdict = (f"Kish ESS {info['ess']:.0f}, Pareto k-hat {info['khat']:.2f}: "
               + ("**reliable; `summary.csv` is this posterior** (the surrogate's is in "
                  "`summary_surrogate.csv`)." if info["reliable"] else
                  "**not reliable** (k-hat > 0.7 or ESS < 50): `summary.csv` is "
                  + ("the FE's own best fit" if reported == "fe-best-fit" else
                     "the surrogate's")
                  + "; run more rounds (`--exact-rounds`) or more runs per round."))
    lines = ["", "## FE-exact posterior", "", how, "", verdict, "",
             "| parameter | FE-exact 2.5 / 50 / 97.5 % | surrogate 2.5 / 50 / 97.5 % |",
             "|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['parameter']} | {r['q2.5']:.4g} / {r['median']:.4g} / "
                     f"{r['q97.5']:.4g} | {r['surrogate_q2.5']:.4g} / "
                     f"{r['surrogate_median']:.4g} / {r['surrogate_q97.5']:.4g} |")
    lines += ["", f"![FE-exact vs surrogate posterior]({fig})"]
    pci = info.get("profile_ci")
    if pci:
        by = {r["parameter"]: r for r in rows}
        lines += ["", "### Profile-likelihood 95 % confidence intervals (through the FE)", "",
                  "Each parameter held on a grid, the others refitted by Levenberg-Marquardt "
                  "through the FE; the interval is where the profile chi-square stays within "
                  f"{pci[0]['delta']:.2f} of its minimum (Wilks, 1 dof). It does not depend on "
                  "the prior box or on how wide the ridge of the other parameters is, unlike "
                  "the posterior's interval; an end at the box's bound means the data do not "
                  "bound the parameter there.", "",
                  "| parameter | profile 95 % CI | posterior 95 % interval | note |",
                  "|---|---|---|---|"]
        for p in pci:
            r = by.get(p["parameter"], {})
            note = ", ".join(n for n, hit in (("reaches the lower bound", p["at_lower_bound"]),
                                              ("reaches the upper bound", p["at_upper_bound"]),
                                              ("profile truncated", p["truncated"])) if hit)
            lines.append(f"| {p['parameter']} | [{p['lower']:.4g}, {p['upper']:.4g}] | "
                         + (f"[{r['q2.5']:.4g}, {r['q97.5']:.4g}]" if r else "–")
                         + f" | {note or '–'} |")
    ident = info.get("identifiability")
    if ident:
        adv = ident["advice"]
        lines += ["", "### Identifiability: what the data leave open", "",
                  adv[:1].upper() + adv[1:]]
        if ident.get("options"):
            lines += ["", "| measurement to add | new values | max difference (um) | at t (s), "
                      "point | expected chi-square between the two ends |", "|---|---|---|---|---|"]
            for o in ident["options"]:
                lines.append(f"| {o['measurement']} | {o['n_new']} | {o['max_diff_um']:.3g} | "
                             f"{o['time_s']:g}, {o['point']} | {o['chi2_apart']:.0f} |")
    return lines


def _inline(text: str) -> str:
    """Markdown inline code and bold -> HTML (text is escaped first)."""
    t = html.escape(text, quote=False)
    t = re.sub(r"`([^`]+)`", r"<code>\1</code>", t)
    return re.sub(r"\*\*([^*]+)\*\*", r"<b>\1</b>", t)


def markdown_to_html(lines: list[str], title: str) -> str:
    """The report's Markdown subset (headings, lists, tables, images, paragraphs) as a
    self-contained HTML page; figures stay beside it as relative links.

    Args:
        lines: Markdown lines as written to ``report.md``.
        title: the page title.
    Returns:
        the HTML text.
    """
    body: list[str] = []
    i = 0
    while i < len(lines):
        ln = lines[i]
        if ln.startswith("#"):
            k = len(ln) - len(ln.lstrip("#"))
            body.append(f"<h{k}>{_inline(ln[k:].strip())}</h{k}>")
        elif ln.startswith("|"):
            rows = []
            while i < len(lines) and lines[i].startswith("|"):
                rows.append([c.strip() for c in lines[i].strip().strip("|").split("|")])
                i += 1
            head, rest = rows[0], [r for r in rows[1:] if not set("".join(r)) <= set("-: ")]
            body.append("<table><tr>" + "".join(f"<th>{_inline(c)}</th>" for c in head)
                        + "</tr>" + "".join("<tr>" + "".join(f"<td>{_inline(c)}</td>"
                                                             for c in r) + "</tr>"
                                            for r in rest) + "</table>")
            continue
        elif ln.startswith("- "):
            items = []
            while i < len(lines) and lines[i].startswith("- "):
                items.append(f"<li>{_inline(lines[i][2:])}</li>")
                i += 1
            body.append("<ul>" + "".join(items) + "</ul>")
            continue
        elif (m := re.fullmatch(r"!\[([^\]]*)\]\(([^)]+)\)", ln.strip())):
            body.append(f'<figure><img src="{html.escape(m.group(2))}" '
                        f'alt="{html.escape(m.group(1))}"><figcaption>'
                        f"{html.escape(m.group(1))}</figcaption></figure>")
        elif ln.strip():
            body.append(f"<p>{_inline(ln)}</p>")
        i += 1
    style = ("body{font-family:sans-serif;max-width:60em;margin:2em auto;padding:0 1em}"
             "table{border-collapse:collapse}td,th{border:1px solid #bbb;padding:.2em .6em;"
             "text-align:right}th{background:#eee}img{max-width:100%}"
             "figcaption{color:#555;font-size:.9em}")
    return (f"<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><title>{html.escape(title)}"
            f"</title><style>{style}</style></head><body>\n" + "\n".join(body)
            + "\n</body></html>\n")


def write_html(lines: list[str], path: Path, title: str) -> Path:
    """Write :func:`markdown_to_html` of ``lines`` to ``path``; returns the path."""
    path.write_text(markdown_to_html(lines, title), encoding="utf-8")
    return path
