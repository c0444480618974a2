"""The bordered-band Cholesky (solderpyro.fem.bordered.BorderedBand) on small synthetic
retained systems, through its public calls only: its solves equal torch.linalg.solve of the
dense assembled K = S + sum_e Bw^T C B (- dKe), within the rounding bound of the condition
number; a matrix that is not positive definite is reported. The reference-mesh solver path
is in tests/unit/native/test_native.py."""

import numpy as np
import pytest
import torch

from solderpyro import _native
from solderpyro.fem.bordered import BorderedBand
from solderpyro.fem.elements import edofs, q4_kinematics
from solderpyro.fem.mesh import Layer, MeshSpec, build_mesh
from solderpyro.materials.elastic import plane_elastic

F64 = torch.float64
EPS = torch.finfo(F64).eps

pytestmark = pytest.mark.skipif(_native.library() is None, reason="no native library")


def _system(nx=6, ny=3, fix_corner=True, seed=0):
    """A strip of ``nx x ny`` Q4 elements (the 'solder'): retained dofs are all its dofs but
    the fixed ones; the border is the dofs of its top and bottom node rows, where a random
    SPD ``S`` (the condensed bars) acts. Returns ``(bb, S, edof, B, Bw, C)``."""
    mesh = build_mesh((Layer("s", "s", 0.0, 0.5, ny),), 3.0, MeshSpec(nx=nx, x_grading=0.5))
    xy = mesh.nodes[mesh.elems]
    B, wdet = q4_kinematics(xy)
    ed = edofs(mesh.elems)
    n_dof = 2 * mesh.n_node
    fixed = np.array([0, 1]) if fix_corner else np.array([], dtype=int)  # u, v of node 0
    free = np.setdiff1d(np.arange(n_dof), fixed)
    ret = np.full(n_dof, -1)
    ret[free] = np.arange(len(free))
    edof = ret[ed]
    n_r = len(free)
    y = mesh.nodes[:, 1]
    bnodes = np.nonzero((y == y.min()) | (y == y.max()))[0]
    bd = ret[np.stack([2 * bnodes, 2 * bnodes + 1], 1).ravel()]
    bd = bd[bd >= 0]
    g = np.random.default_rng(seed)
    M = g.standard_normal((len(bd), len(bd)))
    S = np.zeros((n_r, n_r))
    S[np.ix_(bd, bd)] = 1e3 * (M @ M.T / len(bd) + np.eye(len(bd)))
    Bt = torch.as_tensor(B)
    Bw = Bt * torch.as_tensor(wdet)[..., None, None]
    bb = BorderedBand(S, edof, Bt, Bw)
    return bb, S, edof, Bt, Bw, mesh.n_elem


def _dense(S, edof, B, Bw, C, dKe=None):
    """``(k, n_r, n_r)`` assembled dense K of members with in-plane tangents C."""
    Ke = (Bw.transpose(-1, -2) @ C @ B).sum(2)  # (k, n_e, 8, 8)
    if dKe is not None:
        Ke = Ke.clone()
        Ke[:, -dKe.shape[1]:] -= dKe
    K = torch.as_tensor(S).expand(len(C), -1, -1).clone()
    for e, ed in enumerate(edof):
        ok = np.nonzero(ed >= 0)[0]
        idx = torch.as_tensor(ed[ok])
        K[:, idx[:, None], idx[None, :]] += Ke[:, e][:, ok][:, :, ok]
    return K


def _tangents(k, n_e, seed):
    """Random plane-stress elastic tangents ``(k, n_e, 4, 3, 3)`` (E 5-50 GPa per point)."""
    g = torch.Generator().manual_seed(seed)
    D = plane_elastic(32e3, 0.35, "stress", dtype=F64)[0]
    return D * (0.15 + 1.4 * torch.rand(k, n_e, 4, 1, 1, generator=g, dtype=F64))


def _check(bb, K, cache, slots, seed):
    rhs = torch.randn(len(slots), bb.n_r, generator=torch.Generator().manual_seed(seed),
                      dtype=F64)
    x = bb.solve(cache, slots, rhs)
    ref = torch.linalg.solve(K, rhs[..., None])[..., 0]
    # backward-stable Cholesky: relative error <~ c n eps cond(K); c = 10 is generous
    tol = 10 * bb.n_r * EPS * torch.linalg.cond(K)
    err = (x - ref).norm(dim=1) / ref.norm(dim=1)
    assert bool((err <= tol).all()), (err, tol)
    assert bool(((K @ x[..., None])[..., 0] - rhs).norm(dim=1).le(
        tol * K.norm(dim=(1, 2)) * x.norm(dim=1)).all())


def test_structure_splits_interior_band_and_border():
    bb, S, *_ = _system()
    border = np.abs(S).max(1) > 0
    assert bb.nD == border.sum() and bb.nI == (~border).sum() and bb.nI + bb.nD == bb.n_r
    # reverse Cuthill-McKee on a strip 3 elements high: neighbours within about one node
    # column (4 nodes, 8 dofs) plus the node's own pair: half-width well below n_I
    assert 0 < bb.w < bb.nI // 2


@pytest.mark.parametrize("fix_corner", [True, False])
def test_solve_equals_dense_solve_over_slots(fix_corner):
    """Three members with their own tangents, factored into scattered cache slots, each
    solved: equal to torch.linalg.solve of the dense assembly (fixed dofs dropped or none)."""
    bb, S, edof, B, Bw, n_e = _system(fix_corner=fix_corner)
    C = _tangents(3, n_e, seed=1)
    cache = torch.zeros(5, bb.nbuf, dtype=F64)
    slots = torch.tensor([4, 0, 2])
    info = bb.factor(cache, slots, Cip=C)
    assert torch.equal(info, torch.zeros(3, dtype=torch.int32))
    _check(bb, _dense(S, edof, B, Bw, C), cache, slots, seed=2)


def test_subtracted_element_matrices_enter_the_factor():
    """``dKe`` (the band's condensed modes) is taken off the last elements' matrices: a small
    symmetric positive semi-definite correction keeps K positive definite, and the solve equals
    the dense one of the corrected K."""
    bb, S, edof, B, Bw, n_e = _system()
    C = _tangents(2, n_e, seed=3)
    Ke = (Bw.transpose(-1, -2) @ C @ B).sum(2)[:, -4:]
    dKe = 0.3 * Ke  # 30 % softer: still positive definite with S
    cache = torch.zeros(2, bb.nbuf, dtype=F64)
    info = bb.factor(cache, torch.arange(2), Cip=C, dKe=dKe)
    assert torch.equal(info, torch.zeros(2, dtype=torch.int32))
    _check(bb, _dense(S, edof, B, Bw, C, dKe), cache, torch.arange(2), seed=4)


def test_an_indefinite_member_is_reported_and_the_other_is_not():
    bb, S, edof, B, Bw, n_e = _system()
    C = _tangents(2, n_e, seed=5)
    C[1, n_e // 2] *= -50.0  # one element strongly negative: K is indefinite
    assert torch.linalg.eigvalsh(_dense(S, edof, B, Bw, C)[1]).min() < 0
    info = bb.factor(torch.zeros(2, bb.nbuf, dtype=F64), torch.arange(2), Cip=C)
    assert info[0] == 0 and info[1] > 0


def test_worthwhile_follows_the_operation_count():
    """A long strip (many interior dofs, narrow band, small border) is worth it; a system
    that is all border (nothing interior) is the dense factorization itself and is not."""
    bb = _system(nx=40, ny=3)[0]
    assert bb.worthwhile()
    S = 1e3 * np.eye(16)
    edof = np.arange(8)[None].repeat(2, 0)
    edof[1] += 8
    B = torch.zeros(2, 4, 3, 8, dtype=F64)
    assert not BorderedBand(S, edof, B, B).worthwhile()
