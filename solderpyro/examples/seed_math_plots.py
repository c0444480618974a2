"""Figures 1-4 of the seed's mathematical example."""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import matplotlib.pyplot as plt
import numpy as np
import torch

from solderpyro.reporting.plots import plot_bands, plot_traces


def _save(fig, path: Path) -> None:
    fig.savefig(path, dpi=120)
    plt.close(fig)


class BandStyle(NamedTuple):
    """How a figure draws its predictive bands: the bands' legend label, their matplotlib
    colour, and the figure's title."""

    label: str
    color: str
    title: str


def _prediction(path, x, y, xg, bands, true_fn, style: BandStyle, extra=None) -> None:
    """Predictive bands, the true process and the data on one axes (Figures 1 and 4).

    Args:
        path: the PNG written. x: ``(n, 1)`` and y: ``(n,)`` the data. xg: ``(g, 1)`` the
            grid of the bands (:class:`~solderpyro.calibration.predictive.Bands`) and of
            ``true_fn``. style: :class:`BandStyle`. extra: ``ax -> None`` draws more.
    """
    fig, ax = plt.subplots(figsize=(7, 4.5))
    plot_bands(ax, xg[:, 0], bands, style.label, color=style.color)
    if extra is not None:
        extra(ax)
    ax.plot(xg[:, 0], true_fn(xg[:, 0]), "k:", label="true process")
    ax.plot(x[:, 0], y, "k*", ms=9, label="data")
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.legend()
    ax.set_title(style.title)
    _save(fig, path)


def fig1(path, x, y, xg, bands, t_reg, true_fn) -> None:
    """Data, the regression curve, the direct posterior predictive and the true process."""
    def regression(ax):
        ax.plot(xg[:, 0], 5 * torch.exp(-t_reg * xg[:, 0]), "C1--",
                label=f"regression t={t_reg:.3f}")

    _prediction(path, x, y, xg, bands, true_fn,
                BandStyle("direct", "C0", "Figure 1: data and direct calibration"), regression)


def fig2(path, post) -> None:
    """Traces and marginals of t and sigma."""
    fig = plot_traces(post, ["t", "sigma"])
    fig.suptitle("Figure 2: direct posterior")
    fig.tight_layout()
    _save(fig, path)


def fig3(path, xs, ts, ys, data, post, inp, code) -> None:
    """The code and the GP through the LHS runs at the posterior-median hyperparameters."""
    from solderpyro.calibration.koh import joint_correlation

    xg, tg = np.meshgrid(np.linspace(0, 3, 40), np.linspace(data.theta_box.lower[0],
                                                            data.theta_box.upper[0], 40))
    pts = torch.tensor(np.c_[xg.ravel(), tg.ravel()], dtype=torch.float64)
    true = torch.stack([code(p[:1][None], p[1:]) for p in pts]).reshape(xg.shape)
    u = torch.cat([data.x_box.to_unit(pts[:, :1]), data.theta_box.to_unit(pts[:, 1:])], -1)
    corr = post.raw["corr"].reshape(-1, post.raw["corr"].shape[-1]).median(0).values
    r = joint_correlation(inp, inp.u_sim, inp.u_sim, corr) + 1e-8 * torch.eye(
        inp.u_sim.shape[0], dtype=torch.float64)
    z = (ys - ys.mean()) / ys.std()
    mu = z.mean()  # GLS mean with a constant basis, close enough for a picture
    w = torch.linalg.solve(r, z - mu)
    pred = (mu + joint_correlation(inp, u, inp.u_sim, corr) @ w) * ys.std() + ys.mean()
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    lev = np.linspace(float(min(true.min(), pred.min())), float(max(true.max(), pred.max())), 21)
    for ax, f, title in ((axes[0], true, "code 5 exp(-t x)"),
                         (axes[1], pred.reshape(xg.shape), "GP from the LHS runs")):
        cs = ax.contourf(xg, tg, f.numpy(), levels=lev)
        ax.plot(xs[:, 0], ts[:, 0], "w^", ms=8)
        ax.set_title(title)
        ax.set_xlabel("x")
    axes[0].set_ylabel("t")
    fig.colorbar(cs, ax=axes)
    fig.suptitle("Figure 3: original and surrogate model")
    _save(fig, path)


def fig4(path, x, y, xg, bands, true_fn) -> None:
    """Full-joint posterior predictive against the true process."""
    _prediction(path, x, y, xg, bands, true_fn, BandStyle(
        "full joint", "C2", "Figure 4: posterior prediction of the surrogate calibration"))
