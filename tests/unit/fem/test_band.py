"""The elasto-plastic band of a linear region (solderpyro.fem.band): which elements join it,
uniform strain through the condensed QM6 stress operator, and the J2 return at band points in
plane stress (consistency and the pure-shear closed form). The elastic band against the
condensed QM6 bars and the reference-mesh selection are in
tests/unit/fem/test_band_plasticity.py."""

import math

import numpy as np
import pytest
import torch

from solderpyro.fem.band import (
    BandData,
    adjacent_elements,
    band_elements,
    band_update,
    elastic_stress_operator,
)
from solderpyro.fem.elements import q4_kinematics, qm6_modes
from solderpyro.fem.mesh import Layer, MeshSpec, build_mesh
from solderpyro.materials.elastic import bulk_shear, plane_elastic
from solderpyro.materials.integrate import PointState

F64 = torch.float64
E_CU, NU_CU = 130e3, 0.34  # the reference case (docs/configuration.md), MPa
LAYERS = (Layer("copper", "copper", -4.0, 0.0, 6, 0.3, "top"),
          Layer("solder", "solder", 0.0, 0.5, 2),
          Layer("steel", "steel", 0.5, 4.5, 3, 0.3, "bottom"))
NONLIN = np.array([False, True, False])


@pytest.fixture(scope="module")
def mesh():
    return build_mesh(LAYERS, 15.0, MeshSpec(nx=5))


def test_band_grows_with_depth_and_holds_only_near_elements(mesh):
    """Every band element is copper with every node within ``depth`` of the solder; every
    copper element left out has a node beyond it; a deeper band contains the shallower one;
    the ring is copper, outside the band, and shares a node with it."""
    y = mesh.nodes[mesh.elems][..., 1]
    cu = np.array([LAYERS[r].material == "copper" for r in mesh.region])
    prev = np.array([], dtype=int)
    for depth in (0.2, 0.8, 1.75, 4.0):
        el = band_elements(mesh, "copper", NONLIN, depth)
        assert np.all(cu[el]) and np.all(y[el].min(1) >= -depth - 1e-9)
        out = np.setdiff1d(np.nonzero(cu)[0], el)
        assert np.all(y[out].min(1) < -depth)
        assert set(prev) <= set(el)
        prev = el
        ring = adjacent_elements(mesh, el, "copper")
        assert not set(ring) & set(el) and np.all(cu[ring])
        band_nodes = set(mesh.elems[el].ravel())
        assert all(band_nodes & set(mesh.elems[e]) for e in ring)
    assert len(prev) == cu.sum()  # 4 mm: the whole copper bar
    assert len(adjacent_elements(mesh, prev, "copper")) == 0


@pytest.mark.parametrize("incompatible", [True, False])
def test_stress_operator_gives_D_eps_under_uniform_strain(mesh, incompatible):
    """A linear displacement field strains every element uniformly; the incompatible modes
    integrate to zero, so they take no part, and the stress is D eps at every Gauss point
    (rounding, 1e-10 of the stress)."""
    el = band_elements(mesh, "copper", NONLIN, 1.0)
    xy = mesh.nodes[mesh.elems[el]]
    D = plane_elastic(E_CU, NU_CU, "stress", dtype=F64)[0].numpy()
    P = elastic_stress_operator(xy, D, incompatible)
    a, b, c, d = 1e-3, 4e-4, -2e-4, -6e-4
    ue = np.stack([a * xy[..., 0] + b * xy[..., 1], c * xy[..., 0] + d * xy[..., 1]],
                  -1).reshape(len(el), 8)
    sig = (P @ ue[:, None, :, None])[..., 0]
    ref = D @ np.array([a, d, (b + c) / math.sqrt(2.0)])
    np.testing.assert_allclose(sig, np.broadcast_to(ref, sig.shape), rtol=0,
                               atol=1e-10 * np.abs(ref).max())


def _band(mesh, depth, H):
    el = band_elements(mesh, "copper", NONLIN, depth)
    xy = mesh.nodes[mesh.elems[el]]
    B, wdet = q4_kinematics(xy)
    G = qm6_modes(xy, wdet)
    band = BandData(torch.as_tensor(G), torch.as_tensor(G * wdet[..., None, None]), E_CU,
                    NU_CU, H, "stress", "copper")
    return el, torch.as_tensor(B), band


def _eps_u(B, xy, grad):
    """Compatible strain ``(1, n_eb, n_qp, 3)`` of u = grad @ (x, y)."""
    ue = np.einsum("ij,ekj->eki", grad, xy).reshape(len(xy), 8)
    return (B @ torch.as_tensor(ue)[:, None, :, None])[..., 0][None]


def test_pure_shear_band_return_matches_the_closed_form(mesh):
    """Uniform pure shear gamma (u = gamma y): sigma_zz stays 0 with eps_zz = 0, and the
    radial return gives ebar = (sqrt3 G gamma - sigma_y) / (3G + H) and the shear stress
    tau = (sigma_y + H ebar) / sqrt3 at every point (1e-10 relative: closed form, local
    solve at rounding)."""
    sy, H, gamma = 50.0, 1000.0, 2e-3
    el, B, band = _band(mesh, 1.0, H)
    xy = mesh.nodes[mesh.elems[el]]
    eps_u = _eps_u(B, xy, np.array([[0.0, gamma], [0.0, 0.0]]))
    shape = (1, len(el), 4)
    st = PointState(torch.zeros(*shape, 4, dtype=F64), torch.zeros(shape, dtype=F64),
                    torch.zeros(shape, dtype=F64))
    sig, _, st1, dg, _ = band_update(band, eps_u, st, 0.0, torch.full((1, 1, 1), sy, dtype=F64))
    _, G = bulk_shear(E_CU, NU_CU)
    ebar = (math.sqrt(3.0) * G * gamma - sy) / (3 * G + H)
    assert ebar > 0  # the point yields
    tau = (sy + H * ebar) / math.sqrt(3.0)
    torch.testing.assert_close(dg, torch.full_like(dg, ebar), rtol=1e-10, atol=0)
    torch.testing.assert_close(st1.s, torch.full_like(dg, ebar), rtol=1e-10, atol=0)
    torch.testing.assert_close(sig[..., 2] / math.sqrt(2.0), torch.full_like(dg, tau),
                               rtol=1e-10, atol=0)
    assert sig[..., :2].abs().max() < 1e-9 * tau


def test_band_points_sit_on_the_yield_surface_after_a_plastic_step(mesh):
    """Uniform combined tension and shear, heated copper (eps_th = 5e-4), plane stress: where
    a point flowed, the von Mises stress of (sxx, syy, 0, sxy) is sigma_y + H ebar (the
    return's consistency, 1e-9 relative: the local eps_zz solve converges to 1e-12 of the
    stress); elastic points (huge sigma_y) follow Hooke's plane-stress law exactly."""
    H = 500.0
    el, B, band = _band(mesh, 1.0, H)
    xy = mesh.nodes[mesh.elems[el]]
    eps_u = _eps_u(B, xy, np.array([[2.5e-3, 1.5e-3], [0.0, -4e-4]]))
    shape = (2, len(el), 4)
    st = PointState(torch.zeros(*shape, 4, dtype=F64), torch.zeros(shape, dtype=F64),
                    torch.zeros(shape, dtype=F64))
    eps_u = eps_u.expand(2, -1, -1, -1)
    sy = torch.tensor([60.0, 1e6], dtype=F64)[:, None, None]
    sig, _, st1, dg, _ = band_update(band, eps_u, st, 5e-4, sy)
    assert bool((dg[0] > 0).all()) and bool((dg[1] == 0).all())
    sxx, syy, sxy = sig[0, ..., 0], sig[0, ..., 1], sig[0, ..., 2] / math.sqrt(2.0)
    q = torch.sqrt(sxx**2 - sxx * syy + syy**2 + 3 * sxy**2)
    torch.testing.assert_close(q, 60.0 + H * st1.s[0], rtol=1e-9, atol=0)
    D, d_th = plane_elastic(E_CU, NU_CU, "stress", dtype=F64)
    ref = eps_u[1] @ D.T - 5e-4 * d_th
    torch.testing.assert_close(sig[1], ref, rtol=1e-10, atol=1e-10 * ref.abs().max().item())
