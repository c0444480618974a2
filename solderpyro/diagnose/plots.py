"""Figures of a diagnosis: where the model fails, and which effect's pattern matches.

Full-field data are drawn as maps of the specimen at its true aspect ratio (30 mm x 8.5 mm,
one cell per grid node), one panel per measured time, one colour scale per row symmetric
about zero, in um and in noise sd. Point data (A, B) are drawn against time with the
temperature of the cycle on a twin axis.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from solderpyro.reporting.plots import plt

#: a map row: (label, values (n,) um row for row with the data, z (n,) or None); where z is
#: given, the cells inside the band (|z| <= 2: noise could have made them) are dotted
MapRow = tuple[str, np.ndarray, "np.ndarray | None"]


def is_field(meas: Any) -> bool:
    """Full-field data (more than the four named points)."""
    return len(meas.points()) > 4


def grid_image(meas: Any, values: np.ndarray, t: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The values at time ``t`` (s) on the 31 x 18 reference grid.

    Args:
        meas: measurements (n rows); values: ``(n,)`` row for row with ``meas``.
    Returns:
        ``(img (n_y, n_x), x (n_x,), y (n_y,))``: NaN where the grid node was not measured
        (named points such as A and B are left out); coordinates in mm.
    """
    from solderpyro.fem.problem import reference_grid

    g = reference_grid()[1]
    xs, ys = np.unique(g[:, 0]), np.unique(g[:, 1])
    img = np.full((len(ys), len(xs)), np.nan)
    rows = np.flatnonzero(np.isclose(meas.time_s, t))
    i = np.clip(np.searchsorted(xs, meas.x_mm[rows] - 1e-6), 0, len(xs) - 1)
    j = np.clip(np.searchsorted(ys, meas.y_mm[rows] - 1e-6), 0, len(ys) - 1)
    on = np.isclose(xs[i], meas.x_mm[rows]) & np.isclose(ys[j], meas.y_mm[rows])
    img[j[on], i[on]] = np.asarray(values, float)[rows[on]]
    return img, xs, ys


def _edges(c: np.ndarray) -> np.ndarray:
    h = np.diff(c) / 2
    return np.concatenate([[c[0] - h[0]], c[:-1] + h, [c[-1] + h[-1]]])


def plot_maps(meas: Any, rows: Sequence[MapRow], sigma: float, path: Path, title: str,
              shared: bool = False) -> str:
    """Rows of maps (one per measured time) at the specimen's aspect ratio.

    Args:
        meas: full-field measurements (n rows).
        rows: :data:`MapRow` list, drawn top to bottom.
        sigma: noise sd, um (the colour bars' second scale).
        path: the PNG to write.
        shared: one colour scale for every row (else one per row).
    Returns:
        the file name.
    """
    fig = plt.figure(figsize=map_size(meas, len(rows)), layout="constrained")
    draw_maps(fig, meas, rows, sigma, shared)
    fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path.name


def map_size(meas: Any, n_rows: int) -> tuple[float, float]:
    """Figure size (in) of ``n_rows`` rows of maps, one per measured time, at the specimen's
    aspect ratio (30 mm x 8.5 mm)."""
    w = 3.7
    return (w * len(meas.times()) + 1.9, (w * 8.5 / 30 + 0.62) * n_rows + 0.5)


def draw_maps(fig: Any, meas: Any, rows: Sequence[MapRow], sigma: float,
              shared: bool = False) -> None:
    """Draw :func:`plot_maps`'s rows into ``fig`` (a Figure or SubFigure)."""
    times = list(meas.times())
    nt, nr = len(times), len(rows)
    axes = fig.subplots(nr, nt, squeeze=False)
    vall = max((float(np.nanmax(np.abs(v))) for _, v, _ in rows), default=1.0) or 1.0
    for r, (label, vals, z) in enumerate(rows):
        vm = vall if shared else float(np.nanmax(np.abs(vals)))
        if not vm > 0:  # a denoised map with no structure above the noise: +-1 noise sd
            vm = sigma
        if not np.any(vals):  # said in words: a blank row (on a shared scale too) looked
            label = f"{label}:\nno structure above the noise"  # like a plot that failed
        im = None
        for c, t in enumerate(times):
            ax = axes[r, c]
            img, xs, ys = grid_image(meas, vals, t)
            im = ax.pcolormesh(_edges(xs), _edges(ys), img, cmap="RdBu_r", vmin=-vm, vmax=vm)
            if z is not None and np.any(vals):
                zi = np.abs(grid_image(meas, z, t)[0])
                ax.contourf(xs, ys, zi, levels=[0.0, 2.0], colors="none", hatches=["...."])
            ax.set_aspect("equal")
            ax.tick_params(labelsize=7)
            ax.set_title(f"{label}, t = {t / 60:.0f} min" if c == 0 else f"t = {t / 60:.0f} min",
                         fontsize=8, loc="left" if c == 0 else "center")
            if r == nr - 1:
                ax.set_xlabel("x (mm)", fontsize=7)
            if c == 0:
                ax.set_ylabel("y (mm)", fontsize=7)
        assert im is not None
        cb = fig.colorbar(im, ax=list(axes[r]), fraction=0.02, pad=0.01)
        cb.set_label("um", fontsize=7)
        cb.ax.tick_params(labelsize=6)

        def to_sd(v: Any) -> Any:
            return np.asarray(v) / sigma

        def to_um(v: Any) -> Any:
            return np.asarray(v) * sigma

        sec = cb.ax.secondary_yaxis(-1.6, functions=(to_sd, to_um))
        sec.set_ylabel("noise sd", fontsize=7)
        sec.tick_params(labelsize=6)


def _temperature(ax: Any, cycle: Callable[[float], float] | None, t_end: float) -> None:
    """The cycle's temperature (degC) on a twin axis over ``[0, t_end]`` s."""
    if cycle is None:
        return
    tt = np.linspace(0.0, t_end, 300)
    ax2 = ax.twinx()
    ax2.plot(tt / 60, [cycle(float(v)) for v in tt], color="0.6", lw=1, ls=":")
    ax2.set_ylabel("temperature (degC, dotted)", fontsize=8, color="0.4")
    ax2.tick_params(labelsize=7, colors="0.4")


def plot_point_residuals(meas: Any, pred: np.ndarray, fe_residual: np.ndarray, sigma: float,
                         path: Path, cycle: Callable[[float], float] | None = None,
                         t_end: float | None = None) -> str:
    """Point data: the residual against time at each point, with the predictive band.

    Args:
        meas: measurements (n rows, <= 4 points).
        pred: ``(n_draws, n)`` posterior predictive draws of a new measurement, um.
        fe_residual: ``(n,)`` the FE residual at its best fit, um.
        sigma: noise sd, um. path: the PNG to write.
        cycle: temperature (degC) as a function of time (s), drawn on a twin axis.
        t_end: the cycle's end, s (default the last measured time).
    Returns:
        the file name.
    """
    y = np.asarray(meas.value_um, float)
    med = np.median(pred, 0)
    lo, hi = np.quantile(pred, [0.025, 0.975], 0)
    pts = list(meas.points())
    fig, axes = plt.subplots(len(pts), 1, figsize=(8, 2.8 * len(pts) + 0.4), squeeze=False,
                             sharex=True, layout="constrained")
    for k, p in enumerate(pts):
        ax = axes[k, 0]
        rows = np.flatnonzero(meas.point == p)
        rows = rows[np.argsort(meas.time_s[rows])]
        t = meas.time_s[rows] / 60
        ax.fill_between(t, lo[rows] - med[rows], hi[rows] - med[rows], color="C0", alpha=0.2,
                        label="95 % predictive band (new measurement)")
        ax.plot(t, y[rows] - med[rows], "o-", color="C0", label="data - predictive median")
        ax.plot(t, fe_residual[rows], "s--", color="C3", ms=4,
                label="data - FE at its best fit")
        ax.axhline(0, color="k", lw=0.7)
        ax.set_ylabel(f"residual at {p} (um)", fontsize=8)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper left")
        _temperature(ax, cycle, t_end or float(meas.time_s.max()))
    axes[-1, 0].set_xlabel("time (min)")
    fig.suptitle(f"Where the calibrated model misses the data (noise sd {sigma:.3g} um)",
                 fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path.name


def plot_point_fingerprints(meas: Any, residual: np.ndarray,
                            fps: Sequence[tuple[str, np.ndarray, np.ndarray, float]],
                            sigma: float, path: Path,
                            cycle: Callable[[float], float] | None = None,
                            t_end: float | None = None) -> str:
    """Point data: each candidate's signature over the cycle beside the residual.

    Args:
        meas: measurements (n rows). residual: ``(n,)`` um.
        fps: per candidate ``(name, signature (n,) um, residual after adding it (n,) um,
            correlation with the residual)``.
        sigma: noise sd, um. path: the PNG to write. cycle, t_end: as
            :func:`plot_point_residuals`.
    Returns:
        the file name.
    """
    k = max(len(fps), 1)
    fig, axes = plt.subplots(k, 1, figsize=(8, 2.7 * k + 0.4), squeeze=False, sharex=True,
                             layout="constrained")
    for i, (name, sig, after, corr) in enumerate(fps):
        ax = axes[i, 0]
        for j, p in enumerate(meas.points()):
            rows = np.flatnonzero(meas.point == p)
            rows = rows[np.argsort(meas.time_s[rows])]
            t = meas.time_s[rows] / 60
            ax.plot(t, residual[rows], "s", color=f"C{j}", label=f"residual ({p})")
            ax.plot(t, sig[rows], "-", color=f"C{j}", label=f"{name} signature ({p})")
            ax.plot(t, after[rows], "x:", color=f"C{j}", ms=5, label=f"after adding it ({p})")
        ax.axhspan(-2 * sigma, 2 * sigma, color="0.9", zorder=0)
        ax.axhline(0, color="k", lw=0.7)
        ax.set_ylabel("um", fontsize=8)
        ax.set_title(f"{name}: shape correlation with the residual r = {corr:.2f}",
                     fontsize=9, loc="left")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6, ncol=3, loc="upper left")
        _temperature(ax, cycle, t_end or float(meas.time_s.max()))
    axes[-1, 0].set_xlabel("time (min)")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path.name


def evidence_scale(evidence: Sequence[float], threshold: float) -> str:
    """The ranking's x scale: ``"symlog"`` (linear up to ``threshold``, logarithmic above)
    where the largest evidence is over 100 x ``threshold`` (a flagged candidate beside one
    1,000 x stronger would show no bar on a linear axis), else ``"linear"``."""
    return "symlog" if max([*evidence, 0.0]) > 100.0 * threshold else "linear"


def plot_ranking(scores: Sequence[Any], correlation: dict[str, float], path: Path,
                 after_sd: dict[str, float] | None = None,
                 selected: Sequence[str] = (), caveat: Sequence[str] = ()) -> str:
    """Evidence per candidate effect (bars, best at the top), each labelled with the shape
    correlation of its fingerprint with the (denoised) residual and, where given, the RMS
    residual its refit leaves (noise sd); the selected effects' bars in another colour, and
    those the data cannot rule out (``caveat``: they fit as well and would move the constants)
    hatched and named so, whatever their evidence; logarithmic above the 1 % line where the
    evidence spans more than it shows linearly (:func:`evidence_scale`).

    Args:
        scores: ``Score`` list, best first; correlation: effect -> correlation;
        path: the PNG to write; after_sd: effect -> RMS after its refit, noise sd;
        selected: the effects the diagnosis selected; caveat: the effects its verdict
            cannot rule out.
    Returns:
        the file name.
    """
    names = [s.effect for s in scores][::-1]
    ev = [s.evidence for s in scores][::-1]
    thr = -np.log10(0.01 / max(len(names), 1))
    scale = evidence_scale(ev, thr)
    fig, ax = plt.subplots(figsize=(8, 0.42 * len(names) + 1.3), layout="constrained")
    bars = ax.barh(names, ev, color=["C0" if n in selected else "C1" for n in names])
    ax.axvline(thr, color="k", ls="--", lw=0.8, label="1 % (Bonferroni)")
    chosen = [b for b, n in zip(bars, names, strict=True) if n in selected]
    if chosen:
        chosen[0].set_label("selected")
    open_ = [(b, n) for b, n in zip(bars, names, strict=True)
             if n in caveat and n not in selected]
    for k, (b, _) in enumerate(open_):
        b.set_hatch("///")
        b.set_edgecolor("C2")
        if k == 0:
            b.set_label("cannot be ruled out")
    after_sd = after_sd or {}
    for b, n in zip(bars, names, strict=True):
        label = [f"r = {correlation[n]:.2f}"] if n in correlation else []
        if after_sd.get(n) is not None:
            label.append(f"{after_sd[n]:.2f} sd after")
        if n in caveat and n not in selected:
            label.append("cannot be ruled out")
        if label:
            ax.annotate(", ".join(label), (b.get_width(), b.get_y() + b.get_height() / 2),
                        xytext=(4, 0), textcoords="offset points", va="center", fontsize=7)
    ax.set_xlabel("evidence: -log10 p (score test, or likelihood ratio of the FE refit)"
                  if scale == "linear" else "evidence: -log10 p (score test or FE-refit "
                  "likelihood ratio), logarithmic above the 1 % line")
    ax.set_title("r: fingerprint's shape correlation with the residual; sd after: the RMS "
                 "its refit leaves, in noise sd", fontsize=8, loc="left")
    ax.legend(fontsize=8, loc="lower right")
    top = max(ev + [1.0])
    if scale == "symlog":
        ax.set_xscale("symlog", linthresh=thr)
        ax.set_xlim(0, top * 40)
        ax.set_xticks([0.0] + [10.0**k for k in range(int(np.ceil(np.log10(thr))),
                                                      int(np.ceil(np.log10(top * 40))))])
    else:  # the 1 % line in view where no candidate reaches it
        ax.set_xlim(0, max(top * 1.5, thr * 1.2))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path.name
