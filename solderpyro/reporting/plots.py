"""Plots people would rather look at than read (matplotlib, Agg backend)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def plot_cycle(times, V, names, temps_C, cycle=None, marks=()):
    """V at the points and the temperature over the cycle.

    Args:
        times: ``(n_time,)`` s; V: ``(n_time, n_out)`` um; names: ``n_out`` labels;
        temps_C: ``(n_time,)`` degC; cycle: optional program drawn as a line; marks: times to
            mark (e.g. the seed points).
    Returns:
        the matplotlib Figure.
    """
    fig, ax = plt.subplots(figsize=(8, 4.5))
    t_min = np.asarray(times) / 60.0
    for j, n in enumerate(names[:8]):
        ax.plot(t_min, V[:, j], marker="o", ms=2.5, label=f"V_{n}")
    ax.set_xlabel("time (min)")
    ax.set_ylabel("V relative to O (um)")
    ax.grid(alpha=0.3)
    ax2 = ax.twinx()
    if cycle is not None:
        tt = np.linspace(0.0, cycle.end, 400)
        ax2.plot(tt / 60.0, [cycle(x) for x in tt], color="0.5", ls="--", label="temperature")
    else:
        ax2.plot(t_min, temps_C, color="0.5", ls="--", label="temperature")
    ax2.set_ylabel("temperature (C)")
    for m in marks:
        ax.axvline(m / 60.0, color="0.85", lw=0.8, zorder=0)
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, loc="best")
    ax.set_title("Reference specimen through the thermal cycle")
    fig.tight_layout()
    return fig


def plot_traces(post, names=None):
    """Trace and marginal histogram per scalar parameter (one row each).

    Args:
        post: a :class:`~solderpyro.calibration.Posterior`; names: subset of its columns.
    Returns:
        the matplotlib Figure.
    """
    cols = post.columns()
    names = list(names or cols)
    fig, axes = plt.subplots(len(names), 2, figsize=(9, 2.2 * len(names)), squeeze=False,
                             gridspec_kw={"width_ratios": [3, 1]})
    for i, nm in enumerate(names):
        a = cols[nm]  # (chain, draw)
        for c in range(a.shape[0]):
            axes[i, 0].plot(a[c], lw=0.5, alpha=0.8)
            axes[i, 1].hist(a[c], bins=40, histtype="step", density=True)
        axes[i, 0].set_ylabel(nm)
        axes[i, 1].set_yticks([])
    axes[-1, 0].set_xlabel("draw")
    fig.tight_layout()
    return fig


def plot_bands(ax, x, bands, label="posterior predictive", color="C0"):
    """Median and 95 % band of the process, plus the 95 % band of new observations.

    Args:
        ax: matplotlib axes; x: ``(n_new,)``; bands: a
            :class:`~solderpyro.calibration.Bands` over ``n_new`` inputs.
    """
    x = np.asarray(x)
    ax.fill_between(x, bands.obs_lo.numpy(), bands.obs_hi.numpy(), color=color, alpha=0.12,
                    label="95 % new observation")
    ax.fill_between(x, bands.lo.numpy(), bands.hi.numpy(), color=color, alpha=0.3,
                    label="95 % process")
    ax.plot(x, bands.median.numpy(), color=color, label=f"{label} median")


def plot_validation(result, title="surrogate validation"):
    """Predicted vs true with 95 % bars, and the standardized errors against N(0, 1).

    Args:
        result: a :class:`~solderpyro.surrogate.LooResult`.
    Returns:
        the matplotlib Figure.
    """
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(9, 4))
    y, m, s = (t.reshape(-1).numpy() for t in (result.y, result.mean, result.sd))
    # full field: 50 runs x 2,240 outputs; 2,000 evenly spaced points show the same picture
    # (drawing every one of 112,000 error bars and a 37,000-bin histogram took ~60 s)
    show = np.unique(np.linspace(0, y.size - 1, min(y.size, 2000)).round().astype(int))
    a1.errorbar(y[show], m[show], yerr=1.96 * s[show], fmt="o", ms=3, lw=0.8)
    lo, hi = float(min(y.min(), m.min())), float(max(y.max(), m.max()))
    a1.plot([lo, hi], [lo, hi], "k--", lw=0.8)
    a1.set_xlabel("true output")
    a1.set_ylabel("predicted (95 % bar)")
    a1.set_title(f"coverage {result.coverage95:.0%}, RMSE/sd {result.rmse_rel:.3f}"
                 + (f" ({show.size} of {y.size} shown)" if show.size < y.size else ""))
    z = result.z.reshape(-1).numpy()
    a2.hist(z, bins=int(np.clip(len(z) // 3, 5, 80)), density=True, alpha=0.6)
    g = np.linspace(-4, 4, 200)
    a2.plot(g, np.exp(-0.5 * g**2) / np.sqrt(2 * np.pi), "k-", lw=1)
    a2.set_xlabel("standardized error")
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def plot_exact(names, theta, weights, draws, profile=None, truth=None):
    """FE-exact vs surrogate posterior marginals, and the chi-square profile along the ridge.

    Args:
        names: ``dim`` parameter names; theta: ``(N, dim)`` importance samples (physical) with
            normalized ``weights (N,)``; draws: ``(n, dim)`` surrogate posterior draws.
        profile: optional ``(name, values (G,), chi2 (G,))`` of the profiled parameter.
        truth: optional ``{name: value}`` drawn as vertical lines (synthetic data).
    Returns:
        the matplotlib Figure.
    """
    d = len(names)
    n_p = d + (profile is not None)
    cols = min(3, n_p)
    rows = (n_p + cols - 1) // cols
    fig, axs = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.0 * rows), squeeze=False)
    axs = axs.ravel()
    for k, nm in enumerate(names):
        ax = axs[k]
        lo = min(np.min(draws[:, k]), np.min(theta[weights > 1e-4 * weights.max(), k]))
        hi = max(np.max(draws[:, k]), np.max(theta[weights > 1e-4 * weights.max(), k]))
        bins = np.linspace(lo, hi, 31) if hi > lo else 10
        ax.hist(theta[:, k], bins=bins, weights=weights, density=True, alpha=0.55,
                color="C0", label="FE-exact")
        ax.hist(draws[:, k], bins=bins, density=True, histtype="step", lw=1.5, color="C1",
                label="surrogate")
        if truth and nm in truth:
            ax.axvline(truth[nm], color="k", ls="--", lw=1, label="truth")
        ax.set_xlabel(nm)
        ax.set_yticks([])
    axs[0].legend(fontsize=8)
    if profile is not None:
        nm, v, c2 = profile
        ax = axs[d]
        c2 = np.asarray(c2, float)
        ax.plot(v, c2 - np.nanmin(c2[np.isfinite(c2)]), "o-", color="C2")
        ax.axhline(3.84, color="0.5", ls=":", lw=1, label="chi2(1) 95 %")
        ax.set_xlabel(nm)
        ax.set_ylabel("profile chi2 - min")
        ax.set_yscale("symlog", linthresh=10)
        ax.legend(fontsize=8)
    for ax in axs[n_p:]:
        ax.axis("off")
    fig.suptitle("FE-exact posterior (importance sampling) vs the surrogate's")
    fig.tight_layout()
    return fig
