"""Structured, graded quadrilateral mesh of the layered specimen (mm).

Nodes are numbered row by row (``node = j*(n_col) + i``), elements counter-clockwise. The mesh
is graded toward the free end (x = L/2) and toward the solder layer, where the shear gradients are.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Layer:
    """A horizontal layer: region name, material key, y-range (mm), element rows and grading.

    ``grading`` is the ratio of the element height at ``toward`` ("bottom"|"top"|"none") to the
    element height at the opposite side (< 1 refines toward that side).
    """

    name: str
    material: str
    y0: float
    y1: float
    ny: int
    grading: float = 1.0
    toward: str = "none"


@dataclass(frozen=True)
class MeshSpec:
    """Resolution along x. ``x_grading``: last/first element width (< 1 refines the free end)."""

    nx: int = 30
    x_grading: float = 0.2
    half: bool = True


@dataclass(frozen=True)
class Mesh:
    """Mesh arrays.

    Attributes:
        nodes: ``(n_node, 2)`` coordinates, mm.
        elems: ``(n_elem, 4)`` node indices, counter-clockwise.
        region: ``(n_elem,)`` index into ``layers``.
        layers: the layers, bottom to top.
        n_col: nodes per row.
    """

    nodes: np.ndarray
    elems: np.ndarray
    region: np.ndarray
    layers: tuple[Layer, ...]
    n_col: int

    @property
    def n_node(self) -> int:
        return self.nodes.shape[0]

    @property
    def n_elem(self) -> int:
        return self.elems.shape[0]


def graded(a: float, b: float, n: int, ratio: float, toward: str) -> np.ndarray:
    """``n + 1`` points on ``[a, b]`` with geometric spacing; ``ratio`` = h(toward) / h(other)."""
    if n < 1:
        raise ValueError(f"number of elements must be >= 1, got {n}")
    if ratio <= 0:
        raise ValueError(f"grading ratio must be > 0, got {ratio}")
    if toward == "none" or n == 1 or ratio == 1.0:
        return np.linspace(a, b, n + 1)
    q = ratio ** (1.0 / (n - 1))
    h = q ** np.arange(n)  # first -> last grows by ratio
    if toward == "bottom":  # small at a: h increasing away from a means reverse
        h = h[::-1]
    elif toward != "top":
        raise ValueError(f"toward must be 'bottom', 'top' or 'none', got {toward!r}")
    # h currently goes from 1 (at a) ... ratio (at b) for toward='top'
    x = np.concatenate([[0.0], np.cumsum(h)])
    return a + (b - a) * x / x[-1]


def build_mesh(layers: tuple[Layer, ...], half_length: float, spec: MeshSpec) -> Mesh:
    """Mesh of layers stacked in y over x in [0, L/2] (half model) or [-L/2, L/2].

    Args:
        layers: bottom-to-top layers sharing interfaces (``layers[k].y1 == layers[k+1].y0``).
        half_length: L/2 in mm.
        spec: x resolution and grading.
    """
    for lo, hi in zip(layers[:-1], layers[1:], strict=False):
        if abs(lo.y1 - hi.y0) > 1e-12:
            raise ValueError(f"layers {lo.name} and {hi.name} do not share an interface")
    xs = graded(0.0, half_length, spec.nx, spec.x_grading, "top")
    if not spec.half:
        xs = np.concatenate([-xs[::-1], xs[1:]])
    ys = [np.array([layers[0].y0])]
    rows = []
    for k, lay in enumerate(layers):
        ys.append(graded(lay.y0, lay.y1, lay.ny, lay.grading, lay.toward)[1:])
        rows += [k] * lay.ny
    y = np.concatenate(ys)
    nc, nr = len(xs), len(y)
    X, Y = np.meshgrid(xs, y)
    nodes = np.stack([X.ravel(), Y.ravel()], 1)
    i, j = np.meshgrid(np.arange(nc - 1), np.arange(nr - 1))
    n0 = (j * nc + i).ravel()
    elems = np.stack([n0, n0 + 1, n0 + nc + 1, n0 + nc], 1)
    region = np.repeat(np.array(rows), nc - 1)
    return Mesh(nodes, elems, region, tuple(layers), nc)


def locate(mesh: Mesh, pts: np.ndarray, tol: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """Element index and bilinear shape-function weights of points on the structured mesh.

    Args:
        pts: ``(n_pt, 2)`` coordinates, mm (in the meshed domain).
    Returns:
        ``(elem (n_pt,), weights (n_pt, 4))``.
    Raises:
        ValueError naming the first point outside the mesh.
    """
    nc = mesh.n_col
    xs = mesh.nodes[:nc, 0]
    ys = mesh.nodes[::nc, 1]
    el, wt = [], []
    for x, y in pts:
        if not (xs[0] - tol <= x <= xs[-1] + tol and ys[0] - tol <= y <= ys[-1] + tol):
            raise ValueError(f"point ({x:g}, {y:g}) mm lies outside the mesh")
        i = int(np.clip(np.searchsorted(xs, x) - 1, 0, nc - 2))
        j = int(np.clip(np.searchsorted(ys, y) - 1, 0, len(ys) - 2))
        r = (x - xs[i]) / (xs[i + 1] - xs[i])
        t = (y - ys[j]) / (ys[j + 1] - ys[j])
        el.append(j * (nc - 1) + i)
        wt.append([(1 - r) * (1 - t), r * (1 - t), r * t, (1 - r) * t])
    return np.array(el), np.array(wt)
