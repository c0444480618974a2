"""The fixed operators of a specimen solver, set up once per problem.

The Dirichlet dofs (u = 0 on the symmetry line, v = 0 at the origin O), the observation operator
(V at the output points relative to O), the elements and data of an elasto-plastic band of a
linear material, and the stress probe of the elastic elements next to such a band
(:class:`BandProbe`: their largest von Mises stress, checked during a solve).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch

from solderpyro.effects.base import PlasticBand
from solderpyro.fem.band import BandData, band_elements, elastic_stress_operator
from solderpyro.fem.elements import qm6_modes
from solderpyro.fem.mesh import Mesh, locate
from solderpyro.fem.thermo import StepThermo
from solderpyro.materials.elastic import plane_elastic


def dirichlet(mesh: Mesh, origin: tuple[float, float]) -> tuple[np.ndarray, int]:
    """The fixed dofs (u on the line x = x_O, v at O) and the node of the origin O (mm).

    Raises:
        ValueError: O is not a mesh node.
    """
    x0, y0 = origin
    on_axis = np.nonzero(np.abs(mesh.nodes[:, 0] - x0) < 1e-9)[0]
    d = np.hypot(mesh.nodes[:, 0] - x0, mesh.nodes[:, 1] - y0)
    o = int(np.argmin(d))
    if d[o] > 1e-9:
        raise ValueError(f"origin O={tuple(origin)} is not a mesh node")
    return np.unique(np.concatenate([2 * on_axis, [2 * o + 1]])), o


def observation(mesh: Mesh, pts: np.ndarray, half: bool, node_O: int) -> sp.csr_matrix:
    """``(n_pt, 2 n_node)`` operator of V at the points ``pts`` ``(n_pt, 2)`` (mm) relative to
    V at the node ``node_O``; ``half``: the mesh covers x >= 0 (V is even in x)."""
    q = pts.copy()
    if half:
        q[:, 0] = np.abs(q[:, 0])  # V is even in x about the symmetry line
    el, w = locate(mesh, q)
    rows = np.repeat(np.arange(len(q)), 4)
    cols = (2 * mesh.elems[el] + 1).ravel()
    H = sp.csr_matrix((w.ravel(), (rows, cols)), shape=(len(q), 2 * mesh.n_node))
    Ho = sp.csr_matrix(([1.0] * len(q), (np.arange(len(q)), [2 * node_O + 1] * len(q))),
                       shape=H.shape)
    return (H - Ho).tocsr()


def band_element_indices(mesh: Mesh, materials: dict, spec: PlasticBand,
                         nonlin: np.ndarray) -> np.ndarray:
    """Element indices of the band ``spec`` (``nonlin`` ``(n_layer,)``: nonlinear layers).

    Raises:
        ValueError: the band's material is not a linear material of the problem, or no element
            lies within its depth.
    """
    if spec.material not in materials or materials[spec.material].nonlinear:
        raise ValueError(f"plastic band: {spec.material!r} is not a linear material of the "
                         f"problem ({', '.join(materials)})")
    el_b = band_elements(mesh, spec.material, nonlin, spec.depth)
    if len(el_b) == 0:
        raise ValueError(f"plastic band: no element of {spec.material!r} lies within "
                         f"{spec.depth} mm of the solder")
    return el_b


def band_data(mesh: Mesh, problem, spec: PlasticBand, el_b: np.ndarray, wdet_b: np.ndarray,
              tkw: dict) -> BandData:
    """Material and incompatible modes of the band elements ``el_b`` (``wdet_b``
    ``(n_eb, n_qp)``) of ``problem``."""
    mat = problem.materials[spec.material]
    G = Gw = None
    if problem.incompatible_modes:
        g = qm6_modes(mesh.nodes[mesh.elems[el_b]], wdet_b)
        G = torch.as_tensor(g, **tkw)
        Gw = torch.as_tensor(g * wdet_b[..., None, None], **tkw)
    return BandData(G, Gw, mat.E, mat.nu, spec.H, problem.plane, spec.material)


class BandProbe:
    """In-plane stresses of elastic (condensed) elements next to a band at their points,
    ``sigma = u @ M_r + eps_lin @ M_th`` (``n_p = n_el*n_qp*3`` values per member), and their
    largest von Mises stress (:meth:`peak_vm`).

    Args:
        mesh, problem: the discretised :class:`~solderpyro.fem.problem.Problem`.
        spec: the band (its material is that of the elements).
        el_b: the checked elements' indices.
        cond: the condensation (:func:`~solderpyro.fem.assembly.condense`) with the probe's
            rows (``Hx``, ``hx``).
        lin_keys: the linear materials' keys, in the order of ``eps_lin``.
        tkw: torch dtype and device.
    """

    def __init__(self, mesh: Mesh, problem, spec: PlasticBand, el_b: np.ndarray, cond,
                 lin_keys: list[str], tkw: dict) -> None:
        mat = problem.materials[spec.material]
        D, d_th = (a.numpy() for a in plane_elastic(mat.E, mat.nu, problem.plane,
                                                     dtype=torch.float64))
        P = elastic_stress_operator(mesh.nodes[mesh.elems[el_b]], D,
                                    problem.incompatible_modes)  # (n_eb, n_qp, 3, 8)
        n_eb = len(el_b)
        Pm = np.zeros((P.shape[0] * P.shape[1] * 3, n_eb * 8))  # block diagonal
        for e in range(n_eb):
            Pm[e * 12:(e + 1) * 12, e * 8:(e + 1) * 8] = P[e].reshape(12, 8)
        M_th = np.stack([Pm @ cond.hx[k] - (d_th[None, :] * (k == spec.material)).repeat(
            4 * n_eb, 0).ravel() for k in lin_keys])
        t = lambda a: torch.as_tensor(np.ascontiguousarray(a), **tkw)  # noqa: E731
        self.M_r, self.M_th = t((Pm @ cond.Hx).T), t(M_th)  # (n_r, n_p), (n_mat, n_p)
        self.plane, self.material = problem.plane, mat
        self.i_mat = lin_keys.index(spec.material)

    def peak_vm(self, u, th: StepThermo) -> torch.Tensor:
        """Largest von Mises stress ``(b,)`` MPa at the points for displacements ``u``
        ``(b, n_r)`` and the inputs ``th``; in plane strain with ``sigma_zz = nu (sigma_xx +
        sigma_yy) - E eps_th``."""
        with torch.no_grad():
            sig = (u.detach() @ self.M_r + th.eps_lin.detach() @ self.M_th).reshape(
                u.shape[0], -1, 3)
            sx, sy, txy = sig[..., 0], sig[..., 1], sig[..., 2] * 0.5 ** 0.5
            sz = torch.zeros_like(sx)
            if self.plane == "strain":
                mat = self.material
                eps = th.eps_lin[..., self.i_mat]
                sz = mat.nu * (sx + sy) - mat.E * torch.as_tensor(eps).reshape(-1, 1)
            j2 = 0.5 * ((sx - sy) ** 2 + (sy - sz) ** 2 + (sz - sx) ** 2) + 3.0 * txy * txy
            return j2.sqrt().amax(1)
