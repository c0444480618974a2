"""Bordered-band Cholesky of the retained tangent (native CPU path of the Newton solves).

The retained system of :class:`~solderpyro.fem.solver.SpecimenSolver` is
``K = S + sum_e K_e``: ``S``, the elastic bars condensed once, is dense but only on the
*border* dofs (those of the solder's interfaces with the bars), while the element matrices of
the solder couple neighbouring dofs only. Ordering the *interior* dofs (all others) to a band
(reverse Cuthill-McKee) gives

    K = [[A, Bc], [Bc^T, Dd]],   A banded (half-width w),   Bc sparse,   Dd dense,

and ``K = LL^T`` costs a band Cholesky of ``A``, ``W = L_A^-1 Bc`` and a dense Cholesky of the
Schur complement ``Dd - W^T W``: on the reference mesh (183 interior, 121 border dofs, w = 11)
about a quarter of the work of the dense 304 x 304 factorization and a fifth of its memory, so
the factors of a batch stay in cache. Assembly, factorization and solves run in C
(``solderpyro/_native/linalg.c``), over the members in parallel (torch's thread count); the
dense torch path of the solver stays for other devices, dtypes and autograd.

Shapes: ``n_r`` retained dofs, ``n_e`` elements with ``n_qp`` points; one member's factor is a
flat buffer of :attr:`BorderedBand.nbuf` doubles.
"""

from __future__ import annotations

import ctypes

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import reverse_cuthill_mckee

from solderpyro import _native


class BorderedBand:
    """Structure (the same for every member) of the retained tangent and the C calls using it.

    Args:
        S: ``(n_r, n_r)`` condensed stiffness of the linear regions (MPa mm).
        edof: ``(n_e, 8)`` retained dof of each element dof, -1 where the dof is fixed.
        B, Bw: ``(n_e, n_qp, 3, 8)`` B-matrices and ``B * w det J`` (float64, CPU).
    """

    def __init__(self, S: np.ndarray, edof: np.ndarray, B: torch.Tensor, Bw: torch.Tensor):
        n = S.shape[0]
        border = np.abs(S).max(1) > 0
        interior = np.nonzero(~border)[0]
        D = np.nonzero(border)[0]
        # interior adjacency from the elements, ordered to a band
        rows, cols = [], []
        for ed in edof:
            e = ed[ed >= 0]
            rows.append(np.repeat(e, len(e)))
            cols.append(np.tile(e, len(e)))
        G = sp.csr_matrix((np.ones(sum(len(r) for r in rows)),
                           (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
        order = interior
        if len(interior):
            GI = G[interior][:, interior].tocsr()
            order = interior[reverse_cuthill_mckee(GI, symmetric_mode=True)]
        perm = np.empty(n, dtype=np.int64)
        perm[order] = np.arange(len(order))
        perm[D] = len(order) + np.arange(len(D))
        nI, nD = len(order), len(D)
        GP = G.tocoo()
        pi, pj = perm[GP.row], perm[GP.col]
        ii = (pi < nI) & (pj < nI)
        w = int(np.abs(pi[ii] - pj[ii]).max()) if ii.any() else 0
        # Bc pattern (interior row, border column), CSR by interior row
        ib = (pi < nI) & (pj >= nI)
        pairs = np.unique(np.stack([pi[ib], pj[ib] - nI], 1), axis=0).reshape(-1, 2)
        brow = np.searchsorted(pairs[:, 0], np.arange(nI + 1)).astype(np.int32)
        bcol = pairs[:, 1].astype(np.int32)
        nnzB = len(pairs)
        off_b, off_d = nI * (w + 1), nI * (w + 1) + nnzB
        # offset of every element-matrix entry in the member buffer (band: lower triangle,
        # border block: upper triangle)
        n_e = edof.shape[0]
        emap = np.full((n_e, 8, 8), -1, dtype=np.int32)
        key = {(int(r), int(c)): k for k, (r, c) in enumerate(pairs)}
        for e in range(n_e):
            for a in range(8):
                if edof[e, a] < 0:
                    continue
                pa = int(perm[edof[e, a]])
                for b in range(8):
                    if edof[e, b] < 0:
                        continue
                    pb = int(perm[edof[e, b]])
                    if pa < nI and pb < nI and pb <= pa:
                        emap[e, a, b] = pa * (w + 1) + (pb - pa + w)
                    elif pa < nI <= pb:
                        emap[e, a, b] = off_b + key[(pa, pb - nI)]
                    elif pa >= nI and pb >= nI and pb >= pa:
                        emap[e, a, b] = off_d + (pa - nI) * nD + (pb - nI)
        self.n_r, self.nI, self.nD, self.w, self.nnzB = n, nI, nD, w, nnzB
        self.n_e, self.n_qp = n_e, B.shape[1]
        self.nbuf = off_d + nD * nD
        self._dims = (ctypes.c_long * 8)(n, nI, nD, w, nnzB, n_e, self.n_qp, self.nbuf)
        c = lambda a, dt: torch.as_tensor(np.ascontiguousarray(a, dtype=dt))  # noqa: E731
        self._emap, self._brow, self._bcol = c(emap, np.int32), c(brow, np.int32), c(bcol,
                                                                                    np.int32)
        self._perm = c(perm, np.int32)
        self._SD = c(S[np.ix_(D, D)], np.float64)
        self._B, self._Bw = B.contiguous(), Bw.contiguous()

    def worthwhile(self) -> bool:
        """Whether the bordered factorization needs clearly fewer operations than the dense
        one (else the solver keeps the dense path)."""
        nI, nD, w = self.nI, self.nD, self.w
        cost = nI * w * w + nI * w * nD + nI * nD * nD / 2 + nD ** 3 / 3
        return cost < 0.5 * self.n_r ** 3 / 3

    def factor(self, cache: torch.Tensor, slots: torch.Tensor, tangent=None, Cip=None,
               n_fact: int = 0, dKe: torch.Tensor | None = None, plane_stress: bool = True):
        """Assemble and factor members into ``cache[slots]``.

        Args:
            cache: ``(n_slot, nbuf)`` factor buffers (written in place).
            slots: ``(k,)`` int64 rows of ``cache`` to write.
            tangent: factored 3-D tangents ``(K, g2, coef (k, n_fact, n_qp), nb (..., 4))`` of
                the first ``n_fact`` elements (the solder), or None.
            Cip: ``(k, n_e - n_fact, n_qp, 3, 3)`` in-plane tangents (MPa) of the other
                elements, or None when ``n_fact = n_e``.
            dKe: ``(k, n_eb, 8, 8)`` subtracted from the last ``n_eb`` element matrices (the
                band's condensed incompatible modes), or None.
            plane_stress: condense the factored tangents on eps_zz (else plane strain).
        Returns:
            ``(k,)`` int32: 0, or the failing pivot + 1 (not positive definite).
        """
        lib = _native.library()
        assert lib is not None
        k = len(slots)
        info = torch.zeros(k, dtype=torch.int32)
        sl = slots.to(torch.int64).contiguous()
        tg = [None] * 4 if tangent is None else [t.contiguous() for t in tangent]
        Cc = None if Cip is None else Cip.contiguous()
        dK = None if dKe is None else dKe.contiguous()
        p = _native.ptr
        lib.sp_bb_factor(self._dims, p(self._emap), p(self._brow), p(self._bcol),
                         p(self._perm), p(self._SD), p(self._B), p(self._Bw), k, p(sl),
                         p(cache), *(p(t) for t in tg), n_fact, p(Cc), int(plane_stress),
                         p(dK), self.n_e - (0 if dK is None else dK.shape[1]), p(info),
                         _native.threads("factor", k))
        return info

    def solve(self, cache: torch.Tensor, slots: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
        """``K[slots[j]]^-1 rhs[j]``: ``rhs`` ``(k, n_r)`` -> ``(k, n_r)``."""
        lib = _native.library()
        assert lib is not None
        r = rhs.contiguous()
        x = torch.empty_like(r)
        sl = slots.to(torch.int64).contiguous()
        p = _native.ptr
        lib.sp_bb_solve(self._dims, p(self._brow), p(self._bcol), p(self._perm), len(sl),
                        p(sl), p(cache), p(r), p(x), _native.threads("solve", len(sl)))
        return x
