"""Assembly and static condensation of the linear elastic regions (solderpyro.fem.assembly):
the stiffness has exactly the rigid-body null space, unit thermal loads are the forces of free
expansion, and condensation reproduces the full system (Schur complement, condensed thermal
loads, observation maps) on a one-material block."""

from types import SimpleNamespace

import numpy as np
import pytest
import scipy.sparse as sp

from solderpyro.fem.assembly import condense, linear_system
from solderpyro.fem.mesh import Layer, MeshSpec, build_mesh

STEEL = SimpleNamespace(E=200e3, nu=0.29)  # the reference case (docs/configuration.md), MPa
COPPER = SimpleNamespace(E=130e3, nu=0.34)
LAYERS = (Layer("copper", "copper", -2.0, 0.0, 3, 0.5, "top"),
          Layer("steel", "steel", 0.0, 2.0, 3, 0.5, "bottom"))


def _setup(plane, incompatible, materials=None):
    mesh = build_mesh(LAYERS, 4.0, MeshSpec(nx=4, x_grading=0.5))
    problem = SimpleNamespace(materials=materials or {"copper": COPPER, "steel": STEEL},
                              plane=plane, incompatible_modes=incompatible)
    K, loads = linear_system(mesh, problem, np.arange(mesh.n_elem))
    return mesh, K, loads


def _expansion(mesh, scale=1.0):
    """Dof vector of u = scale * (x, y)."""
    return scale * mesh.nodes.ravel()


@pytest.mark.parametrize("plane", ["stress", "strain"])
@pytest.mark.parametrize("incompatible", [True, False])
def test_stiffness_is_symmetric_with_the_rigid_null_space(plane, incompatible):
    """K is symmetric positive semi-definite with exactly three zero eigenvalues (two
    translations, one rotation), which it maps to zero force (1e-10 of |K|)."""
    mesh, K, _ = _setup(plane, incompatible)
    Kd = K.toarray()
    scale = np.abs(Kd).max()
    np.testing.assert_allclose(Kd, Kd.T, rtol=0, atol=1e-12 * scale)
    ev = np.linalg.eigvalsh(Kd)
    assert np.all(np.abs(ev[:3]) < 1e-10 * ev[-1]) and ev[3] > 1e-6 * ev[-1]
    x, y = mesh.nodes[:, 0], mesh.nodes[:, 1]
    for u in (np.c_[np.ones_like(x), 0 * x], np.c_[0 * x, np.ones_like(x)], np.c_[-y, x]):
        assert np.abs(K @ u.ravel()).max() < 1e-10 * scale


@pytest.mark.parametrize("plane,factor", [("stress", 1.0), ("strain", None)])
def test_unit_thermal_load_is_the_force_of_free_expansion(plane, factor):
    """One material heated: the free expansion u = e (x, y) is stress free, so K u equals the
    unit thermal load exactly (rounding). In plane strain the in-plane free expansion is
    (1 + nu) e (eps_zz = 0), in plane stress e."""
    mesh, K, loads = _setup(plane, True, {"copper": COPPER, "steel": COPPER})
    f = loads["copper"] + loads["steel"]
    e = factor if factor is not None else 1.0 + COPPER.nu
    r = K @ _expansion(mesh, e) - f
    assert np.abs(r).max() < 1e-10 * np.abs(f).max()
    assert np.abs(f).max() > 0  # the boundary carries the loads; interior nodes balance
    assert abs(f[0::2].sum()) < 1e-9 * np.abs(f).max()  # no net force
    assert abs(f[1::2].sum()) < 1e-9 * np.abs(f).max()


def test_condensation_reproduces_the_full_system():
    """Retain the boundary nodes' dofs of a one-material block, condense the interior:
    S is the Schur complement K_rr - K_rc K_cc^-1 K_cr (symmetric); under free thermal
    expansion S u_r = g (the condensed load) and the observation map gives the interior's
    v exactly, H u_r + h = v(interior point) (rounding, 1e-9 relative)."""
    mesh, K, loads = _setup("stress", True, {"copper": STEEL, "steel": STEEL})
    x, y = mesh.nodes[:, 0], mesh.nodes[:, 1]
    edge = (x == x.min()) | (x == x.max()) | (y == y.min()) | (y == y.max())
    r = np.stack([2 * np.nonzero(edge)[0], 2 * np.nonzero(edge)[0] + 1], 1).ravel()
    c = np.setdiff1d(np.arange(2 * mesh.n_node), r)
    inner = np.nonzero(~edge)[0][:3]
    obs = sp.csr_matrix((np.ones(3), (np.arange(3), 2 * inner + 1)), shape=(3, 2 * mesh.n_node))
    extra = sp.csr_matrix((np.ones(2), (np.arange(2), 2 * inner[:2])),
                          shape=(2, 2 * mesh.n_node))
    f = {"steel": loads["copper"] + loads["steel"]}
    cd = condense(K, f, obs, r, c, extra)
    Kd = K.toarray()
    schur = Kd[np.ix_(r, r)] - Kd[np.ix_(r, c)] @ np.linalg.solve(Kd[np.ix_(c, c)],
                                                                   Kd[np.ix_(c, r)])
    np.testing.assert_allclose(cd.S, schur, rtol=0, atol=1e-9 * np.abs(schur).max())
    np.testing.assert_array_equal(cd.S, cd.S.T)
    u = _expansion(mesh)
    g = cd.g["steel"]
    np.testing.assert_allclose(cd.S @ u[r], g, rtol=0, atol=1e-9 * np.abs(g).max())
    np.testing.assert_allclose(cd.H @ u[r] + cd.h["steel"], y[inner], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(cd.Hx @ u[r] + cd.hx["steel"], x[inner[:2]], rtol=1e-9,
                               atol=1e-12)
    assert condense(K, f, obs, r, c).Hx is None
