"""Batched, implicit FE solver of the layered specimen with Anand solder.

One solve advances ``B`` parameter sets together. The mesh, the elastic bars and their
condensation (:mod:`solderpyro.fem.assembly`) are shared by the whole batch; per member only the
solder layer is nonlinear, and its retained system is solved with a batched dense Cholesky.

Time stepping: a deterministic grid (:func:`~solderpyro.fem.loading.time_grid`) shared by the
batch; a member whose Newton iteration fails, or whose inelastic strain increment exceeds
``dep_max``, is sub-stepped on its own (recursive halving), so a result never depends on the
other members of the batch. A member that fails at the deepest level is reported (flag + reason)
and its outputs after the failure are NaN; the others are unaffected.

Differentiability: the Newton iterations run without autograd; at each step the converged
solution is corrected by one Newton step with the graph attached (implicit-function theorem),
so outputs are differentiable with respect to the Anand constants.

Physical effects (:mod:`solderpyro.effects`): ``effects=(...)`` appends the effects' parameters
to the nine constants of each member. They enter through :class:`~solderpyro.effects.EffectSet`
only (temperature history, stress-free temperature and pre-history, thermal strains, solder
modulus, observation), so temperature and thermal strains become per-member tensors; the solver
core never names an effect. Without effects the solver runs the baseline path unchanged.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp
import torch

from ..effects import Effect, EffectSet
from ..materials.elastic import IP, ZZ, condense_zz
from ..materials.integrate import (
    PointState,
    Tangent3D,
    _full_strain,
    ezz_predictor,
    initial_state,
)
from ..params import ANAND_NAMES
from .assembly import condense, linear_system
from .elements import bbar, edofs, q4_kinematics
from .loading import ThermalCycle, time_grid
from .mesh import build_mesh, locate
from .problem import Problem

SDIRK_GAMMA = 1.0 - 0.5 ** 0.5
N_ANAND = len(ANAND_NAMES)


@dataclass
class SolveResult:
    """Outputs of a batched solve.

    Attributes:
        times: ``(n_time,)`` output times, s.
        names: ``n_out`` output labels (e.g. ``"A", "B"``, grid labels).
        V: ``(B, n_time, n_out)`` vertical displacement relative to O, um.
        ok: ``(B,)`` bool, False for members that failed to converge.
        reasons: ``B`` strings, empty for converged members.
        n_steps: number of grid steps; ``n_substeps``: extra sub-steps taken, summed over members.
    """

    times: torch.Tensor
    names: list
    V: torch.Tensor
    ok: torch.Tensor
    reasons: list
    n_steps: int = 0
    n_substeps: int = 0
    extra: dict = field(default_factory=dict)


@dataclass(frozen=True)
class _Thermo:
    """Temperature-dependent inputs at one instant of the solve.

    Attributes:
        T: temperature, degC; eps_th: the solder's free thermal strain; E: its Young's
            modulus, MPa. Floats in the baseline model; ``(b, 1, 1)`` per member with effects.
        eps_lin: free thermal strains of the linear materials, ``(n_mat,)`` or ``(b, n_mat)``.
        per_member: whether the fields are per batch member (then :meth:`index` selects rows).
    """

    T: Any
    eps_th: Any
    E: Any
    eps_lin: torch.Tensor
    per_member: bool = False

    def index(self, idx) -> _Thermo:
        if not self.per_member:
            return self
        return _Thermo(self.T[idx], self.eps_th[idx], self.E[idx], self.eps_lin[idx], True)


class SpecimenSolver:
    """FE model of a :class:`~solderpyro.fem.problem.Problem`, set up once, solved for batches.

    Args:
        problem: geometry, materials, loading and outputs.
        field_points: optional ``(labels, (n_pt, 2) array)`` extra points reported as V (mm).
        dtype, device: torch dtype/device of the solve (float64 recommended).
        effects: physical effects switched on (names of :data:`solderpyro.effects.EFFECTS`,
            :class:`~solderpyro.effects.Effect` instances, or an
            :class:`~solderpyro.effects.EffectSet`); their parameters follow the nine Anand
            constants in ``params``, in this order (see :meth:`param_names`).
    """

    def __init__(self, problem: Problem, field_points=None, dtype=torch.float64,
                 device="cpu", effects: EffectSet | Sequence[str | Effect] = ()) -> None:
        self.problem = problem
        self.effects: EffectSet | None = (effects if isinstance(effects, EffectSet)
                                          else EffectSet(effects) if effects else None)
        if self.effects is not None and len(self.effects) == 0:
            self.effects = None
        self._fx: EffectSet | None = None  # the effects bound to the running solve's times
        self.tkw = dict(dtype=dtype, device=torch.device(device))
        self.mesh = mesh = build_mesh(problem.layers, problem.half_length, problem.mesh)
        nonlin = np.array([problem.materials[lay.material].nonlinear for lay in mesh.layers])
        el_nl = np.nonzero(nonlin[mesh.region])[0]
        el_lin = np.nonzero(~nonlin[mesh.region])[0]
        if len(el_nl) == 0:
            raise ValueError("problem has no nonlinear (solder) region")
        keys = {mesh.layers[mesh.region[e]].material for e in el_nl}
        if len(keys) != 1:
            raise ValueError("exactly one nonlinear material is supported")
        self.solder_key = keys.pop()
        self.solder = problem.materials[self.solder_key]
        fixed = self._dirichlet()
        n_dof = 2 * mesh.n_node
        free = np.setdiff1d(np.arange(n_dof), fixed)
        nl_dofs = np.unique(edofs(mesh.elems[el_nl]))
        r = np.intersect1d(free, nl_dofs)
        c = np.setdiff1d(free, r)
        self.n_r = len(r)
        # observation operator: V(P) - V(O)
        names, pts = list(problem.points), np.array(list(problem.points.values()), float)
        if field_points is not None:
            names += list(field_points[0])
            pts = np.concatenate([pts, np.asarray(field_points[1], float)])
        self.names = names
        self.x_out = torch.as_tensor(pts[:, 0].copy(), **self.tkw)  # (n_out,) mm
        Hobs = self._observation(pts)
        K, loads = linear_system(mesh, problem, el_lin)
        cond = condense(K, loads, Hobs, r, c)
        t = lambda a: torch.as_tensor(np.ascontiguousarray(a), **self.tkw)  # noqa: E731
        self.S = t(cond.S)
        self.lin_keys = list(cond.g)
        self.G = torch.stack([t(cond.g[k]) for k in cond.g])  # (n_mat, n_r)
        self.Hobs = t(cond.H)  # (n_out, n_r)
        self.hobs = torch.stack([t(cond.h[k]) for k in cond.h])  # (n_mat, n_out)
        # solder element data on the retained dofs; a fixed dof points at dof 0 with a zero
        # B-matrix column, so it contributes nothing to strains, forces or tangents
        gmap = np.full(n_dof, -1)
        gmap[r] = np.arange(self.n_r)
        ed = gmap[edofs(mesh.elems[el_nl])]
        B, wdet = q4_kinematics(mesh.nodes[mesh.elems[el_nl]])
        if problem.plane == "strain":
            B = bbar(B, wdet)
        B = B * (ed >= 0)[:, None, None, :]
        self.edof = torch.as_tensor(np.maximum(ed, 0), device=self.tkw["device"])
        self.B, self.wdet = t(B), t(wdet)  # (n_e, n_qp, 3, 8), (n_e, n_qp)
        self.Bw = self.B * self.wdet[..., None, None]
        n_e = self.B.shape[0]
        self.Be = self.B.reshape(n_e, -1, 8)  # (n_e, n_qp*3, 8)
        self.BweT = self.Bw.reshape(n_e, -1, 8).transpose(1, 2).contiguous()  # (n_e, 8, n_qp*3)
        self.kidx = (self.edof[:, :, None] * self.n_r + self.edof[:, None, :]).reshape(-1)
        self.el_solder = el_nl
        self.stats = {"factor": 0, "iter": 0}
        self._fcache: dict[str, torch.Tensor] | None = None

    def param_names(self, times=None) -> list[str]:
        """Names of the ``params`` columns: the nine Anand constants, then the effects'
        parameters (for output times ``times``, s: an observation effect may have one
        parameter per image; None: the effects' defaults)."""
        if self.effects is None:
            return list(ANAND_NAMES)
        fx = self.effects if times is None else self.effects.bind(times)
        return [*ANAND_NAMES, *fx.names]

    # ------------------------------------------------------------------ set-up helpers
    def _dirichlet(self) -> np.ndarray:
        mesh, (x0, y0) = self.mesh, self.problem.origin
        on_axis = np.nonzero(np.abs(mesh.nodes[:, 0] - x0) < 1e-9)[0]
        d = np.hypot(mesh.nodes[:, 0] - x0, mesh.nodes[:, 1] - y0)
        o = int(np.argmin(d))
        if d[o] > 1e-9:
            raise ValueError(f"origin O={self.problem.origin} is not a mesh node")
        self.node_O = o
        return np.unique(np.concatenate([2 * on_axis, [2 * o + 1]]))

    def _observation(self, pts: np.ndarray) -> sp.csr_matrix:
        mesh = self.mesh
        q = pts.copy()
        if self.problem.mesh.half:
            q[:, 0] = np.abs(q[:, 0])  # V is even in x about the symmetry line
        el, w = locate(mesh, q)
        rows = np.repeat(np.arange(len(q)), 4)
        cols = (2 * mesh.elems[el] + 1).ravel()
        H = sp.csr_matrix((w.ravel(), (rows, cols)), shape=(len(q), 2 * mesh.n_node))
        Ho = sp.csr_matrix(([1.0] * len(q), (np.arange(len(q)), [2 * self.node_O + 1] * len(q))),
                           shape=H.shape)
        return (H - Ho).tocsr()

    # ------------------------------------------------------------------ physics per step
    def _eps_th_lin(self, T_C):
        """Free thermal strains ``(n_mat,)`` of the linear materials at T (degC)."""
        mats, T0 = self.problem.materials, self.problem.T_ref_C
        return torch.tensor([float(mats[k].thermal_strain(T_C, T0)) for k in self.lin_keys],
                            **self.tkw)

    def _f_ext(self, T_C):
        """Condensed thermal force ``(n_r,)`` of the elastic regions at temperature T (degC)."""
        return self._eps_th_lin(T_C) @ self.G

    def _thermo_T(self, T_C: float) -> _Thermo:
        """Baseline inputs at a uniform temperature ``T_C`` (degC), shared by the batch."""
        sol, T0 = self.solder, self.problem.T_ref_C
        return _Thermo(T_C, sol.thermal_strain(T_C, T0), sol.modulus(T_C), self._eps_th_lin(T_C))

    def _as_thermo(self, th) -> _Thermo:
        return th if isinstance(th, _Thermo) else self._thermo_T(float(th))

    def _thermo(self, t: float, p: torch.Tensor) -> _Thermo:
        """Inputs at time ``t`` (s) for the members ``p`` ``(b, 9 + n_eff)``: the program's
        temperature in the baseline model, else per member through the bound effects."""
        pr, fx = self.problem, self._fx
        if fx is None:
            return self._thermo_T(pr.cycle(t))
        q = p[:, N_ANAND:]
        T = fx.temperature(pr.cycle, t, pr.T_ref_C, q)  # (b,)
        T_ref = fx.stress_free(pr.T_ref_C, q)  # (b,)
        mats = pr.materials
        eps_lin = torch.stack([fx.thermal_strain(mats[k], T, T_ref, q)
                               for k in self.lin_keys], -1)  # (b, n_mat)
        eps_th = fx.thermal_strain(self.solder, T, T_ref, q)
        E = fx.modulus(self.solder, T, q)
        return _Thermo(T[:, None, None], eps_th[:, None, None], E[:, None, None], eps_lin, True)

    def _strain(self, u):
        """In-plane strains ``(b, n_e, n_qp, 3)``: one small matrix product per element, with
        the batch as the columns (much cheaper than one 3x8 product per point)."""
        b = u.shape[0]
        ue = u[:, self.edof].permute(1, 2, 0)  # (n_e, 8, b)
        return torch.bmm(self.Be, ue).permute(2, 0, 1).reshape(b, *self.B.shape[:3])

    def _material(self, u, ezz, st, p, T_C, dt, tangent=True, guess=None, C3_fixed=None,
                  condense=True):
        """Solder update at all Gauss points for displacements ``u`` and out-of-plane ``ezz``.

        ``T_C``: the temperature (degC, float) or the inputs of :meth:`_thermo`; ``p``:
        ``(b, 9 + n_eff)`` (the Anand constants are its first nine columns).

        Returns ``(sigma_ip, C_ip, sigma_zz, C3, new_state, dep, x)``: in plane stress the
        in-plane stress and tangent are condensed on eps_zz (the residual of sigma_zz = 0 is
        eliminated with the Newton update of eps_zz, so the global iteration drives it to zero).
        With ``condense=False`` the in-plane tangent ``C_ip`` is not formed (None); the Newton
        loop condenses ``C3`` only for the members it refactors (:meth:`_condense`).
        """
        eps = self._strain(u)
        if ezz is None:
            ezz = torch.zeros_like(eps[..., 0])
        th = self._as_thermo(T_C)
        kw = {"eps_th": th.eps_th, "E": th.E} if th.per_member else {}
        sig, st1, C3, dep, x = self.solder.update(
            _full_strain(eps, ezz), st, p[:, None, None, :N_ANAND], th.T, self.problem.T_ref_C,
            dt, guess=guess, tangent="factored" if tangent else False, **kw)
        sig_ip, szz = sig[..., IP], sig[..., ZZ]
        C3 = C3 if C3_fixed is None else C3_fixed
        C = None
        if self.problem.plane == "stress":
            cz = _col_zz(C3)
            cz = cz[..., IP] / cz[..., ZZ, None]
            sig_ip = sig_ip - cz * szz[..., None]
        if tangent and condense:
            C = self._condense(C3)
        return sig_ip, C, szz, C3, st1, dep, x

    def _condense(self, C3):
        """In-plane tangent ``(..., 3, 3)`` from the 3-D one (plane stress or strain)."""
        return condense_zz(C3.full() if isinstance(C3, Tangent3D) else C3, self.problem.plane)

    def _residual(self, u, sigma, fext):
        b, n_e = u.shape[0], self.B.shape[0]
        sg = sigma.reshape(b, n_e, -1).permute(1, 2, 0)  # (n_e, n_qp*3, b)
        fe = torch.bmm(self.BweT, sg).permute(2, 0, 1)  # (b, n_e, 8)
        return (u @ self.S - fext).index_add(1, self.edof.reshape(-1), fe.reshape(b, -1))

    def _tangent(self, C, out=None):
        """Assembled retained tangent ``(b, n_r, n_r)``, written into ``out`` when given."""
        b = C.shape[0]
        CB = C @ self.B  # (b, n_e, n_qp, 3, 8)
        Ke = (self.Bw.transpose(-1, -2) @ CB).sum(2)  # (b, n_e, 8, 8)
        n = self.n_r
        K = torch.empty(b, n, n, **self.tkw) if out is None else out
        K.copy_(self.S.expand(b, n, n))  # into existing memory: no fresh 47 MB pages per call
        K.view(b, n * n).index_add_(1, self.kidx, Ke.reshape(b, -1))
        return K

    def _factor_cache(self, b):
        """Per-member upper Cholesky factors ``U`` (``K = U^T U``) kept across iterations and
        steps, a flag per member, and a workspace of the same size (assembly, gathers)."""
        n = self.n_r
        return {"U": torch.zeros(b, n, n, **self.tkw),
                "have": torch.zeros(b, dtype=torch.bool, device=self.tkw["device"]),
                "ws": torch.empty(b, n, n, **self.tkw)}

    def step(self, u, st: PointState, p, T1, dt, du0=None, gid=None):
        """One backward-Euler step for a batch.

        Args:
            u: ``(b, n_r)`` start-of-step retained displacements, mm.
            st: start-of-step Gauss-point state, leading shape ``(b, n_e, n_qp)``.
            p: ``(b, 9 + n_eff)`` Anand constants (then effect parameters); T1: end-of-step
                temperature, degC (float), or the inputs of :meth:`_thermo`; dt: step, s.
            du0: optional ``(b, n_r)`` predicted displacement increment (Newton's start).
            gid: optional ``(b,)`` indices of these members in the batch of the running solve;
                their Cholesky factors are reused across steps (modified Newton).
        Returns:
            ``(u1, st1, ok (b,), dep_max (b,))``.
        """
        needs_grad = torch.is_grad_enabled() and (p.requires_grad or u.requires_grad
                                                  or st.s.requires_grad)
        T1 = self._as_thermo(T1)
        fext = (T1.eps_lin @ self.G).expand(u.shape[0], -1)  # (b, n_r)
        ok = torch.zeros(u.shape[0], dtype=torch.bool, device=u.device)
        ps = self.problem.plane == "stress"
        sol = self.solder
        with torch.no_grad():
            uk, p0, st0 = u.detach().clone(), p.detach(), st.detach()
            if du0 is not None:
                uk = uk + du0.detach()
            ezz = None
            if ps:
                ezz = ezz_predictor(self._strain(uk), st0, T1.eps_th, T1.E, sol.nu)
            fref = fext.abs().amax(1) + 1e-12
            b = uk.shape[0]
            x = None
            # modified Newton: start from this member's last factorization (kept across steps)
            cache = self._fcache
            if cache is None or gid is None:
                cache, gid = self._factor_cache(b), torch.arange(b, device=uk.device)
            Uc, ws = cache["U"], cache["ws"]
            whole = len(gid) == Uc.shape[0]  # gid is sorted and unique: the identity
            have = cache["have"][gid]
            info = torch.zeros(b, dtype=torch.int32, device=uk.device)
            rprev = torch.full((b,), float("inf"), **self.tkw)
            ev = self._eval(uk, ezz, st0, p0, T1, dt, None, fext, fref)
            ts = self.problem.stepping
            max_iter, rtol = ts.max_iter, ts.rtol
            for _ in range(max_iter):
                sig, C, szz, C3, st1, dep, x, R, rn = ev
                conv = rn <= rtol
                if ps:
                    conv &= szz.abs().amax((1, 2)) <= 1e-9 * (1.0 + sig.abs().amax((1, 2, 3)))
                ok = conv & torch.isfinite(R).all(1)
                if bool(ok.all()):
                    break
                # a member refactors only when it has no factor or its own contraction is poor
                need = (~have | (rn > 0.1 * rprev)) & ~conv
                ni = torch.nonzero(need).squeeze(1)
                k = len(ni)
                if k:
                    Kw = self._tangent(self._condense(_rows(C3, ni)), out=ws[:k])
                    if whole and k == b:  # factor straight into the cache
                        _, ii = torch.linalg.cholesky_ex(Kw, upper=True, out=(Uc, info))
                    else:
                        ii = torch.empty(k, dtype=info.dtype, device=info.device)
                        torch.linalg.cholesky_ex(Kw, upper=True, out=(Kw, ii))
                        Uc.index_copy_(0, gid[ni], Kw)
                        info[ni] = ii
                    have[ni] = ii == 0
                    self.stats["factor"] += k
                self.stats["iter"] += 1
                rprev = torch.where(conv, rprev, rn)
                bad = info != 0
                act = torch.nonzero(~(conv | bad)).squeeze(1)  # only these members iterate
                na = len(act)
                if na == 0:
                    break
                if whole and na == b:
                    Ua = Uc
                else:
                    Ua = torch.index_select(Uc, 0, gid[act], out=ws[:na])
                self.stats["member_iter"] = self.stats.get("member_iter", 0) + na
                du = _chol_solve(Ua, -_rows(R, act))
                bad[act] = ~torch.isfinite(du).all(1)
                bad_a = _rows(bad, act)
                du = torch.where(bad_a[:, None], torch.zeros_like(du), du)
                dz = self._dezz(du, _rows(szz, act), _rows(C3, act)) if ps else None
                ua, za, eva = self._line_search(
                    _rows(uk, act), None if ezz is None else _rows(ezz, act), du, dz,
                    _take(ev, act), _take((st0,), act)[0], _rows(p0, act), _rows(T1, act), dt,
                    _rows(fext, act), _rows(fref, act), bad_a)
                uk = _scatter(uk, ua, act)
                ezz = None if ezz is None else _scatter(ezz, za, act)
                ev = _put(ev, eva, act)
            dep_max = dep.amax((1, 2))
            cache["have"][gid] = have
            Kt = self._tangent(self._condense(C3)) if needs_grad else None  # (b, n_r, n_r)
        if needs_grad:  # one Newton step with the graph attached: exact first derivatives
            sig, _, szz, _, _, _, _ = self._material(uk, ezz, st, p, T1, dt, tangent=False,
                                                     guess=x, C3_fixed=C3)
            R = self._residual(uk, sig, fext)
            du = -_chol_solve(torch.linalg.cholesky(Kt, upper=True), R)
            uk = uk + du
            if ps:
                ezz = ezz + self._dezz(du, szz, C3)
            *_, st1, _, _ = self._material(uk, ezz, st, p, T1, dt, tangent=False, guess=x,
                                           C3_fixed=C3)
        return uk, st1, ok, dep_max

    def _eval(self, u, ezz, st, p, T1, dt, guess, fext, fref):
        sig, C, szz, C3, st1, dep, x = self._material(u, ezz, st, p, T1, dt, guess=guess,
                                                      condense=False)
        R = self._residual(u, sig, fext)
        rn = R.abs().amax(1) / (fref + self._fint_scale(sig))
        rn = torch.where(torch.isfinite(rn), rn, torch.full_like(rn, float("inf")))
        return sig, C, szz, C3, st1, dep, x, R, rn

    def _line_search(self, u, ezz, du, dz, ev, st, p, T1, dt, fext, fref, frozen, n_max=8):
        """Backtracking on the residual norm, per member (a full step is taken when it helps)."""
        rn0 = ev[-1]
        alpha = torch.ones_like(rn0)
        accepted = frozen.clone()
        u_new, z_new, ev_new = u, ezz, ev
        for k in range(n_max):
            a = alpha[:, None]
            ut = u + a * du
            zt = ezz + a[:, :, None] * dz if dz is not None else None
            evt = self._eval(ut, zt, st, p, T1, dt, ev[6], fext, fref)
            good = ~accepted & ((evt[-1] < rn0) | (k == n_max - 1))
            u_new = torch.where(good[:, None], ut, u_new)
            if dz is not None:
                z_new = torch.where(good[:, None, None], zt, z_new)
            gi = torch.nonzero(good).squeeze(1)
            ev_new = _put(ev_new, _take(evt, gi), gi)
            accepted = accepted | good
            if bool(accepted.all()):
                break
            alpha = torch.where(accepted, alpha, 0.5 * alpha)
            self.stats["ls"] = self.stats.get("ls", 0) + 1
        return u_new, z_new, ev_new

    def _dezz(self, du, szz, C3):
        """Newton update of eps_zz that accompanies a displacement update ``du`` (plane stress)."""
        deps = self._strain(du)  # linear in u
        rz = C3.row_zz() if isinstance(C3, Tangent3D) else C3[..., ZZ, :]
        return -(szz + (rz[..., IP] * deps).sum(-1)) / rz[..., ZZ]

    @staticmethod
    def _fint_scale(sig):
        return sig.abs().amax((1, 2, 3)) * 1e-3

    def observe(self, u, T_C):
        """V relative to O at the output points, ``(b, n_out)`` in um.

        Args:
            u: ``(b, n_r)`` retained displacements, mm.
            T_C: temperature, degC (float), or the inputs of :meth:`_thermo` (per member).
        """
        off = self._as_thermo(T_C).eps_lin @ self.hobs  # (n_out,) or (b, n_out)
        return 1e3 * (u @ self.Hobs.T + off)

    # ------------------------------------------------------------------ time loop
    def solve(self, params: torch.Tensor, times, progress: bool = False) -> SolveResult:
        """Run the thermal cycle for a batch of Anand parameter sets (and effect parameters).

        Args:
            params: ``(B, 9 + n_eff)``: the Anand constants in ANAND_NAMES order (MPa, K, 1/s),
                then the effects' parameters in the order of :meth:`param_names` ``(times)``
                (``n_eff = 0`` without effects); may require grad, in which case the outputs
                are differentiable with respect to every column.
            times: output times, s (each in ``(0, cycle end]``).
            progress: show a tqdm bar over the time steps.
        Returns:
            :class:`SolveResult` with ``V`` of shape ``(B, n_time, n_out)`` in um. With an
            effect that simulates a pre-history, V is relative to the state at t = 0.
        """
        times = sorted(float(t) for t in times)
        params, grid, t_zero = self._prepare(params, times)
        try:
            out, alive, reasons, nsub = self._run(params, grid, times, t_zero, progress)
            if self._fx is not None:
                out = self._fx.observe(out, self.x_out, self.problem.origin[0],
                                       params[:, N_ANAND:])
        finally:
            self._fcache = None  # free the factors
            self._fx = None
        return SolveResult(torch.tensor(times, **self.tkw), list(self.names), out, alive,
                           reasons, len(grid) - 1, nsub)

    def _prepare(self, params, times: list[float]):
        """Validate ``params``, bind the effects to ``times`` and build the time grid.

        Returns ``(params, grid (n_step + 1,), t_zero)``: the grid starts at ``-D`` when an
        effect simulates a pre-history of duration D; ``t_zero`` says whether there is one (t = 0
        is then a grid point where the reference of V is taken and the predictor restarts).
        """
        params = torch.as_tensor(params, **self.tkw)
        fx = None if self.effects is None else self.effects.bind(times)
        n_p = N_ANAND + (0 if fx is None else fx.n_params)
        if params.ndim != 2 or params.shape[1] != n_p:
            what = "" if fx is None else f" ({', '.join([*ANAND_NAMES, *fx.names])})"
            raise ValueError(f"params must have shape (B, {n_p}){what}, got "
                             f"{tuple(params.shape)}")
        if not torch.isfinite(params).all():
            raise ValueError("params contain NaN or inf")
        grid = time_grid(self.problem.cycle, tuple(times), self.problem.stepping)
        pre = None if fx is None else fx.pre_history()
        if fx is not None:
            fx.check(params[:, N_ANAND:])
        if pre is not None:  # a shared grid for the pre-history: the box's largest change
            D, dT = pre
            T0 = self.problem.cycle(0.0)
            g0 = time_grid(ThermalCycle((0.0, D), (T0 + dT, T0)), (), self.problem.stepping)
            grid = np.concatenate([g0[:-1] - D, grid])
        self._fx = fx
        return params, grid, pre is not None

    def _run(self, params, grid, times, t_zero: bool, progress: bool):
        """The time loop; returns ``(V (B, n_time, n_out), alive (B,), reasons, n_substeps)``."""
        b = params.shape[0]
        cyc = self.problem.cycle
        u = torch.zeros(b, self.n_r, **self.tkw)
        st = initial_state((b, *self.wdet.shape), params[:, 0, None, None], **self.tkw)
        out = torch.full((b, len(times), len(self.names)), float("nan"), **self.tkw)
        alive = torch.ones(b, dtype=torch.bool, device=u.device)
        reasons = [""] * b
        nsub = [0]
        self._fcache = self._factor_cache(b)
        vel, rate_prev = torch.zeros_like(u), float("nan")
        V0 = None
        it = range(1, len(grid))
        if progress:
            from tqdm.auto import tqdm
            it = tqdm(it, desc=f"FE cycle (B={b})", unit="step")
        outs = []
        for k in it:
            t0, t1 = float(grid[k - 1]), float(grid[k])
            idx = torch.nonzero(alive).squeeze(1)
            if len(idx) == 0:
                break
            rate = (cyc(t1) - cyc(t0)) / (t1 - t0)
            v0 = vel[idx] if abs(rate - rate_prev) < 1e-12 else None
            u_a, st_a, ok = self._advance(u[idx], st.index(idx), params[idx], t0, t1, 0, nsub,
                                          v0, idx)
            vel = _scatter(vel, (u_a - u[idx]) / (t1 - t0), idx)
            rate_prev = rate
            where = f"T={cyc(t1):.1f} C" if t1 > 0 else "pre-history"
            for j in torch.nonzero(~ok).squeeze(1).tolist():
                reasons[int(idx[j])] = (f"no convergence in the step to t={t1:g} s "
                                        f"({where}) after "
                                        f"{self.problem.stepping.max_depth} halvings")
            u, st = _scatter(u, u_a, idx), _scatter_state(st, st_a, idx)
            alive = alive.clone()
            alive[idx] = ok
            if t_zero and t1 == 0.0:  # the Moire reference image: V relative to this state;
                V0 = self.observe(u, self._thermo(0.0, params))  # the cycle starts afresh
                vel, rate_prev = torch.zeros_like(u), float("nan")
                self._fcache["have"].zero_()
            if any(abs(t1 - tt) < 1e-9 for tt in times):
                v = self.observe(u, self._thermo(t1, params))
                v = v if V0 is None else v - V0
                v = torch.where(alive[:, None], v, torch.full_like(v, float("nan")))
                outs.append(v)
        for i in range(len(outs)):
            out = out.clone()
            out[:, i] = outs[i]
        return out, alive, reasons, nsub[0]

    def time_step(self, u, st, p, t0, t1, du0=None, gid=None):
        """Advance a batch from t0 to t1 with the configured scheme; see :meth:`step`.

        SDIRK2 (gamma = 1 - 1/sqrt2): stage 1 is backward Euler to t0 + gamma*h; stage 2 is
        backward Euler over gamma*h to t1 from the start state extrapolated with the stage-1
        rates, ``y* = y0 + (1-gamma)/gamma * (y1 - y0)`` (internal variables only). The method is
        L-stable and stiffly accurate, so it keeps backward Euler's robustness for fast
        relaxation while its error falls as h^2.
        """
        h = t1 - t0
        if self.problem.stepping.scheme == "euler":
            return self.step(u, st, p, self._thermo(t1, p), h, du0=du0, gid=gid)
        g = SDIRK_GAMMA
        ua, sa, oka, da = self.step(u, st, p, self._thermo(t0 + g * h, p), g * h,
                                    du0=None if du0 is None else g * du0, gid=gid)
        k = (1.0 - g) / g
        st2 = PointState(st.eps_p + k * (sa.eps_p - st.eps_p), st.s + k * (sa.s - st.s),
                         sa.eps_zz)
        ub, sb, okb, db = self.step(ua, st2, p, self._thermo(t1, p), g * h, du0=k * (ua - u),
                                    gid=gid)
        return ub, sb, oka & okb, torch.maximum(da, db)

    def _advance(self, u, st, p, t0, t1, depth, nsub, vel=None, gid=None):
        """Advance members from t0 to t1, halving the step for those that need it.

        ``vel`` ``(b, n_r)``: displacement rate of the previous step (predictor), or None.
        """
        ts = self.problem.stepping
        du0 = None if vel is None else vel * (t1 - t0)
        u1, st1, ok, dep = self.time_step(u, st, p, t0, t1, du0, gid)
        good = ok & (dep <= ts.dep_max) if depth < ts.max_depth else ok
        if bool(good.all()) or depth >= ts.max_depth:
            return u1, st1, ok
        idx = torch.nonzero(~good).squeeze(1)
        nsub[0] += len(idx)
        tm = 0.5 * (t0 + t1)
        v = None if vel is None else vel[idx]
        g = None if gid is None else gid[idx]
        ua, sa, oka = self._advance(u[idx], st.index(idx), p[idx], t0, tm, depth + 1, nsub, v, g)
        v = (ua - u[idx]) / (tm - t0)
        ub, sb, okb = self._advance(ua, sa, p[idx], tm, t1, depth + 1, nsub, v, g)
        okb = oka & okb
        return (_scatter(u1, ub, idx), _scatter_state(st1, sb, idx),
                _scatter(ok, okb, idx))


def _chol_solve(U, rhs):
    """Solve ``U^T U x = rhs`` for ``rhs`` of shape ``(b, n)`` (two triangular solves; on CPU
    this is ~3x faster than ``torch.cholesky_solve`` for batched single right-hand sides)."""
    y = torch.linalg.solve_triangular(U.mT, rhs.unsqueeze(-1), upper=False)
    return torch.linalg.solve_triangular(U, y, upper=True).squeeze(-1)


def _col_zz(C3):
    """``C3[..., :, ZZ]`` of a 3-D tangent (tensor or :class:`Tangent3D`)."""
    return C3.col_zz() if isinstance(C3, Tangent3D) else C3[..., :, ZZ]


def _rows(a, idx):
    """``a[idx]`` (tensor, ``PointState`` or ``Tangent3D``) for sorted, unique member indices
    ``idx``; ``a`` itself (no copy) when they are all of its members."""
    if isinstance(a, _Thermo):
        return a if not a.per_member or len(idx) == a.eps_lin.shape[0] else a.index(idx)
    if isinstance(a, PointState | Tangent3D):
        n = a.s.shape[0] if isinstance(a, PointState) else a.K.shape[0]
        return a if len(idx) == n else a.index(idx)
    return a if len(idx) == a.shape[0] else a[idx]


def _take(ev, idx):
    """Members ``idx`` of a tuple of batched results."""
    return tuple(None if a is None else _rows(a, idx) for a in ev)


def _put(ev, sub, idx):
    """Write the members ``idx`` of a batched result tuple from ``sub``."""
    out = []
    for a, b in zip(ev, sub, strict=True):
        if a is None:
            out.append(None)
        elif isinstance(a, PointState):
            out.append(_scatter_state(a, b, idx))
        elif isinstance(a, Tangent3D):
            out.append(Tangent3D(*(_scatter(getattr(a, f), getattr(b, f), idx)
                                   for f in ("K", "g2", "coef", "nb"))))
        else:
            out.append(_scatter(a, b, idx))
    return tuple(out)


def _scatter(full, part, idx):
    if part.shape[0] == full.shape[0] and len(idx) == full.shape[0]:
        return part
    out = full.clone()
    out[idx] = part
    return out


def _scatter_state(full: PointState, part: PointState, idx) -> PointState:
    return PointState(_scatter(full.eps_p, part.eps_p, idx), _scatter(full.s, part.s, idx),
                      _scatter(full.eps_zz, part.eps_zz, idx))
