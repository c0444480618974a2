"""Q4 kinematics, QM6 incompatible modes and the mean-dilatation B-bar
(solderpyro.fem.elements): rigid motions strain nothing, linear fields are exact, the 2x2
Gauss rule integrates bicubics exactly, areas, QM6's pure bending and B-bar's averaging.
(The patch tests of whole meshes are in tests/verification/test_elastic_fe.py.)"""

import math

import numpy as np
import pytest
import torch

from solderpyro.fem.elements import R2, XI, bbar, edofs, q4_kinematics, qm6_modes, qm6_stiffness
from solderpyro.materials.elastic import plane_elastic

#: a rectangle, a parallelogram and a general convex quad (counter-clockwise), mm
QUADS = np.array([
    [[0.0, 0.0], [2.0, 0.0], [2.0, 0.5], [0.0, 0.5]],
    [[0.0, 0.0], [1.5, 0.2], [2.0, 1.2], [0.5, 1.0]],
    [[-0.3, -0.1], [1.1, -0.4], [1.4, 0.9], [-0.1, 0.7]],
])


def _area(xy):
    x, y = xy[..., 0], xy[..., 1]
    return 0.5 * (x * np.roll(y, -1, -1) - np.roll(x, -1, -1) * y).sum(-1)


def _qp_xy(xy):
    """Physical coordinates ``(e, q, 2)`` of the Gauss points (bilinear map of XI)."""
    r, s = XI[:, 0], XI[:, 1]
    N = 0.25 * np.stack([(1 - r) * (1 - s), (1 + r) * (1 - s), (1 + r) * (1 + s),
                         (1 - r) * (1 + s)], 1)  # (q, 4)
    return np.einsum("qk,ekd->eqd", N, xy)


def _nodal(xy, fu, fv):
    """Element dof vector ``(e, 8)`` (u0, v0, u1, ...) of a displacement field."""
    return np.stack([fu(xy[..., 0], xy[..., 1]), fv(xy[..., 0], xy[..., 1])], -1).reshape(
        len(xy), 8)


def test_weights_sum_to_the_element_areas():
    """sum_q w det J is the exact area of a bilinear quad (det J is linear in (r, s))."""
    _, wdet = q4_kinematics(QUADS)
    np.testing.assert_allclose(wdet.sum(1), _area(QUADS), rtol=1e-14)


@pytest.mark.parametrize("i,j", [(0, 0), (1, 0), (0, 3), (3, 3), (2, 1)])
def test_gauss_rule_integrates_bicubics_exactly_on_a_rectangle(i, j):
    """On a rectangle det J is constant and the map affine, so 2x2 Gauss integrates
    x^i y^j (i, j <= 3) exactly: int_0^2 int_0^0.5 x^i y^j = 2^(i+1)/(i+1) 0.5^(j+1)/(j+1)."""
    xy = QUADS[:1]
    _, wdet = q4_kinematics(xy)
    p = _qp_xy(xy)
    got = (p[..., 0] ** i * p[..., 1] ** j * wdet).sum()
    exact = 2.0 ** (i + 1) / (i + 1) * 0.5 ** (j + 1) / (j + 1)
    assert got == pytest.approx(exact, rel=1e-13)


def test_rigid_motions_strain_nothing_and_linear_fields_are_exact():
    """Partition of unity and isoparametric linear completeness: a translation and an
    infinitesimal rotation give zero strain, and u = (a x + b y, c x + d y) gives the
    constant Mandel strain (a, d, (b + c)/sqrt2) at every Gauss point, on distorted quads too
    (rounding: ~1e-15 of the gradient)."""
    B, _ = q4_kinematics(QUADS)
    for fu, fv in [(lambda x, y: 0 * x + 0.3, lambda x, y: 0 * x - 1.2),
                   (lambda x, y: -0.01 * y, lambda x, y: 0.01 * x)]:
        eps = B @ _nodal(QUADS, fu, fv)[:, None, :, None]
        assert np.abs(eps).max() < 1e-15
    a, b, c, d = 1e-3, -2e-3, 5e-4, 3e-3
    eps = (B @ _nodal(QUADS, lambda x, y: a * x + b * y,
                      lambda x, y: c * x + d * y)[:, None, :, None])[..., 0]
    np.testing.assert_allclose(eps, np.broadcast_to([a, d, (b + c) / R2], eps.shape),
                               rtol=0, atol=1e-17)


def test_inverted_element_is_rejected():
    with pytest.raises(ValueError, match="inverted or degenerate"):
        q4_kinematics(QUADS[:1, ::-1].copy())  # clockwise nodes: det J < 0


def test_edof_order():
    np.testing.assert_array_equal(edofs(np.array([[0, 1, 5, 4]])),
                                  [[0, 1, 2, 3, 10, 11, 8, 9]])


def test_qm6_modes_integrate_to_zero_and_keep_three_rigid_modes():
    """Taylor's correction: sum_q w G = 0 on any quad (the patch test of the incompatible
    modes), and the condensed stiffness is symmetric with exactly the three rigid-body null
    vectors, at most as stiff as plain Q4 (K_Q4 - K_QM6 is positive semi-definite)."""
    B, wdet = q4_kinematics(QUADS)
    G = qm6_modes(QUADS, wdet)
    scale = np.abs(G).max() * wdet.sum(1).max()
    assert np.abs((G * wdet[..., None, None]).sum(1)).max() < 1e-14 * scale
    D = plane_elastic(130e3, 0.34, "stress", dtype=torch.float64)[0].numpy()
    K6 = qm6_stiffness(QUADS, D)
    K4 = np.einsum("eqia,ij,eqjb,eq->eab", B, D, B, wdet)
    for k6, k4 in zip(K6, K4, strict=True):
        np.testing.assert_allclose(k6, k6.T, rtol=0, atol=1e-10 * np.abs(k6).max())
        ev = np.linalg.eigvalsh(k6)
        assert np.all(np.abs(ev[:3]) < 1e-10 * ev[-1]) and ev[3] > 1e-4 * ev[-1]
        assert np.linalg.eigvalsh(k4 - k6).min() > -1e-10 * ev[-1]


def test_qm6_bends_a_rectangle_exactly_where_q4_locks():
    """Pure bending in plane stress, u = k x y, v = -k (x^2 + nu y^2)/2 (sigma_xx = E k y
    only) on the rectangle [-a, a] x [-b, b]: QM6's condensed strain energy equals the exact
    (E k^2 / 2) (2a)(2b^3/3) to rounding, while Q4 (its nodal field has eps_yy = 0 and the
    parasitic shear gamma = k x) stores 1/(1 - nu^2) + (a/b)^2 / (2 (1 + nu)) times it (7.29
    at a/b = 4; the Gauss rule integrates these quadratics exactly)."""
    E, nu, a, b, k = 200e3, 0.29, 2.0, 0.5, 1e-3
    xy = np.array([[[-a, -b], [a, -b], [a, b], [-a, b]]])
    D = plane_elastic(E, nu, "stress", dtype=torch.float64)[0].numpy()
    u = _nodal(xy, lambda x, y: k * x * y, lambda x, y: -0.5 * k * (x * x + nu * y * y))[0]
    exact = 0.5 * E * k * k * (2 * a) * (2 * b ** 3 / 3)
    U6 = 0.5 * u @ qm6_stiffness(xy, D)[0] @ u
    B, wdet = q4_kinematics(xy)
    U4 = 0.5 * u @ np.einsum("eqia,ij,eqjb,eq->ab", B, D, B, wdet) @ u
    assert U6 == pytest.approx(exact, rel=1e-12)
    assert U4 / exact == pytest.approx(1 / (1 - nu**2) + (a / b) ** 2 / (2 * (1 + nu)),
                                       rel=1e-12)


def test_bbar_averages_the_volumetric_strain_only():
    """B-bar: the in-plane volumetric strain is the element's (area-weighted) mean at every
    Gauss point; the deviatoric difference eps_xx - eps_yy and the shear are Q4's."""
    B, wdet = q4_kinematics(QUADS)
    Bb = bbar(B, wdet)
    u = np.random.default_rng(1).standard_normal((len(QUADS), 8)) * 1e-3
    e4 = (B @ u[:, None, :, None])[..., 0]
    eb = (Bb @ u[:, None, :, None])[..., 0]
    vol4, volb = e4[..., 0] + e4[..., 1], eb[..., 0] + eb[..., 1]
    mean = (vol4 * wdet).sum(1) / wdet.sum(1)
    np.testing.assert_allclose(volb, np.broadcast_to(mean[:, None], volb.shape), atol=1e-17)
    np.testing.assert_allclose(eb[..., 0] - eb[..., 1], e4[..., 0] - e4[..., 1], atol=1e-17)
    np.testing.assert_array_equal(eb[..., 2], e4[..., 2])
    assert math.isclose(R2, math.sqrt(2.0))
