"""Isotropic elasticity in Mandel notation (solderpyro.materials.elastic) against the closed
forms: bulk and shear moduli, the 3-D stiffness, the plane-stress and plane-strain matrices and
their thermal stresses."""

import pytest
import torch

from solderpyro.materials.elastic import IP, ZZ, bulk_shear, condense_zz, iso_3d, plane_elastic

F64 = torch.float64
#: the reference case (docs/configuration.md) materials (MPa, -)
MATERIALS = [(200e3, 0.29), (32e3, 0.35), (130e3, 0.34)]


def _close(a, b):
    """Rounding-level agreement: the closed forms and the library's are a few flops each."""
    torch.testing.assert_close(torch.as_tensor(a, dtype=F64), torch.as_tensor(b, dtype=F64),
                               rtol=1e-13, atol=1e-13 * float(torch.as_tensor(b).abs().max()))


@pytest.mark.parametrize("E,nu", MATERIALS)
def test_3d_stiffness_is_hookes_law(E, nu):
    """K = E/(3(1-2nu)), G = E/(2(1+nu)); C11 = E(1-nu)/((1+nu)(1-2nu)), C12 = lambda, the
    Mandel shear entry 2G; a hydrostatic strain gives 3K times it, a deviatoric one 2G."""
    K, G = bulk_shear(E, nu)
    _close(K, E / (3 * (1 - 2 * nu)))
    _close(G, E / (2 * (1 + nu)))
    C = iso_3d(torch.tensor(K, dtype=F64), torch.tensor(G, dtype=F64))
    lam = E * nu / ((1 + nu) * (1 - 2 * nu))
    ref = torch.zeros(4, 4, dtype=F64)
    ref[:3, :3] = lam
    ref[range(3), range(3)] = E * (1 - nu) / ((1 + nu) * (1 - 2 * nu))
    ref[3, 3] = 2 * G
    _close(C, ref)
    m = torch.tensor([1.0, 1.0, 1.0, 0.0], dtype=F64)
    _close(C @ m, 3 * K * m)
    dev = torch.tensor([1.0, -0.4, -0.6, 0.7], dtype=F64)
    _close(C @ dev, 2 * G * dev)


@pytest.mark.parametrize("E,nu", MATERIALS)
def test_plane_matrices_are_the_closed_forms(E, nu):
    """Plane stress: D = E/(1-nu^2) [[1, nu, 0], [nu, 1, 0], [0, 0, 1-nu]] (Mandel shear
    entry 2G) and thermal stress per unit free strain E/(1-nu) (1, 1, 0); plane strain:
    D = E/((1+nu)(1-2nu)) [[1-nu, nu, 0], [nu, 1-nu, 0], [0, 0, 1-2nu]] and 3K (1, 1, 0)."""
    D, d = plane_elastic(E, nu, "stress", dtype=F64)
    _close(D, E / (1 - nu**2) * torch.tensor([[1, nu, 0], [nu, 1, 0], [0, 0, 1 - nu]],
                                               dtype=F64))
    _close(d, E / (1 - nu) * torch.tensor([1.0, 1.0, 0.0], dtype=F64))
    D, d = plane_elastic(E, nu, "strain", dtype=F64)
    _close(D, E / ((1 + nu) * (1 - 2 * nu)) * torch.tensor(
        [[1 - nu, nu, 0], [nu, 1 - nu, 0], [0, 0, 1 - 2 * nu]], dtype=F64))
    _close(d, E / (1 - 2 * nu) * torch.tensor([1.0, 1.0, 0.0], dtype=F64))


def test_free_thermal_expansion_is_stress_free():
    """sigma_ip = D eps_ip - d_th eps_th vanishes at the free in-plane expansion: eps_th (1, 1)
    in plane stress, (1 + nu) eps_th (1, 1) in plane strain (eps_zz = 0)."""
    E, nu, e = 32e3, 0.35, 1.2e-3
    D, d = plane_elastic(E, nu, "stress", dtype=F64)
    assert (D @ torch.tensor([e, e, 0.0], dtype=F64) - d * e).abs().max() < 1e-12
    D, d = plane_elastic(E, nu, "strain", dtype=F64)
    assert (D @ torch.tensor([(1 + nu) * e] * 2 + [0.0], dtype=F64) - d * e).abs().max() < 1e-12


def test_plane_stress_condensation_makes_sigma_zz_vanish():
    """For any in-plane strain, eps_zz = -C[zz, ip] eps / C[zz, zz] gives sigma_zz = 0 and the
    in-plane stress D_stress eps, also for a batched anisotropic-looking tangent (an elastic C
    plus a rank-one term, as the plastic tangents are)."""
    K, G = bulk_shear(32e3, 0.35)
    C = iso_3d(torch.tensor([K, 0.7 * K], dtype=F64), torch.tensor([G, 0.4 * G], dtype=F64))
    nb = torch.tensor([0.5, -0.2, -0.3, 0.4], dtype=F64)
    C = C - 0.3 * 2 * G * (nb / nb.norm())[:, None] * (nb / nb.norm())[None, :]
    Dps = condense_zz(C, "stress")
    eps_ip = torch.tensor([1e-3, -4e-4, 6e-4], dtype=F64)
    for k in range(2):
        ezz = -(C[k, ZZ, IP] @ eps_ip) / C[k, ZZ, ZZ]
        full = torch.zeros(4, dtype=F64)
        full[IP], full[ZZ] = eps_ip, ezz
        sig = C[k] @ full
        assert abs(sig[ZZ].item()) < 1e-12 * sig.abs().max().item()
        _close(sig[IP], Dps[k] @ eps_ip)
    _close(condense_zz(C, "strain"), C[:, IP][:, :, IP])
    with pytest.raises(ValueError, match="plane must be 'stress' or 'strain'"):
        condense_zz(C, "axisymmetric")
