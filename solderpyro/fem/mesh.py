"""Structured, graded quadrilateral mesh of the layered specimen (mm).

The mesh is a tensor grid of lines ``xs`` (along the length) and ``ys`` (through the layers),
graded toward the free ends and toward the solder layer, where the shear gradients are. A layer
may end before the half length (``Layer.x1``, e.g. a die shorter than its substrate): the grid
then has a line at every layer end, and the cells of a layer beyond its end are no elements.
Elements and nodes keep the grid's row-by-row order (bottom to top, left to right) with the
unused nodes dropped; ``Mesh.cell`` maps grid cells to elements. Elements are counter-clockwise.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Layer:
    """A horizontal layer: region name, material key, y-range (mm), element rows and grading.

    ``grading`` is the ratio of the element height at ``toward`` ("bottom"|"top"|"none") to the
    element height at the opposite side (< 1 refines toward that side). ``x1``: where the layer
    ends along the length, mm (it spans ``[0, x1]``, or ``[-x1, x1]`` in a full model); None:
    the specimen's half length.
    """

    name: str
    material: str
    y0: float
    y1: float
    ny: int
    grading: float = 1.0
    toward: str = "none"
    #: left out of the run store's hash when None (layers then hash as before ends existed)
    x1: float | None = field(default=None, metadata={"omit_in_hash": lambda la: la.x1 is None})


@dataclass(frozen=True)
class XSegment:
    """Elements along one span between consecutive layer ends (``[0, x_a]``, ``[x_a, x_b]``,
    ...): ``nx`` elements, ``grading`` the ratio of the element width at ``toward``
    ("left" or "right" end of the span, or "none") to the width at the other end (< 1 refines
    toward that end).
    """

    nx: int
    grading: float = 1.0
    toward: str = "none"


@dataclass(frozen=True)
class MeshSpec:
    """Resolution along x. ``x_grading``: last/first element width (< 1 refines the free end).

    ``x_segments``: one :class:`XSegment` per span between the distinct layer ends (left to
    right), replacing ``nx`` and ``x_grading``. Empty: ``nx`` elements over ``[0, L/2]``; where
    layers end before L/2, they are shared among the spans in proportion to their lengths (at
    least one each), each span graded by ``x_grading`` toward its right end.
    """

    nx: int = 30
    x_grading: float = 0.2
    half: bool = True
    #: left out of the run store's hash when empty (see Layer.x1)
    x_segments: tuple[XSegment, ...] = field(default=(), metadata={
        "omit_in_hash": lambda m: not m.x_segments})


@dataclass(frozen=True)
class Mesh:
    """Mesh arrays.

    Attributes:
        nodes: ``(n_node, 2)`` coordinates, mm.
        elems: ``(n_elem, 4)`` node indices, counter-clockwise from the lower left.
        region: ``(n_elem,)`` index into ``layers``.
        layers: the layers, bottom to top.
        n_col: grid lines along x (``len(xs)``; nodes per row where every layer spans the
            length).
        xs: ``(n_col,)`` and ys: ``(n_row + 1,)`` the grid lines, mm.
        cell: ``(n_row, n_col - 1)`` element of each grid cell, -1 where there is no material.
    """

    nodes: np.ndarray
    elems: np.ndarray
    region: np.ndarray
    layers: tuple[Layer, ...]
    n_col: int
    xs: np.ndarray
    ys: np.ndarray
    cell: np.ndarray

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


def extent(layer: Layer, half_length: float) -> float:
    """Where ``layer`` ends along x, mm: its ``x1``, or ``half_length`` when None.

    Raises:
        ValueError: naming the layer when ``x1`` is outside ``(0, half_length]``.
    """
    if layer.x1 is None:
        return half_length
    if not 0.0 < layer.x1 <= half_length * (1 + 1e-12):
        raise ValueError(f"layer {layer.name!r}: x1 = {layer.x1:g} mm must lie in "
                         f"(0, {half_length:g}] (the half length)")
    return min(float(layer.x1), half_length)


def layer_ends(layers: tuple[Layer, ...], half_length: float) -> np.ndarray:
    """``(n_span,)`` the distinct layer ends along x, increasing, mm; the last is
    ``half_length`` (ends closer than 1e-9 relative count as one)."""
    ends = sorted({extent(lay, half_length) for lay in layers} | {half_length})
    out = [ends[0]]
    for e in ends[1:]:
        if e - out[-1] > 1e-9 * half_length:
            out.append(e)
    out[-1] = half_length
    return np.array(out)


def on_material(layers: tuple[Layer, ...], half_length: float, xy: tuple[float, float],
                tol: float = 1e-9) -> bool:
    """Whether the point ``xy`` (mm) lies in or on a layer: ``y0 <= y <= y1`` and
    ``|x| <= x1`` of one of them (to ``tol`` mm)."""
    x, y = xy
    return any(lay.y0 - tol <= y <= lay.y1 + tol and abs(x) <= extent(lay, half_length) + tol
               for lay in layers)


def _x_lines(layers: tuple[Layer, ...], half_length: float, spec: MeshSpec) -> np.ndarray:
    """Grid lines on ``[0, L/2]`` ``(n_x + 1,)``, mm: a line at every layer end."""
    ends = layer_ends(layers, half_length)
    segs = spec.x_segments
    if segs and len(segs) != len(ends):
        spans = ", ".join(f"[{a:g}, {b:g}]" for a, b in zip([0.0, *ends[:-1]], ends,
                                                            strict=True))
        raise ValueError(f"mesh.x_segments has {len(segs)} entries; the layers' ends make "
                         f"{len(ends)} spans along x: {spans} mm")
    if not segs and len(ends) == 1:
        return graded(0.0, half_length, spec.nx, spec.x_grading, "top")
    if not segs:  # nx shared among the spans in proportion to their lengths, >= 1 each
        raw = spec.nx * np.diff(np.concatenate([[0.0], ends])) / half_length
        n = np.maximum(np.floor(raw), 1).astype(int)
        while n.sum() < spec.nx:
            n[int(np.argmax(raw - n))] += 1
        segs = tuple(XSegment(int(k), spec.x_grading, "right") for k in n)
    xs, a = [np.array([0.0])], 0.0
    for b, sg in zip(ends, segs, strict=True):
        side = {"left": "bottom", "right": "top"}.get(sg.toward, sg.toward)
        pts = graded(a, float(b), sg.nx, sg.grading, side)
        pts[-1] = b
        xs.append(pts[1:])
        a = float(b)
    return np.concatenate(xs)


def build_mesh(layers: tuple[Layer, ...], half_length: float, spec: MeshSpec) -> Mesh:
    """Mesh of layers stacked in y over x in [0, L/2] (half model) or [-L/2, L/2].

    A layer with ``x1`` spans ``[0, x1]`` (``[-x1, x1]``): the grid has a line at ``x1`` and
    its cells beyond are no elements; the nodes no element uses are dropped.

    Args:
        layers: bottom-to-top layers sharing interfaces (``layers[k].y1 == layers[k+1].y0``).
        half_length: L/2 in mm.
        spec: x resolution and grading.
    Returns:
        the :class:`Mesh`.
    """
    for lo, hi in zip(layers[:-1], layers[1:], strict=False):
        if abs(lo.y1 - hi.y0) > 1e-12:
            raise ValueError(f"layers {lo.name} and {hi.name} do not share an interface")
    xs = _x_lines(layers, half_length, spec)
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
    ext = np.array([extent(lay, half_length) for lay in layers])
    keep = np.abs(nodes[elems][..., 0].mean(1)) < ext[region]  # (n_cell,) cell centroids
    cell = np.full(len(elems), -1)
    cell[keep] = np.arange(int(keep.sum()))
    if not keep.all():  # drop the cells without material and the nodes no element uses
        used = np.unique(elems[keep])
        new = np.full(len(nodes), -1)
        new[used] = np.arange(len(used))
        nodes, elems, region = nodes[used], new[elems[keep]], region[keep]
    return Mesh(nodes, elems, region, tuple(layers), nc, xs, y, cell.reshape(nr - 1, nc - 1))


def _cell_range(lines: np.ndarray, v: float, tol: float) -> list[int]:
    """Indices of the grid cells along one axis containing ``v`` (two on a line), the one
    ``searchsorted`` picks first."""
    n = len(lines) - 1
    k = int(np.clip(np.searchsorted(lines, v) - 1, 0, n - 1))
    return [k] + [m for m in (k - 1, k + 1)
                  if 0 <= m < n and lines[m] - tol <= v <= lines[m + 1] + tol]


def locate(mesh: Mesh, pts: np.ndarray, tol: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """Element index and bilinear shape-function weights of points on the structured mesh.

    A point on the edge between cells is located in the cell ``searchsorted`` finds (the one
    below / left of the line), or in a neighbour when that one has no material.

    Args:
        mesh: the :class:`Mesh`.
        pts: ``(n_pt, 2)`` coordinates, mm (in the meshed domain).
        tol: how far outside the grid (mm) a point may lie.
    Returns:
        ``(elem (n_pt,), weights (n_pt, 4))``, weights in the order of the element's nodes.
    Raises:
        ValueError naming the first point outside the mesh or off the material.
    """
    xs, ys = mesh.xs, mesh.ys
    el, wt = [], []
    for x, y in pts:
        if not (xs[0] - tol <= x <= xs[-1] + tol and ys[0] - tol <= y <= ys[-1] + tol):
            raise ValueError(f"point ({x:g}, {y:g}) mm lies outside the mesh")
        cells = [(j, i) for j in _cell_range(ys, y, tol) for i in _cell_range(xs, x, tol)
                 if mesh.cell[j, i] >= 0]
        if not cells:
            raise ValueError(f"point ({x:g}, {y:g}) mm lies outside the material (beyond the "
                             f"end of every layer at that height)")
        j, i = cells[0]
        r = (x - xs[i]) / (xs[i + 1] - xs[i])
        t = (y - ys[j]) / (ys[j + 1] - ys[j])
        el.append(int(mesh.cell[j, i]))
        wt.append([(1 - r) * (1 - t), r * (1 - t), r * t, (1 - r) * t])
    return np.array(el), np.array(wt)
