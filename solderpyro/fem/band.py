"""Elasto-plastic band of a linear region: QM6 elements with J2 Gauss points.

The linear elastic bars are condensed once onto the solder's dofs (:mod:`.assembly`). An effect
may make the elements of one linear material within ``depth`` mm of the nonlinear (solder)
region elasto-plastic (:class:`~solderpyro.effects.base.PlasticBand`); those elements then join
the solder in the per-member retained system, and their Gauss points follow
:func:`solderpyro.materials.j2.j2_update`.

The condensed bars use Taylor's incompatible-mode element QM6 (:func:`.elements.qm6_stiffness`),
so the band must too, or its elastic limit would not be the baseline: the strain at a band point
is ``eps = B u_e + G alpha_e`` with four mode amplitudes ``alpha_e`` per element. They are
element-internal and solved per element together with the points' ``eps_zz`` (plane stress) by a
local Newton iteration, ``r_alpha = sum_q w G^T sigma_hat = 0`` and ``sigma_zz = 0``, so that
for the global solver a band element is a plain element with force ``sum_q w B^T sigma`` and
tangent ``K_uu - K_ua K_aa^-1 K_au`` (:func:`mode_correction`). Elastic, this reproduces the
condensed QM6 bars to the Newton tolerance.

Shapes: ``b`` members, ``n_eb`` band elements, ``n_qp = 4`` points, 4 modes; in-plane Mandel
``(xx, yy, sqrt2*xy)``. Units mm, MPa.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from solderpyro.fem.elements import q4_kinematics, qm6_modes
from solderpyro.materials.elastic import IP, ZZ, condense_zz
from solderpyro.materials.integrate import PointState, ezz_predictor, full_strain
from solderpyro.materials.j2 import j2_update

LOCAL_ITERS = 30
LOCAL_RTOL = 1e-12


@dataclass(frozen=True)
class BandData:
    """Arrays and material of the band elements.

    Attributes:
        G: ``(n_eb, n_qp, 3, 4)`` incompatible-mode strain matrices, or None (plain Q4, when
            the problem has ``incompatible_modes=False``).
        Gw: ``G`` times the integration weights ``w det J`` (mm^2); None with ``G``.
        E, nu: elastic constants of the material (MPa, -); H: hardening modulus, MPa.
        plane: ``"stress"`` or ``"strain"``.
        material: the material's key (its free thermal strain comes from the solver).
    """

    G: torch.Tensor | None
    Gw: torch.Tensor | None
    E: float
    nu: float
    H: float
    plane: str
    material: str


def band_elements(mesh, material: str, nonlinear: np.ndarray, depth: float) -> np.ndarray:
    """Indices of the elements of ``material`` lying within ``depth`` mm (every node) of a
    nonlinear layer, in the layered mesh.

    Args:
        mesh: :class:`~.mesh.Mesh`; nonlinear: ``(n_layer,)`` bool, which layers are nonlinear.
        depth: band depth, mm (> 0).
    """
    ys = [(lay.y0, lay.y1) for lay, nl in zip(mesh.layers, nonlinear, strict=True) if nl]
    mat = np.array([lay.material == material for lay in mesh.layers])[mesh.region]
    y = mesh.nodes[mesh.elems][..., 1]  # (n_elem, 4)
    dist = np.min([np.maximum(np.maximum(a - y, y - b), 0.0).max(1) for a, b in ys], 0)
    return np.nonzero(mat & (dist <= depth + 1e-9))[0]


def adjacent_elements(mesh, el_b: np.ndarray, material: str) -> np.ndarray:
    """Elements of ``material`` outside the band ``el_b`` sharing a node with it (the ring of
    elastic elements whose stress the solver checks against the yield stress)."""
    mat = np.array([lay.material == material for lay in mesh.layers])[mesh.region]
    touch = np.isin(mesh.elems, mesh.elems[el_b]).any(1)
    inside = np.isin(np.arange(len(mesh.elems)), el_b)
    return np.nonzero(mat & touch & ~inside)[0]


def elastic_stress_operator(xy: np.ndarray, D: np.ndarray, incompatible: bool) -> np.ndarray:
    """Elastic in-plane stress per element dof, ``(n_eb, n_qp, 3, 8)``: ``sigma = P u_e`` plus
    the thermal part, with the QM6 modes condensed (``alpha = -K_aa^-1 K_au u_e``; uniform
    thermal strains load no mode, since the modes integrate to zero).

    Args:
        xy: ``(n_eb, 4, 2)`` node coordinates, mm; D: ``(3, 3)`` in-plane stiffness, MPa.
        incompatible: whether the elements are QM6 (else plain Q4).
    """
    B, wdet = q4_kinematics(xy)
    if incompatible:
        G = qm6_modes(xy, wdet)
        Kua = np.einsum("eqia,ij,eqjb,eq->eab", B, D, G, wdet)
        Kaa = np.einsum("eqia,ij,eqjb,eq->eab", G, D, G, wdet)
        B = B - G @ np.linalg.solve(Kaa, np.swapaxes(Kua, 1, 2))[:, None]
    return D @ B


def band_update(band: BandData, eps_u: torch.Tensor, st: PointState, eps_th, sigma_y,
                guess: torch.Tensor | None = None, tangent: bool = True):
    """Band update: modes and ``eps_zz`` solved per element, J2 return at the points.

    Args:
        band: :class:`BandData`.
        eps_u: ``(b, n_eb, n_qp, 3)`` compatible in-plane strain ``B u_e``.
        st: start-of-step :class:`PointState` ``(b, n_eb, n_qp)`` (``s`` = equivalent plastic
            strain).
        eps_th: the material's free thermal strain, float or ``(b, 1, 1)``.
        sigma_y: yield stress, MPa, ``(b, 1, 1)``.
        guess: optional ``(b, n_eb, 4, 2)`` warm start (``[..., 0]`` eps_zz per point,
            ``[..., 1]`` the mode amplitudes).
        tangent: whether to return the points' in-plane tangent.
    Returns:
        ``(sigma_ip (b, n_eb, n_qp, 3), C_ip (b, n_eb, n_qp, 3, 3) or None, new_state,
        dgamma (b, n_eb, n_qp), x (b, n_eb, 4, 2))``: ``sigma_ip`` the in-plane stress at
        sigma_zz = 0 (plane stress) and ``x`` the detached local solution. With autograd on,
        one local Newton step with the graph attached gives exact first derivatives.
    """
    with torch.no_grad():
        a = [t.detach() if isinstance(t, torch.Tensor) else t
             for t in (eps_u, eps_th, sigma_y)]
        std = st.detach()
        if guess is None:
            z = (ezz_predictor(a[0], std, torch.as_tensor(a[1]), band.E, band.nu)
                 if band.plane == "stress" else torch.zeros_like(a[0][..., 0]))
            al = torch.zeros_like(z)
        else:
            z, al = guess[..., 0].clone(), guess[..., 1].clone()
        for it in range(LOCAL_ITERS + 1):  # converged elements are frozen: batch invariance
            ev = _local(band, a[0], std, a[1], a[2], z, al)
            ok = _converged(band, *ev[:3])  # (b, n_eb)
            if bool(ok.all()) or it == LOCAL_ITERS:
                break
            zn, aln = _newton(band, z, al, *ev[:5])
            z = torch.where(ok[..., None], z, zn)
            al = torch.where(ok[..., None], al, aln)
        x = torch.stack([z, al], -1)
        bad = ~ok.all(-1)  # (b,) members with an unconverged element
    sig_ip, _, _, cz, Cps, st1, dg = ev
    if torch.is_grad_enabled() and any(isinstance(t, torch.Tensor) and t.requires_grad
                                       for t in (eps_u, eps_th, sigma_y, st.eps_p, st.s)):
        # one Newton step with the graph attached (detached Jacobian), then the outputs there
        sh, szz, r = _local(band, eps_u, st, eps_th, sigma_y, z, al, cz=cz)[:3]
        z, al = _newton(band, z, al, sh, szz, r, cz, Cps)
        sig_ip, _, _, _, _, st1, dg = _local(band, eps_u, st, eps_th, sigma_y, z, al, cz=cz)
    if bool(bad.any()):  # an unconverged local solve poisons its member (the step is halved)
        sig_ip = torch.where(bad[:, None, None, None], torch.nan, sig_ip)
    return sig_ip, Cps if tangent else None, st1, dg, x


def _local(band, eps_u, st, eps_th, sigma_y, z, al, cz=None):
    """The points' update at ``(eps_zz, modes) = (z, al)``.

    Returns ``(sigma_hat (b, n_eb, n_qp, 3), szz, r_alpha (b, n_eb, 4) or None, c_zz column
    (b, n_eb, n_qp, 4), C_ps (b, n_eb, n_qp, 3, 3), new_state, dgamma)``: ``sigma_hat`` the
    in-plane stress condensed on eps_zz (``sigma_ip - c_iz/c_zz sigma_zz``), ``C_ps`` the
    in-plane tangent condensed likewise. With ``cz`` given (a detached Jacobian) no tangent
    is formed and ``C_ps`` is None.
    """
    eps_ip = eps_u if band.G is None else eps_u + (band.G @ al[:, :, None, :, None])[..., 0]
    sig, st1, C3, dg = j2_update(full_strain(eps_ip, z), st, eps_th, band.E, band.nu,
                                 sigma_y, band.H, tangent=cz is None)
    szz = sig[..., ZZ]
    Cps = None
    if C3 is not None:
        cz = C3.col_zz()
        Cps = condense_zz(C3.full(), band.plane)
    if band.plane == "stress":
        sig_hat = sig[..., IP] - (cz[..., IP] / cz[..., ZZ, None]) * szz[..., None]
    else:
        sig_hat, szz = sig[..., IP], torch.zeros_like(szz)
    r = None if band.G is None else _modes(band.Gw, sig_hat)
    return sig_hat, szz, r, cz, Cps, st1, dg


def _modes(Gw: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """``sum_q Gw_q^T a_q``: ``(b, n_eb, 4)`` from ``a`` ``(b, n_eb, n_qp, 3)``, or
    ``(b, n_eb, 4, m)`` from ``a`` ``(b, n_eb, n_qp, 3, m)`` (one product over the 12 rows)."""
    n_e, n_q = Gw.shape[:2]
    GwT = Gw.reshape(n_e, n_q * 3, 4).transpose(1, 2)  # (n_eb, 4, 12)
    if a.ndim == 4:
        return (GwT @ a.reshape(*a.shape[:2], n_q * 3, 1))[..., 0]
    return GwT @ a.reshape(*a.shape[:2], n_q * 3, a.shape[-1])


def _converged(band, sig_hat, szz, r):
    """``(b, n_eb)``: whether an element's local residuals are at rounding level: ``szz`` and
    ``r_alpha`` relative to the stress with a 1 MPa floor (as the global solver's check)."""
    smax = sig_hat.abs().amax(-1)  # (b, n_eb, n_qp)
    ok = (szz.abs() <= LOCAL_RTOL * (1.0 + smax)).all(-1)  # (b, n_eb)
    if r is not None:
        scale = band.Gw.abs().sum((1, 2))[None] * (1.0 + smax.amax(-1))[..., None]
        ok = ok & (r.abs() <= LOCAL_RTOL * scale).all(-1)
    return ok


def _newton(band, z, al, sig_hat, szz, r, cz, Cps):
    """One local Newton step on ``(eps_zz, modes)`` (modes condensed on eps_zz per point)."""
    if band.G is not None:
        Kaa = _modes(band.Gw, Cps @ band.G)  # (b, n_eb, 4, 4)
        da = -torch.linalg.solve(Kaa, r)
        deps = (band.G @ da[:, :, None, :, None])[..., 0]  # (b, n_eb, n_qp, 3)
        al = al + da
    else:
        deps = torch.zeros_like(sig_hat)
    if band.plane == "stress":
        z = z - (szz + (cz[..., IP] * deps).sum(-1)) / cz[..., ZZ]
    return z, al


def mode_correction(band: BandData, B: torch.Tensor, Bw: torch.Tensor,
                    C: torch.Tensor) -> torch.Tensor:
    """``K_ua K_aa^-1 K_au`` ``(b, n_eb, 8, 8)``: what condensing the modes removes from the
    band elements' stiffness ``K_uu``.

    Args:
        band: :class:`BandData` (with modes).
        B, Bw: ``(n_eb, n_qp, 3, 8)`` B-matrices and ``B * w det J``.
        C: ``(b, n_eb, n_qp, 3, 3)`` in-plane tangents at the band points.
    """
    assert band.G is not None and band.Gw is not None
    CG = C @ band.G  # (b, n_eb, n_qp, 3, 4)
    Kua = (Bw.transpose(-1, -2) @ CG).sum(2)  # (b, n_eb, 8, 4)
    Kaa = (band.Gw.transpose(-1, -2) @ CG).sum(2)  # (b, n_eb, 4, 4)
    return Kua @ torch.linalg.solve(Kaa, Kua.transpose(-1, -2))
