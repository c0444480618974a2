"""The files of a prediction: tables, the ArviZ file, figures and the index page.

``OUT/``:

- ``index.html`` (and ``prediction.md``): what was predicted, where, the notes, the table of
  bands, the figures;
- ``prediction.csv``: one row per quantity, region and cycle: median, 95 % band, the share
  of the band due to the Anand constants, draws counted, unit, what it is;
- ``prediction_draws.csv``: each draw's parameters and its last cycle's quantities;
- ``histories.csv``: per history point and grid time, the median and band of the von Mises
  and shear stress, the inelastic shear strain and the accumulated equivalent inelastic
  strain;
- ``predictions.nc``: ArviZ InferenceData, the draws' parameters as ``posterior`` and every
  quantity per draw as ``predictions`` (chain 1, draw N);
- figures: ``prediction_maps.png`` (the last cycle's inelastic work over the joint: median
  and band width), ``prediction_cycles.png`` (per cycle, per region),
  ``prediction_histories.png``, ``prediction_hysteresis.png`` (shear stress against inelastic
  shear strain at each history point);
- ``fields/``: the solved chunks (kept: a rerun reads them).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

import numpy as np

#: quantity -> (unit, what it is)
QUANTITIES = {
    "dW": ("MPa", "inelastic strain energy density of the cycle (MPa = mJ/mm^3)"),
    "dp": ("1", "equivalent inelastic strain of the cycle (inelastic strain range)"),
    "vm_max": ("MPa", "largest von Mises stress in the joint over the prediction"),
    "tau_max": ("MPa", "largest |shear stress sigma_xy| in the joint over the prediction"),
    "rate_max": ("1/s", "largest equivalent inelastic strain rate in the joint"),
}


def _region_label(pred: Any, name: str) -> str:
    for r in pred.regions:
        if r.name == name:
            return r.label
    return "its largest Gauss-point value" if name == "max" else name


def write_prediction(pred: Any, out: Path, run_dir: Path, overrides: list[str],
                     dW: np.ndarray) -> None:
    """Write the files of :class:`~solderpyro.predict.run.Prediction` ``pred`` to ``out``
    (module docstring); ``dW`` ``(N, n_cycles, n_e, n_qp)`` MPa: each draw's per-cycle work
    density at the Gauss points (the maps)."""
    out.mkdir(parents=True, exist_ok=True)
    _tables(pred, out)
    _arviz(pred, out)
    figs = _figures(pred, out, dW)
    _index(pred, out, run_dir, overrides, figs)


def _tables(pred: Any, out: Path) -> None:
    with (out / "prediction.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["quantity", "region", "cycle", "unit", "median", "lo95", "hi95",
                    "constants_share", "n_draws", "what"])
        for (q, r, c), b in pred.bands.items():
            unit, what = QUANTITIES[q]
            w.writerow([q, r, c, unit, f"{b.median:.6g}", f"{b.lo:.6g}", f"{b.hi:.6g}",
                        f"{b.constants_share:.3f}", b.n, f"{what}; {_region_label(pred, r)}"])
    f = pred.fields
    last = {f"{q}_{r}": v[:, -1] for (q, r), v in pred.per_cycle.items()}
    with (out / "prediction_draws.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["draw", *pred.target.names, "ok", *last])
        for i in range(len(f.ok)):
            w.writerow([i, *[f"{x:.8g}" for x in f.theta[i]], int(f.ok[i]),
                        *[f"{v[i]:.6g}" for v in last.values()]])
    with (out / "histories.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["point", "x_mm", "y_mm", "time_s", "quantity", "unit", "median", "lo95",
                    "hi95"])
        for j, h in enumerate(pred.points):
            for qn, unit, x in _history_quantities(f, j):
                lo, med, hi = _quant(x)
                for k, t in enumerate(f.t):
                    w.writerow([h.name, f"{h.at[0]:.5g}", f"{h.at[1]:.5g}", f"{t:.6g}", qn,
                                unit, f"{med[k]:.6g}", f"{lo[k]:.6g}", f"{hi[k]:.6g}"])


def _history_quantities(f: Any, j: int) -> list[tuple[str, str, np.ndarray]]:
    """``(name, unit, (N, S))`` histories at history point ``j`` (failed draws NaN)."""
    import torch

    from solderpyro.fem.record import shear_xy, von_mises

    sig = torch.as_tensor(f.sigma[:, :, j])
    ok = f.ok[:, None]
    vm = np.where(ok, von_mises(sig).numpy(), np.nan)
    tau = np.where(ok, shear_xy(sig).numpy(), np.nan)
    gam = np.where(ok, math.sqrt(2.0) * f.eps_p[:, :, j, 3], np.nan)
    p = np.where(ok, f.p_hist[:, :, j], np.nan)
    return [("von_mises", "MPa", vm), ("sigma_xy", "MPa", tau),
            ("inelastic_shear_strain", "1", gam), ("equivalent_inelastic_strain", "1", p)]


def _quant(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 2.5, 50 and 97.5 % quantiles over axis 0 of ``x`` ``(N, ...)``, NaN rows left
    out."""
    good = x[np.isfinite(x).all(tuple(range(1, x.ndim)))] if x.ndim > 1 else x[np.isfinite(x)]
    if len(good) == 0:
        nan = np.full(x.shape[1:], np.nan)
        return nan, nan, nan
    lo, med, hi = np.quantile(good, [0.025, 0.5, 0.975], axis=0)
    return lo, med, hi


def _arviz(pred: Any, out: Path) -> None:
    import arviz as az

    f = pred.fields
    post = {n.replace("/", "_"): f.theta[None, :, i] for i, n in enumerate(pred.target.names)}
    preds: dict[str, np.ndarray] = {}
    dims: dict[str, list[str]] = {}
    for (q, r), v in pred.per_cycle.items():
        preds[f"{q}_{r}"] = v[None]
        dims[f"{q}_{r}"] = ["cycle"]
    for q in ("vm_max", "tau_max", "rate_max"):
        v = getattr(f, q).reshape(len(f.ok), -1).max(1)
        preds[q] = np.where(f.ok, v, np.nan)[None]
    n_c = len(pred.cycle_ends)
    cycles = {"cycle": np.arange(1, n_c + 1)}
    idata = az.from_dict(posterior=post, predictions=preds, pred_dims=dims,
                         pred_coords=cycles, coords=cycles)
    idata.to_netcdf(str(out / "predictions.nc"))


def _figures(pred: Any, out: Path, dW: np.ndarray) -> list[tuple[str, str]]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figs = []
    figs.append(_maps(pred, out, dW, plt))
    figs.append(_cycles(pred, out, plt))
    if pred.points:
        figs.append(_histories(pred, out, plt))
        figs.append(_hysteresis(pred, out, plt))
    return figs


def _save(fig: Any, out: Path, name: str, dpi: int, plt: Any) -> str:
    """Lay out, write ``out/name`` and close ``fig``; returns ``name``."""
    fig.tight_layout()
    fig.savefig(out / name, dpi=dpi)
    plt.close(fig)
    return name


def _maps(pred: Any, out: Path, dW: np.ndarray, plt: Any) -> tuple[str, str]:
    from matplotlib.colors import LogNorm
    from matplotlib.tri import Triangulation

    last = dW[:, -1][pred.fields.ok].reshape(int(pred.fields.ok.sum()), -1)
    xy = pred.xy.reshape(-1, 2)
    lo, med, hi = _quant(last)
    width = 100.0 * (hi - lo) / np.where(np.abs(med) > 0, np.abs(med), np.nan)
    tri = Triangulation(xy[:, 0], xy[:, 1])
    fig, axs = plt.subplots(2, 1, figsize=(10, 5.2), sharex=True)
    pos = med[med > 0]
    vmin = max(float(pos.min()) if len(pos) else 1e-12, float(np.nanmax(med)) * 1e-4)
    m0 = axs[0].tripcolor(tri, np.clip(med, vmin, None), shading="gouraud",
                          norm=LogNorm(vmin=vmin, vmax=max(float(np.nanmax(med)), vmin * 10)),
                          cmap="viridis")
    fig.colorbar(m0, ax=axs[0], label="median dW, MPa (log)")
    m1 = axs[1].tripcolor(tri, np.nan_to_num(width, nan=0.0), shading="gouraud",
                          cmap="magma")
    fig.colorbar(m1, ax=axs[1], label="95 % band width, % of median")
    for ax in axs:
        ax.set_ylabel("y, mm")
        ax.set_aspect("auto")
    axs[1].set_xlabel("x, mm (thickness stretched)")
    n_c = len(pred.cycle_ends)
    axs[0].set_title(f"Inelastic strain energy density of cycle {n_c} in the solder "
                     f"({last.shape[0]} posterior draws)")
    name = _save(fig, out, "prediction_maps.png", 130, plt)
    return name, ("The last cycle's inelastic strain energy density over the joint: median "
                  "(log scale) and the 95 % band's width relative to it")


def _cycles(pred: Any, out: Path, plt: Any) -> tuple[str, str]:
    n_c = len(pred.cycle_ends)
    cyc = np.arange(1, n_c + 1)
    fig, axs = plt.subplots(1, 2, figsize=(10, 3.8))
    names = {"upper_interface": "upper interface layer",
             "lower_interface": "lower interface layer", "joint": "whole joint",
             "max": "largest point"}
    for ax, q, lab in ((axs[0], "dW", "dW per cycle, MPa"),
                       (axs[1], "dp", "equivalent inelastic strain per cycle")):
        for k, (r, rl) in enumerate(names.items()):
            b = [pred.bands[(q, r, c)] for c in cyc]
            med = np.array([x.median for x in b])
            err = np.array([[x.median - x.lo for x in b], [x.hi - x.median for x in b]])
            ax.errorbar(cyc + 0.08 * (k - 1.5), med, yerr=err, fmt="o-", capsize=3, label=rl)
        ax.set_xlabel("cycle")
        ax.set_ylabel(lab)
        ax.set_yscale("log")
        ax.set_xticks(cyc)
    axs[0].legend(fontsize=8)
    fig.suptitle("Per cycle: median and 95 % band over the posterior draws")
    name = _save(fig, out, "prediction_cycles.png", 130, plt)
    return name, ("Per cycle: the interface layers' and the joint's averages and the largest "
                  "value")


def _histories(pred: Any, out: Path, plt: Any) -> tuple[str, str]:
    f = pred.fields
    n_p = len(pred.points)
    fig, axs = plt.subplots(n_p, 4, figsize=(15, 2.6 * n_p), squeeze=False, sharex=True)
    th = f.t / 3600.0
    cyc = pred.target.setup.problem.cycle
    temps = np.array([cyc(float(t)) for t in f.t])
    for j, h in enumerate(pred.points):
        for k, (qn, unit, x) in enumerate(_history_quantities(f, j)):
            lo, med, hi = _quant(x)
            ax = axs[j, k]
            ax.fill_between(th, lo, hi, alpha=0.3, label="95 % band")
            ax.plot(th, med, lw=1.2, label="median")
            ax.set_ylabel(f"{qn.replace('_', ' ')}, {unit}" if unit != "1" else
                          qn.replace("_", " "), fontsize=8)
            if k == 0:
                tx = ax.twinx()
                tx.plot(th, temps, color="0.65", lw=0.8)
                tx.set_ylabel("temperature, degC", fontsize=7, color="0.5")
                tx.tick_params(labelsize=7, colors="0.5")
                ax.set_title(f"{h.name} (x {h.at[0]:.3g}, y {h.at[1]:.3g} mm)", fontsize=9,
                             loc="left")
    for ax in axs[-1]:
        ax.set_xlabel("time, h")
    axs[0, 0].legend(fontsize=8)
    name = _save(fig, out, "prediction_histories.png", 120, plt)
    return name, "Stress and inelastic shear strain histories at the history points"


def _hysteresis(pred: Any, out: Path, plt: Any) -> tuple[str, str]:
    f = pred.fields
    n_p = len(pred.points)
    fig, axs = plt.subplots(1, n_p, figsize=(4.2 * n_p, 3.8), squeeze=False)
    ok = np.flatnonzero(f.ok)
    key = pred.per_cycle[("dW", "upper_interface")][:, -1]
    mid = ok[np.argsort(key[ok])[len(ok) // 2]] if len(ok) else None
    show = ok[np.linspace(0, len(ok) - 1, min(40, len(ok))).round().astype(int)]
    for j, h in enumerate(pred.points):
        ax = axs[0, j]
        (_, _, tau), (_, _, gam) = (_history_quantities(f, j)[1],
                                    _history_quantities(f, j)[2])
        for i in show:
            ax.plot(100 * gam[i], tau[i], color="0.6", lw=0.5, alpha=0.5)
        if mid is not None:
            ax.plot(100 * gam[mid], tau[mid], color="C3", lw=1.5, label="median-dW draw")
        ax.set_xlabel("inelastic shear strain gamma_p, %")
        ax.set_ylabel("sigma_xy, MPa")
        ax.set_title(h.name, fontsize=9)
    axs[0, 0].legend(fontsize=8, title=f"grey: {len(show)} draws", title_fontsize=8)
    name = _save(fig, out, "prediction_hysteresis.png", 120, plt)
    return name, ("Shear hysteresis at the history points: the loops of posterior draws "
                  "(grey, their spread is the band) and the draw of median dW")


def _fmt(v: float) -> str:
    return "n/a" if not np.isfinite(v) else f"{v:.4g}"


def _index(pred: Any, out: Path, run_dir: Path, overrides: list[str],
           figs: list[tuple[str, str]]) -> None:
    from solderpyro.reporting.report import write_html

    t = pred.target
    n_c = len(pred.cycle_ends)
    ok = int(pred.fields.ok.sum())
    where = ("the calibration's own specimen and cycle" if not t.transfer else
             f"another assembly and cycle ({' '.join(overrides)})")
    lines = [f"# Prediction from {run_dir}", "",
             f"The FE at {len(pred.fields.ok)} posterior draws ({ok} solved) of the "
             f"calibration in `{run_dir}`, on {where}; {n_c} cycle(s); effects carried: "
             f"{', '.join(t.effects) or 'none'}. FE time {pred.seconds:.0f} s.", ""]
    lo_c, hi_c = pred.temperature["calibration"]
    lo_t, hi_t = pred.temperature["target"]
    lines += [f"- Temperatures: the target's {lo_t:g} to {hi_t:g} degC; the calibration saw "
              f"{lo_c:g} to {hi_c:g} degC.",
              f"- Largest inelastic strain rate (median draw): the target's "
              f"{pred.rate['target']:.3g} 1/s; the calibration's {pred.rate['calibration']:.3g}"
              " 1/s.", ""]
    if pred.notes:
        lines += ["## Notes", ""] + [f"- {n}" for n in pred.notes] + [""]
    lines += ["## The last cycle", "",
              "| quantity | region | median | 95 % band | share from the constants | unit |",
              "|---|---|---|---|---|---|"]
    for (q, r, c), b in pred.bands.items():
        if c in (n_c, 0):
            lines.append(f"| {q} | {r} | {_fmt(b.median)} | {_fmt(b.lo)} - {_fmt(b.hi)} | "
                         f"{_fmt(100 * b.constants_share)} % | {QUANTITIES[q][0]} |")
    lines += ["", "Regions:", ""] + [f"- {r.name}: {r.label}" for r in pred.regions] + [""]
    lines += ["History points:", ""] + [
        f"- {h.name}: asked at ({h.xy[0]:g}, {h.xy[1]:g}) mm, the Gauss point at "
        f"({h.at[0]:.4g}, {h.at[1]:.4g}) mm" for h in pred.points] + [""]
    for name, cap in figs:
        lines += [f"![{cap}]({name})", ""]
    lines += ["## Files", "", "- `prediction.csv`: every quantity, region and cycle",
              "- `prediction_draws.csv`: each draw's parameters and last-cycle quantities",
              "- `histories.csv`: the histories' medians and bands",
              "- `predictions.nc`: ArviZ (`posterior`: the draws, `predictions`: the "
              "quantities)", "- `fields/`: the solved chunks (a rerun reads them)"]
    (out / "prediction.md").write_text("\n".join(lines) + "\n", encoding="utf-8")
    write_html(lines, out / "index.html", f"Prediction from {run_dir}")
