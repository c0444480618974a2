"""Layers of different lengths (Layer.x1): the mesh drops the cells beyond a layer's end, and
the rest of the FE model (assembly, boundary conditions, point location, the solver) works on
what remains. A die attach: a silicon die on a solder layer of its own length, on a longer
copper substrate."""

import dataclasses

import numpy as np
import pytest
import scipy.sparse.linalg as spla
import torch

from solderpyro.fem.assembly import linear_system
from solderpyro.fem.band import elastic_stress_operator
from solderpyro.fem.elements import XI, edofs, q4_kinematics
from solderpyro.fem.loading import ThermalCycle, TimeStepping
from solderpyro.fem.mesh import Layer, MeshSpec, XSegment, build_mesh, locate
from solderpyro.fem.operators import dirichlet
from solderpyro.fem.problem import REFERENCE_LAYERS, SN37PB, Elastic, Problem
from solderpyro.fem.solver import SpecimenSolver
from solderpyro.materials.elastic import plane_elastic
from solderpyro.params import ANAND_NAMES, LIU2008

#: elastic die attach: Si die 0.5 mm, solder 0.05 mm (both of half length 3 mm) on Cu 1 mm
#: (half length 5 mm); plane strain; uniform cooling by 100 K from stress-free
MATS = {"silicon": Elastic(169e3, 0.28, 2.6e-6), "solder": Elastic(32e3, 0.35, 23.5e-6),
        "copper": Elastic(130e3, 0.34, 16.3e-6)}
HALF, EDGE, DT = 5.0, 3.0, -100.0


def _die_attach(k: int):
    layers = (Layer("cu", "copper", -1.0, 0.0, 4 * k, 0.3, "top"),
              Layer("solder", "solder", 0.0, 0.05, 2 * k, x1=EDGE),
              Layer("die", "silicon", 0.05, 0.55, 3 * k, 0.5, "bottom", x1=EDGE))
    spec = MeshSpec(x_segments=(XSegment(12 * k, 0.2, "right"), XSegment(8 * k, 0.5, "left")))
    return layers, spec


def _elastic_solve(layers, spec):
    """Displacements of uniform cooling by DT and the stresses ``(n_elem, n_qp, 3)`` MPa
    (xx, yy, sqrt2 xy) at the Gauss points, every element elastic."""
    pr = Problem(layers=layers, materials=MATS, half_length=HALF, mesh=spec, plane="strain")
    mesh = build_mesh(layers, HALF, spec)
    K, loads = linear_system(mesh, pr, np.arange(mesh.n_elem))
    F = sum(loads[m] * MATS[m].alpha * DT for m in loads)
    fixed, _ = dirichlet(mesh, (0.0, 0.0))
    free = np.setdiff1d(np.arange(2 * mesh.n_node), fixed)
    u = np.zeros(2 * mesh.n_node)
    u[free] = spla.spsolve(K[free][:, free].tocsc(), F[free])
    sig = np.zeros((mesh.n_elem, 4, 3))
    for r, lay in enumerate(layers):
        els = np.nonzero(mesh.region == r)[0]
        m = MATS[lay.material]
        D, d = (t.numpy() for t in plane_elastic(m.E, m.nu, "strain", dtype=torch.float64))
        P = elastic_stress_operator(mesh.nodes[mesh.elems[els]], D, True)  # (e, q, 3, 8)
        sig[els] = np.einsum("eqia,ea->eqi", P, u[edofs(mesh.elems[els])]) - d * m.alpha * DT
    return mesh, sig


def test_full_length_layers_give_the_rectangular_mesh_bit_for_bit():
    """x1 equal to the half length (or None) is the full rectangular grid: the same arrays,
    every cell an element in row-major order, every node used."""
    spec = MeshSpec(nx=10, x_grading=0.2)
    ref = build_mesh(REFERENCE_LAYERS, 15.0, spec)
    full = tuple(dataclasses.replace(lay, x1=15.0) for lay in REFERENCE_LAYERS)
    for half in (True, False):
        sp = dataclasses.replace(spec, half=half)
        a, b = build_mesh(REFERENCE_LAYERS, 15.0, sp), build_mesh(full, 15.0, sp)
        for f in ("nodes", "elems", "region", "xs", "ys", "cell"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
        np.testing.assert_array_equal(a.cell.ravel(), np.arange(a.n_elem))
    assert ref.n_node == ref.n_col * len(ref.ys)


def test_full_length_layers_give_the_same_solve_bit_for_bit():
    """The solver on the reference layers with x1 = L/2 reproduces x1 = None exactly (a short
    cycle on a coarse mesh, Liu's constants)."""
    layers = tuple(dataclasses.replace(lay, ny=max(lay.ny // 4, 1)) for lay in REFERENCE_LAYERS)
    base = Problem(layers=layers, mesh=MeshSpec(nx=8), cycle=ThermalCycle((0.0, 600.0, 900.0),
                   (25.0, 75.0, 75.0)), stepping=TimeStepping(dT_max=10.0))
    full = dataclasses.replace(base, layers=tuple(dataclasses.replace(lay, x1=15.0)
                                                  for lay in layers))
    p = torch.tensor([[LIU2008[k] for k in ANAND_NAMES]], dtype=torch.float64)
    va = SpecimenSolver(base).solve(p, (600.0, 900.0)).V
    vb = SpecimenSolver(full).solve(p, (600.0, 900.0)).V
    assert torch.equal(va, vb)


@pytest.mark.parametrize("half", [True, False])
def test_short_layers_end_at_their_x1_with_no_loose_nodes(half):
    """Every element lies within its layer's extent and the element areas sum to the layers'
    areas; every node belongs to an element (a node without one would make the stiffness
    singular); the grid has a line at the die edge; elements keep the row-major order."""
    layers, spec = _die_attach(1)
    spec = dataclasses.replace(spec, half=half)
    mesh = build_mesh(layers, HALF, spec)
    w = 1 if half else 2
    xy = mesh.nodes[mesh.elems]
    x, y = xy[..., 0], xy[..., 1]
    area = 0.5 * (x * np.roll(y, -1, 1) - np.roll(x, -1, 1) * y).sum(1)
    assert np.all(area > 0)
    for r, lay in enumerate(layers):
        sel = mesh.region == r
        ext = HALF if lay.x1 is None else lay.x1
        assert np.abs(x[sel]).max() == pytest.approx(ext, abs=1e-12)
        assert area[sel].sum() == pytest.approx(w * ext * (lay.y1 - lay.y0), rel=1e-12)
    assert np.array_equal(np.unique(mesh.elems), np.arange(mesh.n_node))
    assert np.min(np.abs(mesh.xs - EDGE)) == 0.0
    yc, xc = y.mean(1), x.mean(1)
    order = np.lexsort((xc, yc))
    np.testing.assert_array_equal(order, np.arange(mesh.n_elem))
    n_under = 12 * (1 if half else 2)
    assert (mesh.region == 1).sum() == 2 * n_under  # solder: 2 rows under the die only


def test_die_attach_cooling_equilibrium_and_a_free_overhang():
    """Uniform cooling of an elastic die attach: through every vertical cut (the Gauss lines)
    the axial force and moment summed over the layers vanish (the part beyond the cut is
    free), to 1e-6 of the integral of |sigma_xx| on both meshes (the integration of the
    elements' stresses along a Gauss line satisfies equilibrium exactly; the residual is the
    linear solve's rounding); the substrate's overhang more than one substrate thickness from
    the die edge carries less than 1 % of the largest stress in the substrate under the die."""
    for k in (1, 2):
        mesh, sig = _elastic_solve(*_die_attach(k))
        xy = mesh.nodes[mesh.elems]
        _, wdet = q4_kinematics(xy)
        dx = xy[:, 1, 0] - xy[:, 0, 0]
        xq = xy[:, 0, 0][:, None] + 0.5 * dx[:, None] * (1 + XI[:, 0])  # (e, q)
        yq = xy[:, 0, 1][:, None] + 0.5 * (xy[:, 3, 1] - xy[:, 0, 1])[:, None] * (1 + XI[:, 1])
        dy = wdet / (0.5 * dx[:, None])  # each Gauss point's share of the cut, mm
        sx = sig[..., 0]
        cuts = np.unique(np.round(xq, 12))
        assert len(cuts) == 2 * len(mesh.xs[:-1])
        for xc in cuts:
            on = np.abs(xq - xc) < 1e-10
            N, scale = (sx * dy)[on].sum(), (np.abs(sx) * dy)[on].sum()
            M = (sx * dy * yq)[on].sum()
            assert abs(N) < 1e-6 * scale and abs(M) < 1e-6 * scale, (k, xc)
        cu = (mesh.region == 0)[:, None]
        under = np.abs(sig)[np.broadcast_to(cu & (xq < EDGE - 1.0), xq.shape)].max()
        far = np.abs(sig)[np.broadcast_to(cu & (xq > EDGE + 1.0), xq.shape)].max()
        assert under > 50.0  # MPa: the substrate is loaded under the die
        assert far < 0.01 * under, (k, far, under)


def test_points_off_the_material_are_refused():
    """Locating a point above the substrate beyond the die edge fails, naming the point; points
    on the die's corner and the substrate's far corner are found, with weights summing to 1."""
    layers, spec = _die_attach(1)
    mesh = build_mesh(layers, HALF, spec)
    with pytest.raises(ValueError, match=r"point \(4, 0.3\) mm lies outside the material"):
        locate(mesh, np.array([[4.0, 0.3]]))
    el, w = locate(mesh, np.array([[EDGE, 0.55], [HALF, -1.0], [4.0, 0.0], [EDGE, 0.0]]))
    np.testing.assert_allclose(w.sum(1), 1.0, rtol=1e-14)
    # a point on an interface is located in the cell below it
    assert [mesh.layers[mesh.region[e]].name for e in el] == ["die", "cu", "cu", "cu"]
    pr = Problem(layers=layers, materials={**MATS, "solder": SN37PB}, half_length=HALF,
                 mesh=spec, points={"P": (4.0, 0.3)})
    with pytest.raises(ValueError, match=r"\(4, 0.3\) mm lies outside the material"):
        SpecimenSolver(pr)


def test_layer_ends_and_segments_are_checked():
    layers, spec = _die_attach(1)
    with pytest.raises(ValueError, match="x_segments has 1 entries.*2 spans.*\\[0, 3\\], "
                                         "\\[3, 5\\]"):
        build_mesh(layers, HALF, MeshSpec(x_segments=(XSegment(4),)))
    bad = (layers[0], dataclasses.replace(layers[1], x1=6.0), layers[2])
    with pytest.raises(ValueError, match="layer 'solder': x1 = 6 mm"):
        build_mesh(bad, HALF, spec)
    # without segments nx is shared in proportion to the spans: 3 + 2 of 5
    mesh = build_mesh(layers, HALF, MeshSpec(nx=5, x_grading=1.0))
    np.testing.assert_allclose(mesh.xs, [0.0, 1.0, 2.0, 3.0, 4.0, 5.0], atol=1e-14)
