"""J2 radial return (solderpyro.materials.j2) and the elasto-plastic band of a linear region
(solderpyro.fem.band): consistent tangent and derivatives against finite differences, the
elastic branch and the elastic band against the condensed QM6 bars, band selection."""

import numpy as np
import pytest
import torch

from solderpyro.effects import EFFECTS
from solderpyro.fem.band import (
    BandData,
    adjacent_elements,
    band_elements,
    band_update,
    elastic_stress_operator,
    mode_correction,
)
from solderpyro.fem.elements import q4_kinematics, qm6_modes, qm6_stiffness
from solderpyro.fem.mesh import build_mesh
from solderpyro.fem.problem import COPPER, Problem
from solderpyro.materials.elastic import bulk_shear, iso_3d, plane_elastic
from solderpyro.materials.integrate import PointState
from solderpyro.materials.j2 import j2_update

F64 = torch.float64
E, NU, H = COPPER.E, COPPER.nu, 1000.0


def _state(shape, ebar=0.0, eps_p=None):
    ep = torch.zeros(*shape, 4, dtype=F64) if eps_p is None else eps_p
    return PointState(ep, torch.full(shape, ebar, dtype=F64), torch.zeros(shape, dtype=F64))


def _strains(n, scale, seed=0):
    g = torch.Generator().manual_seed(seed)
    return scale * (2.0 * torch.rand(n, 4, generator=g, dtype=F64) - 1.0)


@pytest.mark.parametrize("scale", [1e-4, 2e-3])
def test_j2_tangent_matches_finite_differences(scale):
    """Consistent tangent (factored form) vs central differences of the return, on the
    elastic (scale 1e-4: q_tr ~ 10 MPa < sigma_y) and the plastic branch (2e-3), with a
    previous plastic strain and hardening: 1e-7 relative (h = 1e-8 on strains ~1e-3)."""
    eps = _strains(16, scale)
    ep0 = _strains(16, 2e-4, seed=1)
    ep0[:, :3] -= ep0[:, :3].mean(-1, keepdim=True)  # deviatoric
    st = _state((16,), 0.01, ep0)
    sig, _, C, dg = j2_update(eps, st, 1e-4, E, NU, 30.0, H)
    assert bool((dg > 0).any()) == (scale > 1e-3)
    h = 1e-8
    fd = torch.stack([(j2_update(eps + h * e, st, 1e-4, E, NU, 30.0, H)[0]
                       - j2_update(eps - h * e, st, 1e-4, E, NU, 30.0, H)[0]) / (2 * h)
                      for e in torch.eye(4, dtype=F64)], -1)
    err = ((C.full() - fd).abs().max() / fd.abs().max()).item()
    assert err < 1e-7, err


def test_j2_elastic_branch_is_the_elastic_law():
    """Below yield the return is the elastic law (1e-12 relative) and changes no state."""
    eps = _strains(8, 1e-5)
    st = _state((8,), 0.02)
    sig, new, C, dg = j2_update(eps, st, 2e-5, E, NU, 50.0, H)
    K, G = bulk_shear(E, NU)
    m = torch.tensor([1.0, 1.0, 1.0, 0.0], dtype=F64)
    ref = (iso_3d(torch.tensor(K, dtype=F64), torch.tensor(G, dtype=F64))
           @ (eps - 2e-5 * m)[..., None])[..., 0]
    assert torch.allclose(sig, ref, rtol=1e-12, atol=1e-12)
    assert torch.equal(dg, torch.zeros_like(dg)) and torch.equal(new.s, st.s)
    assert torch.equal(new.eps_p, st.eps_p)


def test_j2_autograd_wrt_yield_stress_and_state():
    """d(sigma, ebar)/d(sigma_y, ebar_n, eps_th) by autograd vs central differences (1e-7)."""
    eps = _strains(6, 2e-3, seed=3)
    sy = torch.tensor(40.0, dtype=F64, requires_grad=True)
    eb = torch.full((6,), 0.005, dtype=F64, requires_grad=True)
    et = torch.tensor(1e-4, dtype=F64, requires_grad=True)
    w = torch.linspace(-1.0, 1.0, 24, dtype=F64).reshape(6, 4)

    def f(sy, eb, et):
        sig, new, _, _ = j2_update(eps, PointState(torch.zeros(6, 4, dtype=F64), eb,
                                                   torch.zeros(6, dtype=F64)),
                                   et, E, NU, sy, H, tangent=False)
        return (sig * w).sum() + 1e3 * new.s.sum()

    g = torch.autograd.grad(f(sy, eb, et), (sy, eb, et))
    with torch.no_grad():
        for val, gi, h in ((sy, g[0], 1e-4), (et, g[2], 1e-10)):
            fd = (f(*(val + h if v is val else v for v in (sy, eb, et)))
                  - f(*(val - h if v is val else v for v in (sy, eb, et)))) / (2 * h)
            assert torch.allclose(gi, fd, rtol=1e-7), (gi, fd)
        e0 = torch.zeros(6, dtype=F64)
        e0[2] = 1e-6
        fd = (f(sy, eb + e0, et) - f(sy, eb - e0, et)) / 2e-6
        assert torch.allclose(g[1][2], fd, rtol=1e-7), (g[1][2], fd)


# ------------------------------------------------------------------ the band

def _reference_band(depth=EFFECTS["copper_plasticity"].depth):
    pr = Problem()
    mesh = build_mesh(pr.layers, pr.half_length, pr.mesh)
    nonlin = np.array([pr.materials[lay.material].nonlinear for lay in mesh.layers])
    return pr, mesh, band_elements(mesh, "copper", nonlin, depth)


def test_band_selection_on_the_reference_mesh():
    """The default depth 1.75 mm: the five copper element rows next to the solder (down to
    y = -1.746 mm), every column; the ring around it is the sixth row."""
    pr, mesh, el = _reference_band()
    y = mesh.nodes[mesh.elems[el]][..., 1]
    assert len(el) == 5 * pr.mesh.nx and y.max() <= 0.0 and y.min() >= -1.75
    ring = adjacent_elements(mesh, el, "copper")
    yr = mesh.nodes[mesh.elems[ring]][..., 1]
    assert len(ring) == pr.mesh.nx and yr.max() == pytest.approx(y.min())


def _band_data(mesh, el, plane="stress"):
    xy = mesh.nodes[mesh.elems[el]]
    _, wdet = q4_kinematics(xy)
    G = qm6_modes(xy, wdet)
    return BandData(torch.as_tensor(G), torch.as_tensor(G * wdet[..., None, None]), E, NU,
                    H, plane, "copper")


@pytest.mark.parametrize("plane", ["stress", "strain"])
def test_elastic_band_element_is_qm6(plane):
    """Below yield a band element (local modes and eps_zz solved) is the condensed QM6 element
    of the bars: force sum_q w B^T sigma = K_QM6 u_e - f_th and tangent K_uu - K_ua K_aa^-1
    K_au = K_QM6, for random nodal displacements (1e-9 relative)."""
    _, mesh, el = _reference_band(0.3)
    xy = mesh.nodes[mesh.elems[el]]
    B, wdet = q4_kinematics(xy)
    band = _band_data(mesh, el, plane)
    g = torch.Generator().manual_seed(5)
    ue = 1e-4 * torch.randn(2, len(el), 8, generator=g, dtype=F64)  # (b, n_eb, 8) mm
    Bt = torch.as_tensor(B)
    eps_u = (Bt @ ue[:, :, None, :, None])[..., 0]  # (b, n_eb, n_qp, 3)
    et = torch.tensor([2e-4, -1e-4], dtype=F64)[:, None, None]
    st = _state((2, len(el), 4))
    sy = torch.full((2, 1, 1), 1e4, dtype=F64)
    sig, C, _, dg, _ = band_update(band, eps_u, st, et, sy)
    assert torch.equal(dg, torch.zeros_like(dg))
    Bw = Bt * torch.as_tensor(wdet)[..., None, None]
    f = (Bw.transpose(-1, -2) @ sig[..., None])[..., 0].sum(2)  # (b, n_eb, 8)
    D, d_th = (a.numpy() for a in plane_elastic(E, NU, plane, dtype=F64))
    Kq = torch.as_tensor(qm6_stiffness(xy, D))
    fth = torch.as_tensor(np.einsum("eqia,i,eq->ea", B, d_th, wdet))
    ref = (Kq @ ue[..., None])[..., 0] - et[:, :, 0, None] * fth
    assert ((f - ref).abs().max() / ref.abs().max()).item() < 1e-9
    Kb = (Bw.transpose(-1, -2) @ C @ Bt).sum(2) - mode_correction(band, Bt, Bw, C)
    assert ((Kb - Kq).abs().max() / Kq.abs().max()).item() < 1e-9


def test_elastic_stress_operator_matches_the_band_update():
    """The elastic stress recovery of the baseline path's check (QM6 modes condensed) gives
    the band update's elastic stress (1e-9 relative)."""
    _, mesh, el = _reference_band(0.3)
    xy = mesh.nodes[mesh.elems[el]]
    B, _ = q4_kinematics(xy)
    D, d_th = (a.numpy() for a in plane_elastic(E, NU, "stress", dtype=F64))
    P = torch.as_tensor(elastic_stress_operator(xy, D, True))  # (n_eb, n_qp, 3, 8)
    ue = 1e-4 * torch.randn(1, len(el), 8, generator=torch.Generator().manual_seed(2),
                            dtype=F64)
    eps_u = (torch.as_tensor(B) @ ue[:, :, None, :, None])[..., 0]
    sig = band_update(_band_data(mesh, el), eps_u, _state((1, len(el), 4)), 1e-4,
                      torch.full((1, 1, 1), 1e4, dtype=F64), tangent=False)[0]
    ref = (P @ ue[:, :, None, :, None])[..., 0] - 1e-4 * torch.as_tensor(d_th)
    assert ((sig - ref).abs().max() / ref.abs().max()).item() < 1e-9

