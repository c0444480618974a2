"""One-off assembly and static condensation of the linear elastic regions (scipy, float64).

The elastic bars are linear and shared by every batch member, so their interior dofs are
condensed once onto the dofs of the nonlinear regions (the solder layer):

    S = K_rr - K_rc K_cc^-1 K_cr,   g_k = F_k,r - K_rc K_cc^-1 F_k,c,

and observations of condensed dofs become linear maps of the retained dofs. The batched Newton
then works on the small retained system only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from solderpyro.fem.elements import edofs, q4_kinematics, qm6_stiffness
from solderpyro.materials.elastic import plane_elastic


@dataclass
class Condensed:
    """Result of the condensation (numpy arrays, float64).

    Attributes:
        S: ``(n_r, n_r)`` condensed elastic stiffness on the retained dofs.
        g: ``{material: (n_r,)}`` condensed thermal force per unit free thermal strain.
        H: ``(n_out, n_r)`` observation map (V at points) on the retained dofs, mm/mm.
        h: ``{material: (n_out,)}`` observation offset per unit free thermal strain of material.
        Hx, hx: the same for the ``extra`` operator of :func:`condense` (None without one).
    """

    S: np.ndarray
    g: dict
    H: np.ndarray
    h: dict
    Hx: np.ndarray | None = None
    hx: dict | None = None


def linear_system(mesh, problem, lin_elems: np.ndarray):
    """Global sparse stiffness and unit thermal loads of the linear elastic elements."""
    n_dof = 2 * mesh.n_node
    rows: list[np.ndarray] = []
    cols: list[np.ndarray] = []
    vals: list[np.ndarray] = []
    loads: dict[str, np.ndarray] = {}
    for key, mat in problem.materials.items():
        els = np.array([e for e in lin_elems if mesh.layers[mesh.region[e]].material == key],
                       dtype=int)
        if len(els) == 0:
            continue
        D, d_th = (t.numpy() for t in plane_elastic(mat.E, mat.nu, problem.plane,
                                                      dtype=torch.float64))
        xy = mesh.nodes[mesh.elems[els]]
        B, wdet = q4_kinematics(xy)
        if problem.incompatible_modes:
            Ke = qm6_stiffness(xy, D)
        else:
            Ke = np.einsum("eqia,ij,eqjb,eq->eab", B, D, B, wdet)
        fe = np.einsum("eqia,i,eq->ea", B, d_th, wdet)
        ed = edofs(mesh.elems[els])
        rows.append(np.repeat(ed, 8, 1).ravel())
        cols.append(np.tile(ed, (1, 8)).ravel())
        vals.append(Ke.ravel())
        f = np.zeros(n_dof)
        np.add.at(f, ed.ravel(), fe.ravel())
        loads[key] = f
    K = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(n_dof, n_dof))
    return K, loads


def condense(K: sp.csr_matrix, loads: dict, obs: sp.csr_matrix, r: np.ndarray,
             c: np.ndarray, extra: sp.csr_matrix | None = None) -> Condensed:
    """Condense the free dofs ``c`` onto ``r``.

    Args:
        K: ``(n_dof, n_dof)`` sparse linear stiffness; loads: ``{material: (n_dof,)}``.
        obs: ``(n_out, n_dof)`` sparse observation operator.
        r, c: retained and condensed free dof indices.
        extra: optional ``(n_x, n_dof)`` operator mapped like ``obs`` (into ``Hx``, ``hx``),
            e.g. the dofs of elements whose stresses are recovered.
    """
    Krr = K[r][:, r].toarray()
    Krc = K[r][:, c]
    Kcc = K[c][:, c].tocsc()
    lu = spla.splu(Kcc)
    X = lu.solve(Krc.T.toarray())  # (n_c, n_r) = Kcc^-1 Kcr
    S = Krr - Krc @ X
    S = 0.5 * (S + S.T)
    Hr = obs[:, r].toarray()
    Hc = obs[:, c].toarray()
    H = Hr - Hc @ X
    g, h = {}, {}
    for key, f in loads.items():
        y = lu.solve(f[c])
        g[key] = f[r] - Krc @ y
        h[key] = Hc @ y
    if extra is None:
        return Condensed(S, g, H, h)
    Ec = extra[:, c]
    Hx = extra[:, r].toarray() - Ec @ X
    hx = {key: Ec @ lu.solve(f[c]) for key, f in loads.items()}
    return Condensed(S, g, H, h, Hx, hx)
