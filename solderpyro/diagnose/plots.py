"""Figures of a diagnosis: where the model fails, and which effect's pattern matches."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from solderpyro.plots import plt


def _panels(meas: Any, n_times: int):
    field = len(meas.points()) > 4
    if field:
        fig, axes = plt.subplots(1, n_times, figsize=(3.2 * n_times + 1, 3.4), squeeze=False)
        return fig, list(axes[0]), True
    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    return fig, [ax], False


def _draw(ax_list, meas: Any, values: np.ndarray, label: str, field: bool, color: str,
          vmax: float | None = None, marker: str = "o-"):
    """Values row for row with ``meas``: lines over time per point, or maps per time."""
    if not field:
        ax = ax_list[0]
        for k, p in enumerate(meas.points()):
            rows = np.flatnonzero(meas.point == p)
            ax.plot(meas.time_s[rows] / 60, values[rows], marker=marker[0],
                    color=color if len(meas.points()) == 1 else f"C{k}",
                    ls="-" if marker == "o-" else "--", label=f"{label} ({p})")
        return None
    im = None
    for ax, t in zip(ax_list, meas.times(), strict=False):
        rows = np.flatnonzero(meas.time_s == t)
        vm = vmax or float(np.abs(values).max()) or 1.0
        im = ax.scatter(meas.x_mm[rows], meas.y_mm[rows], c=values[rows], cmap="RdBu_r",
                        vmin=-vm, vmax=vm, s=14, marker="s")
        ax.set_title(f"{label}, t = {t / 60:.0f} min", fontsize=8)
        ax.set_xlabel("x (mm)")
    ax_list[0].set_ylabel("y (mm)")
    return im


def plot_residuals(meas: Any, residual: np.ndarray, pc: Any, sigma: float, path: Path) -> str:
    """Refitted FE residuals (um) per point over time (or as maps per time for full-field
    data), with the +-2 sigma noise band and the predictive check's z-scores.

    Args:
        meas: the measurements (n rows); residual: ``(n,)`` um; pc: ``PredictiveCheck``;
        sigma: noise sd, um; path: the PNG to write.
    Returns:
        the file name.
    """
    fig, axes, field = _panels(meas, len(meas.times()))
    im = _draw(axes, meas, residual, "residual", field, "C0")
    if field:
        fig.colorbar(im, ax=axes, label="residual (um)")
    else:
        ax = axes[0]
        ax.axhspan(-2 * sigma, 2 * sigma, color="0.85", label="+-2 sigma noise")
        ax.axhline(0, color="k", lw=0.8)
        ax.set_xlabel("time (min)")
        ax.set_ylabel("measured - model (um)")
        ax.grid(alpha=0.3)
        ax2 = ax.twinx()
        ax2.plot(meas.time_s / 60, pc.z, "k.", ms=5, alpha=0.6, label="predictive z")
        ax2.set_ylabel("standardized residual z (posterior predictive)")
        ax.legend(fontsize=8, loc="upper left")
        fig.tight_layout()
    fig.suptitle("Where the calibrated model misses the data", fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path.name


def plot_ranking(meas: Any, residual: np.ndarray, scores: list[Any], sigma: float,
                 path: Path, top: int = 3) -> str:
    """Evidence per candidate effect (bars) and, for the best ``top`` ones, the residual beside
    the effect's fitted pattern (what it would change, after the calibrated parameters refit).

    Args:
        meas: measurements; residual: ``(n,)`` um; scores: ``Score`` list, best first;
        sigma: noise sd, um; path: the PNG to write.
    Returns:
        the file name.
    """
    field = len(meas.points()) > 4
    k = min(top, len(scores))
    fig = plt.figure(figsize=(11, 3.2 * (k + 1)))
    ax0 = fig.add_subplot(k + 1, 1, 1)
    ev = [s.evidence for s in scores]
    ax0.barh([s.effect for s in scores][::-1], ev[::-1], color="C1")
    ax0.axvline(-np.log10(0.01 / max(len(scores), 1)), color="k", ls="--", lw=0.8,
                label="1 % (Bonferroni)")
    ax0.set_xlabel("evidence: -log10 p (score test, or likelihood ratio of the FE refit)")
    ax0.legend(fontsize=8)
    for i, s in enumerate(scores[:k]):
        ax = fig.add_subplot(k + 1, 1, i + 2)
        if field:
            order = np.lexsort((meas.x_mm, meas.y_mm, meas.time_s))
            ax.plot(residual[order], ".", ms=2, color="0.4", label="residual")
            ax.plot(s.pattern[order], "-", lw=0.8, color="C3", label=f"{s.effect} pattern")
            ax.set_xlabel("observation (time, then y, then x)")
        else:
            for j, p in enumerate(meas.points()):
                rows = np.flatnonzero(meas.point == p)
                t = meas.time_s[rows] / 60
                ax.plot(t, residual[rows], "s", color=f"C{j}", label=f"residual ({p})")
                ax.plot(t, s.pattern[rows], "--", color=f"C{j}", label=f"{s.effect} ({p})")
            ax.set_xlabel("time (min)")
        ax.axhspan(-2 * sigma, 2 * sigma, color="0.9")
        ax.set_ylabel("um")
        ax.set_title(f"{s.effect}: score {s.statistic:.1f} on {s.dof} dof, identifiable "
                     f"{s.identifiable:.2f}", fontsize=9)
        ax.legend(fontsize=7, ncol=2)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path.name
