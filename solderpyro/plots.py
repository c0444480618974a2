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
