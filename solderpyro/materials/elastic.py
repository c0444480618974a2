"""Isotropic linear elasticity in Mandel notation (xx, yy, zz, sqrt2*xy).

In Mandel notation the double contraction is a dot product, so tangents are plain matrices.
In-plane components used by the 2-D FE are indices ``IP = [0, 1, 3]``.
"""

from __future__ import annotations

import torch

IP = [0, 1, 3]  # in-plane Mandel components (xx, yy, sqrt2*xy)
ZZ = 2


def bulk_shear(E: torch.Tensor | float, nu: torch.Tensor | float):
    """Bulk and shear moduli (MPa) from Young's modulus (MPa) and Poisson's ratio."""
    return E / (3.0 * (1.0 - 2.0 * nu)), E / (2.0 * (1.0 + nu))


def iso_3d(K: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
    """3-D isotropic stiffness ``(..., 4, 4)`` in Mandel form from ``K, G`` of shape ``(...)``."""
    K = torch.as_tensor(K)
    G = torch.as_tensor(G, dtype=K.dtype)
    m = torch.tensor([1.0, 1.0, 1.0, 0.0], dtype=K.dtype, device=K.device)
    mm = m[:, None] * m[None, :]
    idev = torch.eye(4, dtype=K.dtype, device=K.device) - mm / 3.0
    return K[..., None, None] * mm + 2.0 * G[..., None, None] * idev


def condense_zz(C: torch.Tensor, plane: str) -> torch.Tensor:
    """In-plane tangent ``(..., 3, 3)`` from a 3-D Mandel tangent ``(..., 4, 4)``.

    ``plane="stress"`` eliminates eps_zz with sigma_zz = 0; ``"strain"`` drops it (eps_zz = 0).
    """
    idx = torch.tensor(IP, device=C.device)
    Cip = C.index_select(-2, idx).index_select(-1, idx)
    if plane == "strain":
        return Cip
    if plane != "stress":
        raise ValueError(f"plane must be 'stress' or 'strain', got {plane!r}")
    cz = C.index_select(-1, idx)[..., ZZ, :]  # C[zz, ip] = C[ip, zz] (symmetric)
    return Cip - cz[..., :, None] * cz[..., None, :] / C[..., ZZ, ZZ, None, None]


def plane_elastic(E: float, nu: float, plane: str, **tkw) -> tuple[torch.Tensor, torch.Tensor]:
    """In-plane elastic stiffness ``(3, 3)`` and the in-plane stress per unit free thermal strain.

    Returns:
        ``(D, d_th)``: ``sigma_ip = D @ eps_ip - d_th * eps_th`` where ``eps_th = alpha*(T-T_ref)``
        is the free (isotropic) thermal strain; ``d_th`` has shape ``(3,)``.
    """
    K, G = bulk_shear(torch.tensor(E, **tkw), torch.tensor(nu, **tkw))
    C = iso_3d(K, G)
    D = condense_zz(C, plane)
    m = torch.tensor([1.0, 1.0, 1.0, 0.0], **tkw)
    if plane == "strain":
        d_th = (C @ m)[IP]  # 3K * [1, 1, 0]
    else:
        d_th = D @ m[IP]
    return D, d_th
