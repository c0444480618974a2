"""The structured layered mesh (solderpyro.fem.mesh): graded spacings, the specimen's geometry
and layers, counter-clockwise elements, and point location by bilinear weights."""

import numpy as np
import pytest

from solderpyro.fem.mesh import Layer, MeshSpec, build_mesh, graded, locate

#: the reference case (docs/configuration.md): copper [-4, 0], Sn37Pb [0, 0.5],
#: SUS630 [0.5, 4.5] mm, L/2 = 15 mm
LAYERS = (Layer("copper", "copper", -4.0, 0.0, 4, 0.25, "top"),
          Layer("solder", "solder", 0.0, 0.5, 3),
          Layer("steel", "steel", 0.5, 4.5, 4, 0.25, "bottom"))
HALF = 15.0


def _areas(mesh):
    """Shoelace area (mm^2) of every element, positive for counter-clockwise nodes."""
    xy = mesh.nodes[mesh.elems]  # (e, 4, 2)
    x, y = xy[..., 0], xy[..., 1]
    return 0.5 * (x * np.roll(y, -1, 1) - np.roll(x, -1, 1) * y).sum(1)


@pytest.mark.parametrize("toward", ["top", "bottom"])
def test_graded_spacing_is_geometric_with_the_stated_end_ratio(toward):
    """n + 1 points from a to b; consecutive widths in a constant ratio q with
    q^(n-1) = ratio, the small end on the side named (rounding ~1e-15 relative)."""
    a, b, n, ratio = -4.0, 0.0, 6, 0.2
    x = graded(a, b, n, ratio, toward)
    h = np.diff(x)
    assert len(x) == n + 1 and x[0] == a and x[-1] == pytest.approx(b, abs=1e-14)
    assert np.all(h > 0) and h.sum() == pytest.approx(b - a, rel=1e-14)
    end, other = (h[-1], h[0]) if toward == "top" else (h[0], h[-1])
    assert end / other == pytest.approx(ratio, rel=1e-12)
    q = h[1:] / h[:-1]
    np.testing.assert_allclose(q, q[0], rtol=1e-12)


def test_graded_uniform_cases_and_bad_input():
    np.testing.assert_allclose(graded(0.0, 3.0, 3, 0.5, "none"), [0.0, 1.0, 2.0, 3.0])
    np.testing.assert_allclose(graded(0.0, 3.0, 3, 1.0, "top"), [0.0, 1.0, 2.0, 3.0])
    np.testing.assert_allclose(graded(0.0, 2.0, 1, 0.1, "top"), [0.0, 2.0])
    with pytest.raises(ValueError, match="number of elements"):
        graded(0.0, 1.0, 0, 1.0, "none")
    with pytest.raises(ValueError, match="grading ratio"):
        graded(0.0, 1.0, 3, 0.0, "top")
    with pytest.raises(ValueError, match="toward"):
        graded(0.0, 1.0, 3, 0.5, "left")


@pytest.mark.parametrize("half", [True, False])
def test_mesh_covers_the_specimen_with_ccw_elements_in_their_layers(half):
    """Element areas (all > 0: counter-clockwise) sum to the domain's, 8.5 mm x L/2 (half)
    or L (full), to rounding; each layer's elements sum to its own strip; every element's
    centroid lies in its layer's y-range; counts are nx (x2 full) times the rows."""
    spec = MeshSpec(nx=12, x_grading=0.2, half=half)
    mesh = build_mesh(LAYERS, HALF, spec)
    width = HALF if half else 2 * HALF
    A = _areas(mesh)
    n_rows = sum(lay.ny for lay in LAYERS)
    n_cols = spec.nx * (1 if half else 2)
    assert mesh.n_elem == n_rows * n_cols and mesh.n_node == (n_rows + 1) * (n_cols + 1)
    assert mesh.n_col == n_cols + 1
    assert np.all(A > 0)
    assert A.sum() == pytest.approx(width * 8.5, rel=1e-13)
    yc = mesh.nodes[mesh.elems][..., 1].mean(1)
    for k, lay in enumerate(LAYERS):
        sel = mesh.region == k
        assert A[sel].sum() == pytest.approx(width * (lay.y1 - lay.y0), rel=1e-13)
        assert np.all((yc[sel] > lay.y0) & (yc[sel] < lay.y1))
    xs = mesh.nodes[:mesh.n_col, 0]
    assert xs[-1] == pytest.approx(HALF, abs=1e-13)
    if half:
        assert xs[0] == 0.0
        # x grading: last/first element width = 0.2, the fine end at the free edge x = L/2
        assert (xs[-1] - xs[-2]) / (xs[1] - xs[0]) == pytest.approx(0.2, rel=1e-12)
    else:
        np.testing.assert_allclose(xs, -xs[::-1], atol=1e-13)  # mirror image about x = 0


def test_layers_must_share_interfaces():
    bad = (LAYERS[0], Layer("solder", "solder", 0.1, 0.5, 2))
    with pytest.raises(ValueError, match="copper and solder do not share an interface"):
        build_mesh(bad, HALF, MeshSpec(nx=4))


def test_locate_interpolates_bilinear_fields_exactly():
    """The weights are the Q4 shape functions at the point: non-negative, summing to 1, and
    reproducing a bilinear field a + b x + c y + d x y on the (rectangular) element exactly
    (rounding, ~1e-13 of the field's size); at a node the weight is 1 on that node."""
    mesh = build_mesh(LAYERS, HALF, MeshSpec(nx=8))
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(0, HALF, 40), rng.uniform(-4.0, 4.5, 40)]
    pts = np.r_[pts, [[15.0, 4.5], [15.0, -4.0], [0.0, 0.0]]]  # A, B and O of the reference case
    el, w = locate(mesh, pts)
    assert np.all(w >= -1e-12) and np.allclose(w.sum(1), 1.0, atol=1e-14)

    def f(x, y):
        return 1.5 - 0.3 * x + 0.7 * y + 0.02 * x * y

    vals = f(mesh.nodes[:, 0], mesh.nodes[:, 1])
    got = (w * vals[mesh.elems[el]]).sum(1)
    np.testing.assert_allclose(got, f(pts[:, 0], pts[:, 1]), rtol=0, atol=1e-12)
    # each point lies inside the element found
    xy = mesh.nodes[mesh.elems[el]]
    for d in (0, 1):
        assert np.all((xy[..., d].min(1) - 1e-12 <= pts[:, d])
                      & (pts[:, d] <= xy[..., d].max(1) + 1e-12))
    node = mesh.elems[el[-1]][np.argmax(w[-1])]
    assert np.allclose(mesh.nodes[node], [0.0, 0.0]) and w[-1].max() == pytest.approx(1.0)


def test_locate_names_a_point_outside_the_mesh():
    mesh = build_mesh(LAYERS, HALF, MeshSpec(nx=4))
    with pytest.raises(ValueError, match=r"point \(16, 0\) mm lies outside the mesh"):
        locate(mesh, np.array([[1.0, 0.0], [16.0, 0.0]]))
