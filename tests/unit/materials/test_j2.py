"""J2 radial return (solderpyro.materials.j2): after a plastic step the stress is on the
hardened yield surface, the plastic strain is deviatoric and normal to it, the pressure is
elastic, and the energy dissipated is non-negative. The tangent, the elastic branch and the
autograd derivatives are in tests/unit/fem/test_band_plasticity.py; the pure-shear loading and
reversal in tests/verification/test_effects_physics.py."""

import math

import torch

from solderpyro.materials.elastic import bulk_shear
from solderpyro.materials.integrate import PointState
from solderpyro.materials.j2 import j2_update

F64 = torch.float64
E, NU, H = 130e3, 0.34, 1000.0  # copper (docs/configuration.md), MPa; hardening modulus
M = torch.tensor([1.0, 1.0, 1.0, 0.0], dtype=F64)


def _von_mises(sig):
    dev = sig - sig[..., :3].sum(-1, keepdim=True) / 3.0 * M
    return torch.sqrt(1.5 * (dev * dev).sum(-1))


def _random(n, seed):
    g = torch.Generator().manual_seed(seed)
    eps = 3e-3 * (2 * torch.rand(n, 4, generator=g, dtype=F64) - 1)
    ep = 1e-3 * (2 * torch.rand(n, 4, generator=g, dtype=F64) - 1)
    ep[:, :3] -= ep[:, :3].mean(-1, keepdim=True)  # plastic strain is deviatoric
    ebar = 2e-3 * torch.rand(n, generator=g, dtype=F64)
    return eps, PointState(ep, ebar, torch.zeros(n, dtype=F64))


def test_plastic_step_ends_on_the_hardened_yield_surface():
    """Random strains 0.3 %, prior plastic strain and ebar, sigma_y = 60 MPa: every point
    that flowed has q = sigma_y + H (ebar_n + dgamma) (1e-12 relative: a closed form), and
    none that did not flow is above its yield stress."""
    eps, st = _random(200, 0)
    sy = 60.0
    sig, st1, _, dg = j2_update(eps, st, 2e-4, E, NU, sy, H)
    q = _von_mises(sig)
    plastic = dg > 0
    assert 20 < int(plastic.sum()) < 200  # both branches are exercised
    torch.testing.assert_close(q[plastic], (sy + H * st1.s)[plastic], rtol=1e-12, atol=0)
    torch.testing.assert_close(st1.s, st.s + dg, rtol=0, atol=0)
    assert bool((q[~plastic] <= sy + H * st.s[~plastic]).all())


def test_plastic_flow_is_deviatoric_normal_and_dissipative():
    """The plastic strain increment has no trace, points along dev(sigma) with magnitude
    sqrt(3/2) dgamma (its equivalent strain is dgamma), and sigma : deps_p = q dgamma >= 0;
    the pressure is K tr(eps - eps_th m), untouched by the flow (1e-12 relative)."""
    eps, st = _random(100, 1)
    eth = 2e-4
    sig, st1, _, dg = j2_update(eps, st, eth, E, NU, 40.0, H)
    dep = st1.eps_p - st.eps_p
    assert dep[:, :3].sum(-1).abs().max() < 1e-18
    dev = sig - sig[:, :3].sum(-1, keepdim=True) / 3.0 * M
    q = _von_mises(sig)
    pl = dg > 0
    expect = 1.5 * dg[pl, None] * dev[pl] / q[pl, None]
    torch.testing.assert_close(dep[pl], expect, rtol=1e-12, atol=1e-18)
    torch.testing.assert_close(dep.norm(dim=-1), math.sqrt(1.5) * dg, rtol=1e-12, atol=1e-18)
    work = (sig * dep).sum(-1)
    torch.testing.assert_close(work, q * dg, rtol=1e-12, atol=1e-12)
    assert bool((work >= 0).all())
    K, _ = bulk_shear(E, NU)
    p = sig[:, :3].mean(-1)
    torch.testing.assert_close(p, K * ((eps - st.eps_p)[:, :3].sum(-1) - 3 * eth), rtol=1e-12,
                               atol=1e-9)


def test_isochoric_axial_strain_closed_form():
    """A volume-preserving axial strain (e, -e/2, -e/2) from the virgin state, beyond yield:
    q_tr = 3 G e, dgamma = (3 G e - sigma_y)/(3 G + H), and the stress is the deviator
    q (2/3, -1/3, -1/3) with q = sigma_y + H dgamma, no pressure (1e-12 relative)."""
    _, G = bulk_shear(E, NU)
    e, sy = 1e-3, 50.0
    eps = torch.tensor([[e, -e / 2, -e / 2, 0.0]], dtype=F64)
    st = PointState(torch.zeros(1, 4, dtype=F64), torch.zeros(1, dtype=F64),
                    torch.zeros(1, dtype=F64))
    sig, _, _, dg = j2_update(eps, st, 0.0, E, NU, sy, H)
    dg_ref = (3 * G * e - sy) / (3 * G + H)
    assert dg_ref > 0
    torch.testing.assert_close(dg, torch.tensor([dg_ref], dtype=F64), rtol=1e-12, atol=0)
    q = sy + H * dg_ref
    torch.testing.assert_close(sig[0], torch.tensor([2 * q / 3, -q / 3, -q / 3, 0.0],
                                                    dtype=F64), rtol=1e-12, atol=1e-12)
