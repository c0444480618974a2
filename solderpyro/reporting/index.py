"""``index.html``: the entry page of a run directory, the one page to open in a browser.

Verdict first (the diagnosis's, the comparison's, the calibration's trust line), then the
figures that show where the model misses the data, the tables, the warnings, and links to
everything else the directory holds: the full reports (``report.html`` and ``report.md``,
``diagnosis.html``, ``comparison.md``), the CSVs, ``posterior.nc``, the JSON records and any
other file. It is rebuilt from whatever the directory holds by ``calibrate``, ``diagnose``,
``compare`` and ``koh`` (which adds its own verdict and warnings), so it is always the latest
state. Self-contained: inline style, images beside it as relative links, nothing fetched
from a network.
"""

from __future__ import annotations

import csv
import html
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from solderpyro.config.rundir import (
    COMPARISON_JSON,
    DIAGNOSIS_JSON,
    RUN_JSON,
    RunInfo,
    read_json,
    try_read,
)

#: figures, in the order a reader needs them: where it fails, which effect, the fall, the rest
FIGURES = (
    ("diagnosis_residuals.png", "Where the model misses the data: the residual and its "
     "denoised part (maps per measured time; point data: against time with the predictive "
     "band)"),
    ("diagnosis_fingerprints.png", "The best candidates' fingerprints beside the residual, and "
     "the residual left after adding each"),
    ("comparison.png", "Before / after adding the effect: residuals and marginals"),
    ("diagnosis_ranking.png", "Evidence per candidate effect"),
    ("fig10_predictive.png", "Posterior predictive against the data"),
    ("design.png", "Adaptive design: marginals per round, where the FE runs went"),
    ("fig9_posterior.png", "Posterior traces and marginals"),
    ("exact_posterior.png", "FE-exact posterior against the surrogate's"),
    ("fig8_literature.png", "Literature constants against the data"),
    ("surrogate_loo.png", "Surrogate leave-one-out check"),
    ("traces.png", "Posterior traces (koh)"),
)
#: the files a run directory may hold, each with what it is, in the order the page lists them
LINKS = (("report.html", "calibration report"), ("report.md", "calibration report (Markdown)"),
         ("diagnosis.html", "diagnosis"), ("diagnosis.md", "diagnosis (Markdown)"),
         ("comparison.md", "comparison (Markdown)"),
         ("summary.csv", "posterior summary, the reported posterior (CSV)"),
         ("summary_surrogate.csv", "the surrogate posterior's summary (CSV)"),
         ("exact_posterior.csv", "FE-exact posterior beside the surrogate's (CSV)"),
         ("profile_ci.csv", "profile-likelihood intervals (CSV)"),
         ("design.csv", "the adaptive design's FE runs (CSV)"),
         ("data.csv", "the measurements (CSV)"),
         ("posterior.nc", "posterior, predictive and log-likelihood (ArviZ NetCDF)"),
         ("draws.npz", "the reported posterior's draws and predictive (NumPy)"),
         ("exact_samples.npz", "FE-exact importance samples (NumPy)"),
         ("diagnosis.json", "diagnosis (JSON)"), ("comparison.json", "comparison (JSON)"),
         ("design_rounds.json", "the adaptive design's rounds (JSON)"),
         (RUN_JSON, "run settings and record (JSON)"),
         ("sampler_state.npz", "the sampler's adapted state, for --warm-from (NumPy)"),
         ("discretization_correction.npz", "the discretization correction used (NumPy)"),
         ("proposed.csv", "the next simulator runs to make (koh --propose; CSV)"),
         ("pending.csv", "proposed runs not yet in the run table (koh --propose; CSV)"))
STYLE = ("body{font-family:sans-serif;max-width:100em;margin:1.5em auto;padding:0 1em;"
         "color:#222}.verdict{border-left:.5em solid #888;padding:.6em 1em;margin:1em 0;"
         "background:#f4f4f4;font-size:1.1em}.bad{border-color:#c0392b;background:#fdecea}"
         ".good{border-color:#27ae60;background:#eafaf1}table{border-collapse:collapse;"
         "margin:.5em 0}td,th{border:1px solid #bbb;padding:.2em .6em;text-align:right}"
         "th{background:#eee}td:first-child{text-align:left}img{max-width:100%;"
         "border:1px solid #ddd}figcaption{color:#555;font-size:.9em;margin-bottom:1.5em}")


def _e(s: Any) -> str:
    return html.escape(str(s), quote=True)


def _table(head: list[str], rows: list[list[Any]]) -> str:
    return ("<table><tr>" + "".join(f"<th>{_e(h)}</th>" for h in head) + "</tr>"
            + "".join("<tr>" + "".join(f"<td>{_e(c)}</td>" for c in r) + "</tr>"
                      for r in rows) + "</table>")


def _num(v: Any, fmt: str = ".4g") -> str:
    try:
        return format(float(v), fmt)
    except (TypeError, ValueError):
        return str(v)


def _verdicts(d: Path, diag: dict | None, cmp: dict | None, run: RunInfo | None,
              given: bool = False) -> list[tuple[str, str]]:
    """``(css class, html)`` of each verdict, most telling first (none for an empty directory
    whose verdict is ``given``)."""
    out: list[tuple[str, str]] = []
    if diag is not None:
        by = {r["effect"]: r for r in diag.get("ranking", [])}
        sel = [e for e in diag.get("selected", []) if e in by]
        extra = ""
        if sel and diag.get("misfit") and diag.get("explained"):
            # only what the diagnosis selected (an unexplained misfit names no effect)
            extra = " Add: " + ", ".join(
                f"<b>{_e(e)}</b> (its fingerprint's shape correlation with the residual r = "
                f"{_num(by[e].get('fingerprint_correlation'), '.2f')})" for e in sel) + "."
        out.append(("bad" if diag.get("misfit") else "good",
                     f"<b>Diagnosis:</b> {_e(diag['verdict'])}.{extra}"))
    if cmp is not None:
        b, a = cmp["before"], cmp["after"]
        loo = ("PSIS-LOO ELPD" if a.get("elpd_method", "").startswith("psis") else
               "log predictive density")
        diff = (f" ({_num(cmp['elpd_gain'], '.1f')} &plusmn; "
                f"{_num(cmp.get('elpd_gain_se', float('nan')), '.1f')} nats)")
        added = ", ".join(a.get("effects", [])) or "nothing"
        good = cmp["elpd_gain"] > 0 and a["rms_um"] < b["rms_um"]
        out.append(("good" if good else "bad",
                     f"<b>Compared with the run before</b> (effects on now: {_e(added)}): RMS "
                     f"residual {_num(b['rms_um'])} &rarr; {_num(a['rms_um'])} um; {loo} "
                     f"{_num(b['elpd'], '.1f')} &rarr; {_num(a['elpd'], '.1f')}{diff}."))
    if run is not None:
        chk = run.checks.fe_check
        ok = chk.get("ok", True)
        txt = f"<b>Calibration:</b> trust {_e(run.trust)}."
        if chk:
            txt += (f" FE check: best RMS residual {_num(chk.get('rms_um'))} um = "
                    f"{_num(chk.get('rms_over_sigma'), '.2f')} noise sd.")
        out.append(("good" if ok and diag is None else "", txt))
    if not out and not given:
        out.append(("", f"{_e(d)} holds no solderpyro run yet."))
    return out


def _warnings(d: Path, diag: dict | None, cmp: dict | None) -> list[str]:
    out: list[str] = []
    rep = d / "report.md"
    if rep.is_file():
        on = False
        for ln in rep.read_text().splitlines():
            if ln.startswith("## "):
                on = ln.strip() == "## Warnings"
            elif on and ln.startswith("- ") and ln[2:].strip() != "none":
                out.append(ln[2:].replace("**", "").replace("`", ""))
    if diag is not None:
        out += [f"diagnosis: {s}" for s in diag.get("suggestions", [])]
    if cmp is not None:
        out += [f"comparison: {w}" for w in cmp.get("warnings", [])]
    return out


def _summary_rows(d: Path) -> list[list[str]]:
    from solderpyro.calibration.intervals import CENTRAL, WIDENED, reported_interval

    p = d / "summary.csv"
    if not p.is_file():
        return []
    out = []
    with p.open(newline="") as fh:
        for r in csv.DictReader(fh):
            lo, hi = reported_interval(r)  # the central quantiles in runs made before it
            face = r.get("interval") not in (None, "", CENTRAL)
            kind = r.get("interval")
            note = (f" (95 % {WIDENED[kind]})" if kind in WIDENED
                    else f" (95 % from its {kind})" if face else "")
            out.append([r["parameter"] + note,
                        _num(lo), _num(r["median"]), _num(hi),
                        _num(r.get("r_hat", "nan"), ".3f"), _num(r.get("ess_bulk", "nan"), ".0f")])
    return out


def write_index(run_dir: str | Path, verdict: tuple[str, str] | None = None,
                warnings: Sequence[str] = ()) -> Path:
    """Write ``run_dir/index.html`` from what the directory holds (module docstring).

    Args:
        run_dir: a run directory (calibration, diagnosis, comparison, ``koh``).
        verdict: ``(css class "good" | "bad" | "", plain text)``, a verdict shown first (that
            of a directory without a run record: ``koh``'s).
        warnings: plain-text warnings listed before those the directory's reports hold.
    Returns:
        the path of ``index.html``.
    """
    d = Path(run_dir)
    rd = try_read(d)
    diag, cmp = read_json(d / DIAGNOSIS_JSON), read_json(d / COMPARISON_JSON)
    run = rd.info if rd is not None else None
    body = [f"<h1>solderpyro run: {_e(d.name)}</h1>"]
    lead = [(verdict[0], _e(verdict[1]))] if verdict is not None else []
    body += [f'<div class="verdict {c}">{t}</div>'
             for c, t in lead + _verdicts(d, diag, cmp, run, bool(lead))]
    figs = [(f, cap) for f, cap in FIGURES if (d / f).is_file()]
    if figs:
        body.append("<h2>Figures</h2>")
        body += [f'<figure><img src="{_e(f)}" alt="{_e(cap)}"><figcaption>{_e(cap)} '
                 f'(<a href="{_e(f)}">{_e(f)}</a>)</figcaption></figure>' for f, cap in figs]
    if diag is not None and diag.get("ranking"):
        from solderpyro.diagnose.decide import share_text

        body.append("<h2>Candidate effects (best first)</h2>")
        body.append(_table(["effect", "FE refit", "likelihood ratio (or screen)",
                            "RMS after (noise sd)", "systematic misfit removed",
                            "fingerprint r", "flagged"],
                           [[r["effect"], _e(str(r.get("refit", ""))),
                             _num(r["statistic"], ".1f"),
                             _num(r.get("rms_after_sd", float("nan")), ".2f"),
                             share_text(r.get("explained_share")),
                             _num(r.get("fingerprint_correlation"), ".2f"),
                             "yes" if r["flagged"] else ""]
                            for r in diag["ranking"] + diag.get("failed", [])]))
    rows = _summary_rows(d)
    if rows:
        head = ["parameter", "95 % from", "median", "95 % to", "R-hat", "ESS"]
        if all(r[-2:] == ["nan", "nan"] for r in rows):  # a summary without them (koh's)
            head, rows = head[:-2], [r[:-2] for r in rows]
        body.append("<h2>Posterior</h2>")
        body.append(_table(head, rows))
    warn = [*warnings, *_warnings(d, diag, cmp)]
    body.append("<h2>Warnings</h2>")
    body.append("<ul>" + "".join(f"<li>{_e(w)}</li>" for w in warn) + "</ul>" if warn
                else "<p>none</p>")
    links = [(f, lab) for f, lab in LINKS if (d / f).is_file()]
    known = {f for f, _ in LINKS} | {f for f, _ in FIGURES} | {"index.html"}
    links += [(p.name, "figure" if p.suffix == ".png" else "file")
              for p in sorted(d.iterdir())
              if p.is_file() and p.name not in known and not p.name.startswith((".", "_"))]
    if cmp is not None and cmp.get("before_dir"):
        rel = os.path.relpath(Path(cmp["before_dir"]) / "index.html", d)
        links.append((rel, "the run before (its index)"))
    if cmp is not None and cmp.get("after_dir") and Path(cmp["after_dir"]).resolve() \
            != d.resolve():
        rel = os.path.relpath(Path(cmp["after_dir"]) / "index.html", d)
        links.append((rel, "the run after (its index)"))
    body.append("<h2>Reports and files</h2><ul>" + "".join(
        f'<li><a href="{_e(f)}">{_e(lab)}</a> ({_e(f)})</li>' for f, lab in links) + "</ul>")
    page = (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>solderpyro: '
            f"{_e(d.name)}</title><style>{STYLE}</style></head><body>\n" + "\n".join(body)
            + "\n</body></html>\n")
    p = d / "index.html"
    p.write_text(page, encoding="utf-8")
    return p
