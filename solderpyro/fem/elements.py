"""Bilinear quadrilateral (Q4) kinematics at 2x2 Gauss points, in-plane Mandel B-matrices.

Strain vectors are Mandel ``(xx, yy, sqrt2*xy)``, so ``f = B^T sigma`` and ``K = B^T C B`` need
no engineering-shear factors. Also: incompatible modes (Taylor's QM6) for the linear elastic
regions, whose bending Q4 would lock, and the mean-dilatation B-bar for the solder in plane strain.
"""

from __future__ import annotations

import math

import numpy as np

GP = 1.0 / math.sqrt(3.0)
XI = np.array([[-GP, -GP], [GP, -GP], [GP, GP], [-GP, GP]])  # (n_qp, 2)
W = np.ones(4)
R2 = math.sqrt(2.0)


def _dN_dxi(xi: np.ndarray) -> np.ndarray:
    """Q4 shape-function derivatives ``(n_qp, 2, 4)`` in the reference square."""
    r, s = xi[:, 0], xi[:, 1]
    dr = 0.25 * np.stack([-(1 - s), (1 - s), (1 + s), -(1 + s)], 1)
    ds = 0.25 * np.stack([-(1 - r), -(1 + r), (1 + r), (1 - r)], 1)
    return np.stack([dr, ds], 1)


def _bmat(dNdx: np.ndarray) -> np.ndarray:
    """Mandel B ``(..., 3, 2k)`` from derivatives ``(..., 2, k)``; dofs (u0, v0, u1, ...)."""
    sh = dNdx.shape[:-2]
    k = dNdx.shape[-1]
    B = np.zeros((*sh, 3, 2 * k))
    B[..., 0, 0::2] = dNdx[..., 0, :]
    B[..., 1, 1::2] = dNdx[..., 1, :]
    B[..., 2, 0::2] = dNdx[..., 1, :] / R2
    B[..., 2, 1::2] = dNdx[..., 0, :] / R2
    return B


def q4_kinematics(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """B-matrices and integration weights of Q4 elements.

    Args:
        xy: ``(n_elem, 4, 2)`` node coordinates, mm.
    Returns:
        ``(B (n_elem, n_qp, 3, 8), wdet (n_elem, n_qp))`` with ``wdet = w * det J`` in mm^2.
    """
    dN = _dN_dxi(XI)  # (q, 2, 4)
    J = np.einsum("qak,ekb->eqab", dN, xy)  # (e, q, 2, 2): dx_b/dxi_a
    det = np.linalg.det(J)
    if np.any(det <= 0):
        raise ValueError("mesh has an inverted or degenerate element")
    dNdx = np.linalg.solve(J, np.broadcast_to(dN, J.shape[:2] + dN.shape[1:]))
    return _bmat(dNdx), det * W


def bbar(B: np.ndarray, wdet: np.ndarray) -> np.ndarray:
    """Mean-dilatation B-bar: replace the in-plane volumetric part by its element average.

    Args:
        B: ``(n_elem, n_qp, 3, 8)``; wdet: ``(n_elem, n_qp)``.
    """
    vol = B[..., 0, :] + B[..., 1, :]  # (e, q, 8)
    vbar = (vol * wdet[..., None]).sum(1) / wdet.sum(1)[:, None]
    dv = (vbar[:, None, :] - vol) / 2.0
    Bb = B.copy()
    Bb[..., 0, :] += dv
    Bb[..., 1, :] += dv
    return Bb


def qm6_stiffness(xy: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Condensed QM6 (Taylor-corrected incompatible modes) element stiffness ``(n_elem, 8, 8)``.

    Passes the patch test (the incompatible strains integrate to zero) and represents pure
    bending of rectangles exactly. Thermal loads of uniform eigenstrain are unaffected.

    Args:
        xy: ``(n_elem, 4, 2)`` node coordinates; D: ``(3, 3)`` in-plane stiffness (Mandel), MPa.
    """
    B, wdet = q4_kinematics(xy)
    G = qm6_modes(xy, wdet)  # (e, q, 3, 4)
    Kuu = np.einsum("eqia,ij,eqjb,eq->eab", B, D, B, wdet)
    Kua = np.einsum("eqia,ij,eqjb,eq->eab", B, D, G, wdet)
    Kaa = np.einsum("eqia,ij,eqjb,eq->eab", G, D, G, wdet)
    return Kuu - Kua @ np.linalg.solve(Kaa, np.swapaxes(Kua, 1, 2))


def qm6_modes(xy: np.ndarray, wdet: np.ndarray) -> np.ndarray:
    """Strain matrices ``(n_elem, n_qp, 3, 4)`` of QM6's four incompatible modes (Taylor's
    correction: Jacobian at the centre, scaled by ``det J0 / det J``, so they integrate to zero).

    Args:
        xy: ``(n_elem, 4, 2)`` node coordinates, mm; wdet: ``(n_elem, n_qp)`` from
            :func:`q4_kinematics`.
    """
    dN = _dN_dxi(np.zeros((1, 2)))[0]
    J0 = np.einsum("ak,ekb->eab", dN, xy)
    det0 = np.linalg.det(J0)
    r, s = XI[:, 0], XI[:, 1]
    dP = np.zeros((4, 2, 2))  # d(1-r^2, 1-s^2)/d(r, s)
    dP[:, 0, 0] = -2 * r
    dP[:, 1, 1] = -2 * s
    dPdx = np.linalg.solve(J0[:, None], np.broadcast_to(dP, (len(xy), 4, 2, 2)))
    return _bmat(dPdx) * (det0[:, None] / (wdet / W))[..., None, None]


def edofs(elems: np.ndarray) -> np.ndarray:
    """Element dof indices ``(n_elem, 8)`` in the order (u0, v0, u1, v1, ...)."""
    return np.stack([2 * elems, 2 * elems + 1], -1).reshape(len(elems), 8)
