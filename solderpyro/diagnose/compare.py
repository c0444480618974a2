"""Before/after: how much an added effect improves the fit (``solderpyro compare``).

Reads two run directories of ``solderpyro calibrate`` on the same data (e.g. without and with
``effects=[NAME]``) and reports, from their posterior predictive draws:

- RMS residual of the predictive median against the data, um;
- the posterior predictive misfit statistic (mean of ``sum((y - mu)^2 / sigma^2)``) and its
  p-value (:func:`~solderpyro.diagnose.stats.predictive_check`);
- the expected log predictive density of each observation left out, ELPD, by ArviZ's PSIS-LOO
  (``az.loo``, nats, higher is better, with its standard error, the effective number of
  parameters ``p_loo`` and the Pareto k-hat of every observation: above 0.7 the estimate of
  that observation is not reliable, and the comparison says so) from the ``log_likelihood``
  group of ``posterior.nc`` (the pointwise ``log N(y_i; m_i(theta), v_i(theta) + sigma^2)``
  with the surrogate's mean and code variance at each posterior draw), and the difference of
  the two with its standard error (``az.compare``). A run written before posterior.nc had
  that group falls back to the in-sample Gaussian approximation ``sum_i log N(y_i; m_i, v_i)``
  of the predictive draws (``elpd_method`` says which);
- the shift of every common parameter's posterior (median and 95 % interval);
- ``comparison.png``: the residual of each run's predictive median (full field: maps per time,
  each GP-denoised, one colour scale for both; points: against time with the
  predictive band) and the marginals before and after, on one figure.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from solderpyro.config.rundir import POSTERIOR_NC, RUN_FILES, RunDir
from solderpyro.diagnose.stats import predictive_check


def _logpdf(y: np.ndarray, mu: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    return -0.5 * ((y - mu) / sigma) ** 2 - np.log(sigma) - 0.5 * np.log(2 * np.pi)


def load_idata(run_dir: str | Path) -> Any:
    """``posterior.nc`` of a run as ArviZ InferenceData, or None when it has no
    ``log_likelihood`` group (a run of an earlier version)."""
    from solderpyro.calibration.mcmc import import_arviz as _arviz

    p = Path(run_dir) / POSTERIOR_NC
    if not p.is_file():
        return None
    idata = _arviz().from_netcdf(str(p))
    return idata if "log_likelihood" in idata.groups() else None


def psis_loo(idata: Any) -> tuple[Any, list[str]]:
    """ArviZ's PSIS-LOO of ``idata`` and its warnings (the Pareto k-hat ones among them)."""
    import warnings

    from solderpyro.calibration.mcmc import import_arviz as _arviz

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        loo = _arviz().loo(idata, pointwise=True)
    msgs = list(dict.fromkeys(str(w.message) for w in caught
                              if not issubclass(w.category, FutureWarning)))
    return loo, msgs


def measured(run_dir: str | Path) -> np.ndarray:
    """``(n_obs,)`` um: the measured values a run was calibrated on. A run whose data had the
    FE's discretization error taken off (``discretization_correction.npz``, see
    :meth:`~solderpyro.pipeline.problem.ObservedData.corrected`) keeps the corrected ones in
    ``draws.npz``; its residuals and log densities are those of the measured data under the
    corrected model, so two runs with different corrections compare as they are."""
    run = RunDir.read(run_dir, RUN_FILES)
    y = run.draws().y_obs
    corr = run.correction()
    if corr is not None:
        y = y + corr["delta"]
    return y


def run_metrics(run_dir: str | Path) -> dict[str, Any]:
    """Fit metrics of one calibration run (see the module docstring).

    Returns:
        dict with ``rms_um``, ``misfit_mean``, ``misfit_p``, ``elpd``, ``elpd_se``,
        ``elpd_method`` (``"psis-loo"`` or ``"gaussian"``), ``p_loo``, ``pareto_k_bad``
        (observations with k-hat > 0.7), ``pareto_k_max``, ``warnings``, ``n``, ``effects``
        and ``summary`` (parameter -> row of summary.csv).
    """
    run = RunDir.read(run_dir, RUN_FILES)
    d, info, dr = run.path, run.info, run.draws()
    y, mu, sig, obs = dr.y_obs, dr.process, dr.sigma_pred, dr.observed
    pc = predictive_check(y, mu, sig)
    summ = run.summary()
    out: dict[str, Any] = {
        "rms_um": float(np.sqrt(np.mean((np.median(mu, 0) - y) ** 2))),
        "misfit_mean": float(pc.t_obs.mean()), "misfit_p": pc.p_value, "n": int(len(y)),
        "effects": list(info.effects), "summary": summ, "warnings": []}
    # posterior.nc holds the surrogate's NUTS posterior; where the run reports another one (the
    # FE's own best fit of a model that misfits, whose surrogate posterior sits in an island
    # only the surrogate likes, or the FE-exact one) its PSIS-LOO is not the reported result's
    # (it came out nan on such a base run): the reported predictive in draws.npz is used below
    kind = info.posterior
    idata = load_idata(d) if kind == "surrogate" else None
    if idata is not None:
        loo, msgs = psis_loo(idata)
        k = np.asarray(loo.pareto_k)
        out.update(elpd=float(loo.elpd_loo), elpd_se=float(loo.se), p_loo=float(loo.p_loo),
                   elpd_method="psis-loo", pareto_k_max=float(k.max()),
                   pareto_k_bad=int((k > 0.7).sum()),
                   warnings=[f"{d.name}: ArviZ: {m}" for m in msgs])
        if out["pareto_k_bad"]:
            out["warnings"].append(
                f"{d.name}: {out['pareto_k_bad']} of {len(k)} observations have Pareto k-hat "
                f"> 0.7 (largest {k.max():.2f}): PSIS-LOO is not reliable for them")
    else:
        elpd_i = _logpdf(y, obs.mean(0), obs.std(0, ddof=1))
        out.update(elpd=float(elpd_i.sum()), elpd_se=float(np.sqrt(len(y) * elpd_i.var())),
                   elpd_method="gaussian", p_loo=float("nan"), pareto_k_max=float("nan"),
                   pareto_k_bad=0)
        out["warnings"].append(
            f"{d.name}: the reported posterior is the {kind} one (posterior.nc holds the "
            "surrogate's): ELPD is the in-sample Gaussian approximation of its predictive"
            if kind != "surrogate" else
            f"{d.name}: posterior.nc has no log_likelihood group (an earlier version): ELPD is "
            "the in-sample Gaussian approximation")
    return out


def compare(before: str | Path, after: str | Path, out: str | Path | None = None
            ) -> dict[str, Any]:
    """Compare two runs on the same data; writes ``comparison.json`` and ``comparison.md`` into
    ``out`` (default: ``after``).

    Raises:
        ValueError: when the two runs were calibrated on different data.
    """
    a, b = run_metrics(before), run_metrics(after)
    ya, yb = measured(before), measured(after)
    if ya.shape != yb.shape or not np.allclose(ya, yb):
        raise ValueError(f"{before} and {after} were calibrated on different data")
    shifts = []
    for p in a["summary"]:
        if p in b["summary"]:
            ra, rb = a["summary"][p], b["summary"][p]
            shifts.append({"parameter": p, "before": [ra["q2.5"], ra["median"], ra["q97.5"]],
                           "after": [rb["q2.5"], rb["median"], rb["q97.5"]]})
    added = [p for p in b["summary"] if p not in a["summary"]]
    gain_se = float(np.sqrt(a["elpd_se"] ** 2 + b["elpd_se"] ** 2))
    if a["elpd_method"] == b["elpd_method"] == "psis-loo":
        gain_se = _diff_se(before, after)
    res = {"before": {k: v for k, v in a.items() if k != "summary"},
           "after": {k: v for k, v in b.items() if k != "summary"},
           "elpd_gain": b["elpd"] - a["elpd"], "elpd_gain_se": gain_se, "shifts": shifts,
           "added": {p: b["summary"][p] for p in added},
           "warnings": a["warnings"] + b["warnings"],
           "before_dir": str(Path(before).resolve()), "after_dir": str(Path(after).resolve())}
    o = Path(out or after)
    o.mkdir(parents=True, exist_ok=True)
    try:
        res["figure"] = plot_comparison(before, after, o / "comparison.png")
    except Exception as err:  # a figure never costs the comparison's numbers
        res["warnings"].append(f"comparison.png not drawn: {err!r}")
    (o / "comparison.json").write_text(json.dumps(res, indent=2) + "\n")
    lines = [f"# Before / after: {', '.join(b['effects']) or 'baseline'} vs "
             f"{', '.join(a['effects']) or 'baseline'}", "",
             "| | before | after |", "|---|---|---|",
             f"| RMS residual (um) | {a['rms_um']:.4g} | {b['rms_um']:.4g} |",
             f"| misfit statistic (mean; n = {a['n']}) | {a['misfit_mean']:.4g} | "
             f"{b['misfit_mean']:.4g} |",
             f"| predictive p-value | {a['misfit_p']:.3g} | {b['misfit_p']:.3g} |",
             f"| ELPD, {a['elpd_method']} / {b['elpd_method']} (nats) | {a['elpd']:.2f} +- "
             f"{a['elpd_se']:.2f} | {b['elpd']:.2f} +- {b['elpd_se']:.2f} |",
             f"| observations with Pareto k-hat > 0.7 | {a['pareto_k_bad']} | "
             f"{b['pareto_k_bad']} |", "",
             f"ELPD gain {res['elpd_gain']:.2f} +- {gain_se:.2f} nats (standard error of the "
             "difference, paired over observations).", "",
             "## Posterior shifts (2.5 / 50 / 97.5 %)", "",
             "| parameter | before | after |", "|---|---|---|"]
    for s in shifts:
        lines.append(f"| {s['parameter']} | " + " / ".join(f"{v:.4g}" for v in s["before"])
                     + " | " + " / ".join(f"{v:.4g}" for v in s["after"]) + " |")
    for p, r in res["added"].items():
        lines.append(f"| {p} (added) | | {r['q2.5']:.4g} / {r['median']:.4g} / "
                     f"{r['q97.5']:.4g} |")
    lines += ["", "## Warnings", ""] + ([f"- {w}" for w in res["warnings"]] or ["- none"])
    if "figure" in res:
        lines += ["", f"![before / after: residuals and marginals]({res['figure']})"]
    (o / "comparison.md").write_text("\n".join(lines) + "\n")
    from solderpyro.reporting.index import write_index

    write_index(o)
    return res


def _diff_se(before: str | Path, after: str | Path) -> float:
    """Standard error of the PSIS-LOO ELPD difference (``az.compare``'s ``dse``), paired over
    observations."""
    import warnings

    from solderpyro.calibration.mcmc import import_arviz as _arviz

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tab = _arviz().compare({"before": load_idata(before), "after": load_idata(after)},
                               ic="loo")
    return float(tab["dse"].max())


def _sigma(run: RunDir) -> float:
    """The noise sd of a run, um: the data's stated one, else the posterior median."""
    if run.info.sigma_known:
        return float(run.info.sigma_known)
    return float(np.median(run.draws().sigma))


def plot_comparison(before: str | Path, after: str | Path, path: Path) -> str:
    """Before / after on one figure: the residual of each run's predictive median (maps per
    time, each GP-denoised, one colour scale for both; or, for point
    data, against time with the 95 % predictive band) above the marginals of every parameter
    (before grey, after red; parameters only after: red alone).

    Returns:
        the file name.
    """
    from solderpyro.diagnose.denoise import denoise
    from solderpyro.diagnose.plots import draw_maps, is_field, map_size
    from solderpyro.reporting.plots import plt

    runs = [RunDir.read(d, RUN_FILES) for d in (before, after)]
    d0, d1 = runs[0].path, runs[1].path
    meas = runs[0].measurements()
    sigma = _sigma(runs[0])
    z = [r.draws() for r in runs]
    res = [zz.y_obs - np.median(zz.process, 0) for zz in z]
    names, n0 = z[1].names, z[0].names
    field = is_field(meas)
    w, h = map_size(meas, 2) if field else (10.0, 5.0)
    fig = plt.figure(figsize=(max(w, 10.0), h + 2.6), layout="constrained")
    sub: Any = fig.subfigures(2, 1, height_ratios=[h, 2.6])
    top, bot = sub[0], sub[1]
    eff = [", ".join(r.info.effects) or "baseline" for r in runs]
    lab = [f"{d.name} ({e})" for d, e in zip((d0, d1), eff, strict=True)]
    if field:
        xy = np.c_[meas.x_mm, meas.y_mm]
        s0 = denoise(xy, res[0], meas.time_s, sigma)
        s1 = denoise(xy, res[1], meas.time_s, sigma)
        draw_maps(top, meas, [(f"before: {lab[0]}", s0.mean, s0.z),
                              (f"after: {lab[1]}", s1.mean, s1.z)], sigma, shared=True)
        top.suptitle("Denoised residual of the predictive median (dotted: inside its 95 % "
                     "band), one colour scale", fontsize=9)
    else:
        pts = list(meas.points())
        axes = top.subplots(1, len(pts), squeeze=False)[0]
        for ax, p in zip(axes, pts, strict=True):
            rows = np.flatnonzero(meas.point == p)
            rows = rows[np.argsort(meas.time_s[rows])]
            t = meas.time_s[rows] / 60
            for k, (zz, r) in enumerate(zip(z, res, strict=True)):
                med = np.median(zz.process, 0)
                lo, hi = np.quantile(zz.observed, [0.025, 0.975], 0)
                col = "0.4" if k == 0 else "C3"
                ax.fill_between(t, (lo - med)[rows], (hi - med)[rows], color=col, alpha=0.15)
                ax.plot(t, r[rows], "o-" if k == 0 else "s-", color=col,
                        label=("before: " if k == 0 else "after: ") + lab[k])
            ax.axhline(0, color="k", lw=0.7)
            ax.set_title(f"residual at {p} (data - predictive median), 95 % band", fontsize=9)
            ax.set_xlabel("time (min)")
            ax.set_ylabel("um")
            ax.legend(fontsize=7)
            ax.grid(alpha=0.3)
    allp = n0 + [p for p in names if p not in n0]
    axs = bot.subplots(1, len(allp), squeeze=False)[0]
    for ax, p in zip(axs, allp, strict=True):
        # shared bins, each histogram scaled to its own peak: a narrow "before" (e.g. the FE's
        # best fit of a model that misfits) on a density scale flattened the "after" into
        # its baseline
        vals = [(k, zz.theta[:, nm.index(p)])
                for k, (zz, nm) in enumerate(((z[0], n0), (z[1], names))) if p in nm]
        edges = np.histogram_bin_edges(np.concatenate([v for _, v in vals]), bins=50)
        for k, v in vals:
            c = np.histogram(v, bins=edges)[0].astype(float)
            ax.stairs(c / max(c.max(), 1.0), edges, fill=not k, color="C3" if k else "0.75",
                      lw=1.5, label="after" if k else "before")
        ax.set_title(p, fontsize=9)
        ax.set_yticks([])
        ax.tick_params(labelsize=7)
    axs[0].legend(fontsize=7)
    bot.suptitle("Marginal posteriors before (grey) and after (red), each scaled to its peak",
                 fontsize=9)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path.name
