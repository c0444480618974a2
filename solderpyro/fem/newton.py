"""The Newton iteration of one implicit step of the batch, with its line search.

Each member iterates on its retained displacements (and, in plane stress, the solder's eps_zz)
until its residual norm is below ``rtol``: modified Newton, where a member refactors its
tangent only when it has no factor or its own contraction is poor, and the factors are kept
across iterations and steps (:attr:`NewtonStep.fcache`); a backtracking line search on the
residual norm per member. The factors are dense upper Cholesky ones (torch) or, on the CPU in
float64 with the native kernels, bordered-band ones (:class:`~solderpyro.fem.bordered.
BorderedBand`). With autograd on, the converged solution is corrected by one Newton step with
the graph attached (implicit-function theorem), which gives exact first derivatives.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch

from solderpyro import _native
from solderpyro.fem.band import BandData, mode_correction
from solderpyro.fem.batch import put, rows, scatter, take
from solderpyro.fem.bordered import BorderedBand
from solderpyro.fem.points import BandTangent, PointEvaluator, split_state
from solderpyro.fem.thermo import MemberStep
from solderpyro.materials.elastic import condense_zz
from solderpyro.materials.integrate import PointState, Tangent3D, ezz_predictor


@dataclass(frozen=True)
class RetainedOperators:
    """The fixed operators of the retained (nonlinear) system.

    Attributes:
        S: ``(n_r, n_r)`` condensed linear stiffness, MPa mm.
        G: ``(n_mat, n_r)`` condensed thermal force per unit free thermal strain of each linear
            material, N/mm.
        B, Bw: ``(n_e, n_qp, 3, 8)`` B-matrices and ``B * w det J`` of the nonlinear elements.
        BweT: ``Bw`` as ``(n_e, 8, n_qp*3)``; edof: ``(n_e, 8)`` retained dofs; kidx:
            ``(n_e*64,)`` flat indices of the element matrices in ``(n_r, n_r)``.
        n_s: solder elements (first); band: the band's data or None; bb: the native
            bordered-band factorization or None (dense torch path).
    """

    S: torch.Tensor
    G: torch.Tensor
    B: torch.Tensor
    Bw: torch.Tensor
    BweT: torch.Tensor
    edof: torch.Tensor
    kidx: torch.Tensor
    n_s: int
    band: BandData | None
    bb: BorderedBand | None


class Load(NamedTuple):
    """The members' external load: ``fext`` ``(b, n_r)`` condensed thermal forces (N/mm) and
    ``fref`` ``(b,)`` their scale for the residual norm."""

    fext: torch.Tensor
    fref: torch.Tensor

    def rows(self, idx) -> Load:
        """The load of the members ``idx`` (sorted, unique)."""
        return Load(rows(self.fext, idx), rows(self.fref, idx))


class NewtonPoint(NamedTuple):
    """Where a member's iteration stands: displacements ``u`` ``(b, n_r)`` mm, eps_zz ``ezz``
    ``(b, n_s, n_qp)`` or None, residual norm ``rn`` ``(b,)`` and the local solution ``x``
    ``(..., 2)`` (warm start of the Gauss-point update)."""

    u: torch.Tensor
    ezz: torch.Tensor | None
    rn: torch.Tensor
    x: torch.Tensor | None


@dataclass
class _Factors:
    """The factors the iteration uses: cache rows ``gid`` of the members, the cache ``Uc``
    and a workspace ``ws``, which members ``have`` a factor, the last ``info``, whether the
    native (bordered-band) path runs and whether ``gid`` is the whole cache."""

    Uc: torch.Tensor
    ws: torch.Tensor
    have: torch.Tensor
    info: torch.Tensor
    gid: torch.Tensor
    native: bool
    whole: bool


def chol_solve(U, rhs):
    """Solve ``U^T U x = rhs`` for ``rhs`` of shape ``(b, n)`` (two triangular solves; on CPU
    this is ~3x faster than ``torch.cholesky_solve`` for batched single right-hand sides)."""
    y = torch.linalg.solve_triangular(U.mT, rhs.unsqueeze(-1), upper=False)
    return torch.linalg.solve_triangular(U, y, upper=True).squeeze(-1)


def fint_scale(sig):
    """Scale ``(b,)`` of the internal forces in the residual norm: 1e-3 of the largest
    stress (MPa) of each member."""
    return sig.abs().amax((1, 2, 3)) * 1e-3


class NewtonStep:
    """One backward-Euler step of a batch: modified Newton with line search.

    Args:
        points: the Gauss-point evaluation (:class:`~solderpyro.fem.points.PointEvaluator`).
        ops: the retained system's operators (:class:`RetainedOperators`).
        problem: the :class:`~solderpyro.fem.problem.Problem` (plane, stepping controls).
        tkw: torch dtype and device.
    """

    def __init__(self, points: PointEvaluator, ops: RetainedOperators, problem,
                 tkw: dict) -> None:
        self.points, self.ops, self.problem, self.tkw = points, ops, problem, tkw
        self.n_r = ops.S.shape[0]
        self.stats = {"factor": 0, "iter": 0}
        #: per-member factors kept across steps during a solve (:meth:`factor_cache`), or None
        self.fcache: dict[str, torch.Tensor] | None = None

    # ------------------------------------------------------------------ linear algebra
    def residual(self, u, sigma, fext):
        """Residual ``(b, n_r)`` N/mm: ``S u - fext`` plus the internal forces of the in-plane
        stresses ``sigma`` ``(b, n_e, n_qp, 3)`` MPa."""
        o = self.ops
        b, n_e = u.shape[0], o.B.shape[0]
        sg = sigma.reshape(b, n_e, -1).permute(1, 2, 0)  # (n_e, n_qp*3, b)
        fe = torch.bmm(o.BweT, sg).permute(2, 0, 1)  # (b, n_e, 8)
        return (u @ o.S - fext).index_add(1, o.edof.reshape(-1), fe.reshape(b, -1))

    def tangent(self, C, out=None):
        """Assembled retained tangent ``(b, n_r, n_r)`` of the in-plane tangents ``C``
        ``(b, n_e, n_qp, 3, 3)``, written into ``out`` when given."""
        o = self.ops
        b = C.shape[0]
        CB = C @ o.B  # (b, n_e, n_qp, 3, 8)
        Ke = (o.Bw.transpose(-1, -2) @ CB).sum(2)  # (b, n_e, 8, 8)
        n = self.n_r
        if o.band is not None and o.band.G is not None:  # condense the band's modes
            Ke[:, o.n_s:] -= mode_correction(o.band, o.B[o.n_s:], o.Bw[o.n_s:], C[:, o.n_s:])
        K = torch.empty(b, n, n, **self.tkw) if out is None else out
        K.copy_(o.S.expand(b, n, n))  # into existing memory: no fresh 47 MB pages per call
        K.view(b, n * n).index_add_(1, o.kidx, Ke.reshape(b, -1))
        return K

    def native_linalg(self) -> bool:
        """Whether the Newton solves use the native bordered-band factorization."""
        return self.ops.bb is not None and _native.enabled() and _native.library() is not None

    def factor_cache(self, b):
        """Per-member factors kept across iterations and steps, a flag per member, and (dense
        path) a workspace of the same size (assembly, gathers). Native path: ``F`` ``(b, nbuf)``
        bordered-band factors (:class:`~.bordered.BorderedBand`); dense path: upper Cholesky
        factors ``U`` ``(b, n_r, n_r)`` (``K = U^T U``)."""
        n = self.n_r
        if self.native_linalg():
            assert self.ops.bb is not None
            return {"F": torch.zeros(b, self.ops.bb.nbuf, **self.tkw),
                    "have": torch.zeros(b, dtype=torch.bool, device=self.tkw["device"])}
        return {"U": torch.zeros(b, n, n, **self.tkw),
                "have": torch.zeros(b, dtype=torch.bool, device=self.tkw["device"]),
                "ws": torch.empty(b, n, n, **self.tkw)}

    def factor_native(self, F, slots, C3):
        """Assemble and factor (bordered band) the tangents ``C3`` (factored, full, or with a
        band) of ``k`` members into the rows ``slots`` of ``F``; returns ``info`` ``(k,)``."""
        o = self.ops
        bb = o.bb
        assert bb is not None
        ps = self.problem.plane == "stress"
        if isinstance(C3, BandTangent):
            dKe = None
            if o.band is not None and o.band.G is not None:
                dKe = mode_correction(o.band, o.B[o.n_s:], o.Bw[o.n_s:], C3.band)
            if isinstance(C3.solder, Tangent3D):
                t = C3.solder
                return bb.factor(F, slots, (t.K, t.g2, t.coef, t.nb), C3.band, o.n_s, dKe, ps)
            Cip = torch.cat([condense_zz(C3.solder, self.problem.plane), C3.band], 1)
            return bb.factor(F, slots, None, Cip, 0, dKe, ps)
        if isinstance(C3, Tangent3D):
            return bb.factor(F, slots, (C3.K, C3.g2, C3.coef, C3.nb), None, o.n_s, None, ps)
        return bb.factor(F, slots, None, self.points.condense(C3), 0, None, ps)

    def _refactor(self, fs: _Factors, ni, C3) -> None:
        """Assemble and factor the tangents of the members ``ni`` into their cache rows."""
        k = len(ni)
        if fs.native:
            ii = self.factor_native(fs.Uc, fs.gid[ni], rows(C3, ni))
            fs.info[ni] = ii
        else:
            Kw = self.tangent(self.points.condense(rows(C3, ni)), out=fs.ws[:k])
            if fs.whole and k == fs.info.shape[0]:  # factor straight into the cache
                _, ii = torch.linalg.cholesky_ex(Kw, upper=True, out=(fs.Uc, fs.info))
            else:
                ii = torch.empty(k, dtype=fs.info.dtype, device=fs.info.device)
                torch.linalg.cholesky_ex(Kw, upper=True, out=(Kw, ii))
                fs.Uc.index_copy_(0, fs.gid[ni], Kw)
                fs.info[ni] = ii
        fs.have[ni] = ii == 0
        self.stats["factor"] += k

    def _solve(self, fs: _Factors, act, rhs):
        """Newton updates ``(na, n_r)`` of the members ``act`` for the right-hand sides
        ``rhs``."""
        if fs.native:
            assert self.ops.bb is not None
            return self.ops.bb.solve(fs.Uc, fs.gid[act], rhs)
        na = len(act)
        Ua = fs.Uc if fs.whole and na == fs.info.shape[0] else torch.index_select(
            fs.Uc, 0, fs.gid[act], out=fs.ws[:na])
        return chol_solve(Ua, rhs)

    # ------------------------------------------------------------------ the iteration
    def evaluate(self, u, ezz, st, ms: MemberStep, guess, load: Load):
        """Stresses, tangent and state at ``(u, ezz)`` (:meth:`~.points.PointEvaluator.
        material`, not condensed), the residual ``R`` ``(b, n_r)`` and its norm ``rn``
        ``(b,)`` (inf where not finite)."""
        pts = self.points
        fused = pts.material_fused(u, ezz, st, ms, guess)
        if fused is not None:
            sig, C, szz, C3, st1, dep, x, f = fused
            R = f - load.fext  # f = S u + internal forces
        else:
            sig, C, szz, C3, st1, dep, x = pts.material(u, ezz, st, ms, guess=guess,
                                                        condense=False)
            R = self.residual(u, sig, load.fext)
        rn = R.abs().amax(1) / (load.fref + fint_scale(sig))
        rn = torch.where(torch.isfinite(rn), rn, torch.full_like(rn, float("inf")))
        return sig, C, szz, C3, st1, dep, x, R, rn

    def line_search(self, start: NewtonPoint, du, dz, st, ms: MemberStep, load: Load,
                    inplace=False, n_max=8):
        """Backtracking on the residual norm, per member (a full step is taken when it helps).

        ``start``: the members' iterate (its ``rn`` the residual norms before the step, its
        ``x`` the warm start); ``du``, ``dz``: the Newton update of the displacements and of
        eps_zz (or None). Returns ``(u, ezz, ev)`` at each member's accepted step (the last
        halving is accepted unconditionally). ``inplace``: the evaluations' arrays may be
        written in place (native path: fresh, contiguous arrays).
        """
        u, ezz, rn0, x0 = start
        alpha = torch.ones_like(rn0)
        accepted = torch.zeros_like(rn0, dtype=torch.bool)
        u_new, z_new, ev_new = u, ezz, None
        for k in range(n_max):
            a = alpha[:, None]
            ut = u + a * du
            zt = ezz + a[:, :, None] * dz if dz is not None else None
            evt = self.evaluate(ut, zt, st, ms, x0, load)
            good = ~accepted & ((evt[-1] < rn0) | (k == n_max - 1))
            if ev_new is None and bool(good.all()):
                return ut, zt, evt
            u_new = torch.where(good[:, None], ut, u_new)
            if dz is not None:
                assert zt is not None and z_new is not None
                z_new = torch.where(good[:, None, None], zt, z_new)
            gi = torch.nonzero(good).squeeze(1)
            ev_new = evt if ev_new is None else put(ev_new, take(evt, gi), gi, inplace)
            accepted = accepted | good
            if bool(accepted.all()):
                break
            alpha = torch.where(accepted, alpha, 0.5 * alpha)
            self.stats["ls"] = self.stats.get("ls", 0) + 1
        return u_new, z_new, ev_new

    def _factors(self, b: int, gid) -> _Factors:
        """The factor cache rows of ``b`` members (``gid``: their rows in :attr:`fcache`, or
        None: a fresh cache of their own)."""
        cache = self.fcache
        if cache is None or gid is None:
            cache, gid = self.factor_cache(b), torch.arange(b, device=self.tkw["device"])
        native = "F" in cache
        Uc = cache["F"] if native else cache["U"]
        ws = Uc if native else cache["ws"]  # assembly / gather workspace (dense path)
        return _Factors(Uc, ws, cache["have"][gid], torch.zeros(b, dtype=torch.int32,
                                                                 device=Uc.device),
                        gid, native, len(gid) == Uc.shape[0])  # gid sorted, unique

    def _iterate(self, uk, ezz, st0, ms: MemberStep, load: Load, fs: _Factors):
        """The Newton loop from ``(uk, ezz)``; returns ``(uk, ezz, ok, ev)`` with ``ev`` the
        evaluation the last iteration checked (the members' converged one)."""
        ps = self.problem.plane == "stress"
        b = uk.shape[0]
        ok = torch.zeros(b, dtype=torch.bool, device=uk.device)
        rprev = torch.full((b,), float("inf"), **self.tkw)
        ev = self.evaluate(uk, ezz, st0, ms, None, load)
        last = ev
        ts = self.problem.stepping
        for _ in range(ts.max_iter):
            last = ev
            sig, C, szz, C3, st1, dep, x, R, rn = ev
            conv = rn <= ts.rtol
            if ps:
                conv &= szz.abs().amax((1, 2)) <= 1e-9 * (1.0 + sig.abs().amax((1, 2, 3)))
            ok = conv & torch.isfinite(R).all(1)
            if bool(ok.all()):
                break
            # a member refactors only when it has no factor or its own contraction is poor
            need = (~fs.have | (rn > 0.1 * rprev)) & ~conv
            ni = torch.nonzero(need).squeeze(1)
            if len(ni):
                self._refactor(fs, ni, C3)
            self.stats["iter"] += 1
            rprev = torch.where(conv, rprev, rn)
            bad = fs.info != 0
            act = torch.nonzero(~(conv | bad)).squeeze(1)  # only these members iterate
            if len(act) == 0:
                break
            self.stats["member_iter"] = self.stats.get("member_iter", 0) + len(act)
            du = self._solve(fs, act, -rows(R, act))
            fin = torch.isfinite(du).all(1)
            bad[act] = ~fin
            if not bool(fin.all()):  # a non-finite update: the member stays where it is
                act, du = act[fin], du[fin]
                if len(act) == 0:
                    continue
            dz = self.points.dezz(du, rows(szz, act), rows(C3, act)) if ps else None
            start = NewtonPoint(rows(uk, act), None if ezz is None else rows(ezz, act),
                                rows(rn, act), rows(x, act))
            ua, za, eva = self.line_search(start, du, dz, take((st0,), act)[0], ms.rows(act),
                                           load.rows(act), inplace=fs.native)
            uk = scatter(uk, ua, act, fs.native)
            ezz = None if ezz is None else scatter(ezz, za, act, fs.native)
            ev = put(ev, eva, act, fs.native)
        return uk, ezz, ok, last

    def step(self, u, st: PointState, ms: MemberStep, du0=None, gid=None):
        """One backward-Euler step for a batch: ``u`` ``(b, n_r)`` mm and ``st`` (leading
        shape ``(b, n_e, n_qp)``) at the start, the members' step ``ms``, optional predicted
        increment ``du0`` ``(b, n_r)`` and cache rows ``gid`` ``(b,)`` (see
        :meth:`SpecimenSolver.step <solderpyro.fem.solver.SpecimenSolver.step>`).

        Returns ``(u1, st1, ok (b,), dep_max (b,))``.
        """
        p, T1 = ms.p, ms.th
        needs_grad = torch.is_grad_enabled() and (
            p.requires_grad or u.requires_grad or st.s.requires_grad
            or (st.X is not None and st.X.requires_grad)
            or (st.p_rate is not None and st.p_rate.requires_grad))
        fext = (T1.eps_lin @ self.ops.G).expand(u.shape[0], -1)  # (b, n_r)
        ps = self.problem.plane == "stress"
        with torch.no_grad():
            uk, st0 = u.detach().clone(), st.detach()
            ms0 = MemberStep(p.detach(), T1, ms.dt)
            if du0 is not None:
                uk = uk + du0.detach()
            ezz = None
            if ps:
                e0, s0 = self.points.strain(uk), st0
                if self.ops.band is not None:
                    e0, s0 = e0[:, :self.ops.n_s], split_state(st0, self.ops.n_s)[0]
                ezz = ezz_predictor(e0, s0, T1.eps_th, T1.E, self.points.solder.nu)
            load = Load(fext, fext.abs().amax(1) + 1e-12)
            # modified Newton: start from this member's last factorization (kept across steps)
            fs = self._factors(uk.shape[0], gid)
            uk, ezz, ok, ev = self._iterate(uk, ezz, st0, ms0, load, fs)
            _, _, _, C3, st1, dep, x, _, _ = ev
            dep_max = dep.amax((1, 2))
            cache = self.fcache if self.fcache is not None and gid is not None else None
            if cache is not None:
                cache["have"][gid] = fs.have
            Kt = self.tangent(self.points.condense(C3)) if needs_grad else None
        if needs_grad:  # one Newton step with the graph attached: exact first derivatives
            pts = self.points
            sig, _, szz, _, _, _, _ = pts.material(uk, ezz, st, ms, guess=x, tangent=False,
                                                   C3_fixed=C3)
            R = self.residual(uk, sig, fext)
            du = -chol_solve(torch.linalg.cholesky(Kt, upper=True), R)
            uk = uk + du
            if ps:
                ezz = ezz + pts.dezz(du, szz, C3)
            *_, st1, _, _ = pts.material(uk, ezz, st, ms, guess=x, tangent=False, C3_fixed=C3)
        return uk, st1, ok, dep_max
