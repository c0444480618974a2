"""Reliability quantities from the solder's recorded fields, and their posterior bands.

Per cycle (between two cycle ends):

* ``dW``: the inelastic strain energy density of the cycle, ``Delta W = W(end_k) -
  W(end_k-1)`` (MPa = mJ/mm^3), volume-averaged over a region of the solder as Darveaux
  prescribes: a layer of fixed thickness along each interface (:func:`regions` names its
  elements and thickness) and the whole joint; and its largest Gauss-point value (at the
  corner where an interface meets the free end the stress is singular, so this one grows as
  the mesh is refined: a mesh-dependent indicator, not a converged value).
* ``dp``: the cycle's equivalent inelastic strain, ``sum sqrt(2/3) |Delta eps_p|`` (the
  inelastic strain range a Coffin-Manson law takes), the same averages and maximum.

Over the whole prediction: the largest von Mises stress and ``|sigma_xy|`` (MPa) and the
largest equivalent inelastic strain rate (1/s) in the joint.

A band is the 2.5 / 50 / 97.5 % quantiles over the posterior draws. Its share due to the
Anand constants: the fraction of the quantity's variance over the draws that a quadratic
regression on the calibrated constants explains (1 where the calibration has no other
parameter; the rest comes from the effects' parameters the prediction carries).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Region:
    """Solder Gauss points a quantity is averaged over.

    Attributes:
        name: ``upper_interface``, ``lower_interface`` or ``joint``.
        label: what it is, in words, with the elements' thickness.
        mask: ``(n_e, n_qp)`` bool, its Gauss points.
        thickness_mm: the elements' height (the joint's for ``joint``).
    """

    name: str
    label: str
    mask: np.ndarray
    thickness_mm: float


def regions(el_y: np.ndarray, y0: float, y1: float, n_qp: int,
            layer_mm: float | None = None) -> list[Region]:
    """The interface layers and the whole joint of a solder layer between ``y0`` and ``y1``
    mm.

    An interface layer is the solder elements lying within ``layer_mm`` of that interface
    (default a quarter of the joint's thickness): a fixed thickness, so that its average
    converges as the mesh is refined (an element row's average does not: a finer row lies
    closer to the singular corner where the interface meets the free end). Where the elements
    there are thicker than ``layer_mm``, the row touching the interface is the layer (its
    label says how thick it is).

    Args:
        el_y: ``(n_e, 2)`` mm, each solder element's lowest and highest y.
        y0, y1: the layer's lower and upper faces, mm.
        n_qp: Gauss points per element.
        layer_mm: the interface layers' thickness, mm.
    """
    h = float(y1 - y0) / 4.0 if layer_mm is None else float(layer_mm)
    tol = 1e-9 * max(1.0, abs(y1 - y0))
    out = []
    for name, where, inside, touch in (
            ("upper_interface", "upper", el_y[:, 0] >= y1 - h - tol,
             np.abs(el_y[:, 1] - y1) < tol),
            ("lower_interface", "lower", el_y[:, 1] <= y0 + h + tol,
             np.abs(el_y[:, 0] - y0) < tol)):
        rows = inside if inside.any() else touch
        th = float(np.max(el_y[rows, 1]) - np.min(el_y[rows, 0]))
        face = y1 if where == "upper" else y0
        out.append(Region(name, f"the solder within {th * 1e3:.3g} um of the {where} interface "
                                f"(y = {face:g} mm; {int(rows.sum())} elements)",
                          np.repeat(rows[:, None], n_qp, 1), th))
    out.append(Region("joint", f"the whole solder joint ({len(el_y)} elements, {y1 - y0:g} "
                               "mm thick)", np.ones((len(el_y), n_qp), bool), y1 - y0))
    return out


def per_cycle(cum: np.ndarray, base: np.ndarray | None) -> np.ndarray:
    """Per-cycle increments ``(N, n_cycles, n_e, n_qp)`` of a field read at the cycle ends,
    ``cum`` ``(N, n_cycles, n_e, n_qp)``, from ``base`` ``(N, n_e, n_qp)`` (its value at the
    first cycle's start; None: zero)."""
    start = np.zeros_like(cum[:, :1]) if base is None else base[:, None]
    return np.diff(np.concatenate([start, cum], 1), axis=1)


def averages(x: np.ndarray, weight: np.ndarray, regs: list[Region]) -> dict[str, np.ndarray]:
    """Volume averages ``(N, n_cycles)`` per region of ``x`` ``(N, n_cycles, n_e, n_qp)``
    (``weight`` ``(n_e, n_qp)`` mm^2 per unit depth), and ``max``: the largest point value."""
    out = {}
    for r in regs:
        w = np.where(r.mask, weight, 0.0)
        out[r.name] = (x * w).sum((-2, -1)) / w.sum()
    out["max"] = x.max((-2, -1))
    return out


@dataclass(frozen=True)
class Band:
    """A quantity's posterior band.

    Attributes:
        median, lo, hi: the 50, 2.5 and 97.5 % quantiles over the draws (the quantity's
            unit).
        constants_share: the share of the variance due to the calibrated Anand constants,
            in [0, 1].
        n: draws counted (the failed ones are left out).
    """

    median: float
    lo: float
    hi: float
    constants_share: float
    n: int


def constants_share(q: np.ndarray, constants: np.ndarray, others: np.ndarray) -> float:
    """Share ``[0, 1]`` of the variance of ``q`` ``(N,)`` a quadratic regression on
    ``constants`` ``(N, k)`` explains, of what one on ``constants`` and ``others``
    ``(N, j)`` explains (1 with no ``others`` columns: the constants are then the band's only
    source; linear terms alone where the draws are too few for the quadratic; NaN where they
    are too few for those)."""
    if others.shape[1] == 0 or np.var(q) == 0:
        return 1.0

    def explained(X: np.ndarray) -> float:
        Z = (X - X.mean(0)) / np.where(X.std(0) > 0, X.std(0), 1.0)
        cols = [np.ones(len(Z)), *Z.T]
        cols += [Z[:, i] * Z[:, j] for i in range(Z.shape[1]) for j in range(i, Z.shape[1])]
        F = np.stack(cols, 1)
        if F.shape[1] >= len(q):  # too few draws for the quadratic: linear terms alone
            F = F[:, :1 + Z.shape[1]]
        if F.shape[1] >= len(q):
            return float("nan")
        coef, *_ = np.linalg.lstsq(F, q, rcond=None)
        return float(np.var(F @ coef))

    both = explained(np.concatenate([constants, others], 1))
    if not np.isfinite(both):  # fewer draws than the regression's terms: no split
        return float("nan")
    return float(np.clip(explained(constants) / both, 0.0, 1.0)) if both > 0 else 1.0


def band(q: np.ndarray, constants: np.ndarray, others: np.ndarray) -> Band:
    """The :class:`Band` of ``q`` ``(N,)`` over the draws (NaN: failed draws, left out);
    ``constants`` ``(N, k)`` and ``others`` ``(N, j)``: the draws' parameters."""
    ok = np.isfinite(q)
    if not ok.any():
        nan = float("nan")
        return Band(nan, nan, nan, nan, 0)
    lo, med, hi = np.quantile(q[ok], [0.025, 0.5, 0.975])
    share = constants_share(q[ok], constants[ok], others[ok]) if ok.sum() > 2 else float("nan")
    return Band(float(med), float(lo), float(hi), share, int(ok.sum()))
