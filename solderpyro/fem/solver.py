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
modulus, the solder's back stress, an elasto-plastic band of a linear region, observation), so
temperature and thermal strains become per-member tensors; the solver core never names an
effect. A back stress adds ``X`` to the Gauss-point state. A plastic band
(:mod:`solderpyro.fem.band`) needs a second discretisation whose retained system includes the
band: it is built once, and each member is solved on it only if its band may yield, else on the
baseline one. Without effects the solver runs the baseline path unchanged.

Native path (CPU, float64, no autograd; :mod:`solderpyro._native`): one C call per Newton
evaluation does the strains, the Anand update, the plane-stress condensation and the internal
forces (:meth:`SpecimenSolver._material_fused`), and the retained tangent is assembled, factored
and solved in its bordered-band form (:mod:`solderpyro.fem.bordered`) instead of dense; the
algorithm and its decisions are the same, results agree to rounding (~1e-13 um). Everything else
(other devices, autograd's correction step, ``SOLDERPYRO_NATIVE=0``, no compiler) runs the torch
code.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp
import torch

from solderpyro import _native
from solderpyro.effects import Effect, EffectSet
from solderpyro.effects.base import PlasticBand
from solderpyro.fem.assembly import condense, linear_system
from solderpyro.fem.band import (
    BandData,
    adjacent_elements,
    band_elements,
    band_update,
    elastic_stress_operator,
    mode_correction,
)
from solderpyro.fem.bordered import BorderedBand
from solderpyro.fem.elements import bbar, edofs, q4_kinematics, qm6_modes
from solderpyro.fem.loading import time_grid
from solderpyro.fem.mesh import build_mesh, locate
from solderpyro.fem.problem import AnandSolder, Problem
from solderpyro.materials.elastic import IP, ZZ, condense_zz, plane_elastic
from solderpyro.materials.integrate import PointState, Tangent3D, ezz_predictor, initial_state
from solderpyro.materials.integrate import full_strain as _full_strain
from solderpyro.params import ANAND_NAMES

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
        C_k: the solder's Prager modulus ``(b, 1, 1)`` MPa, or None (no back stress).
        band: ``(eps_th, sigma_y)``, each ``(b, 1, 1)``, of an elasto-plastic band's material
            (free thermal strain, yield stress MPa), or None (no band).
    """

    T: Any
    eps_th: Any
    E: Any
    eps_lin: torch.Tensor
    per_member: bool = False
    C_k: Any = None
    band: Any = None

    def index(self, idx) -> _Thermo:
        if not self.per_member:
            return self
        return _Thermo(self.T[idx], self.eps_th[idx], self.E[idx], self.eps_lin[idx], True,
                       None if self.C_k is None else self.C_k[idx],
                       None if self.band is None else tuple(a[idx] for a in self.band))


class SpecimenSolver:
    """FE model of a :class:`~solderpyro.fem.problem.Problem`, set up once, solved for batches.

    Args:
        problem: geometry, materials, loading and outputs.
        field_points: optional ``(labels, (n_pt, 2) array)`` extra points reported as V (mm).
        dtype, device: torch dtype/device of the solve (float64 recommended).
        effects: physical effects switched on (names of :data:`solderpyro.effects.EFFECTS`,
            :class:`~solderpyro.effects.Effect` instances, or an
            :class:`~solderpyro.effects.EffectSet`); their parameters follow the nine Anand
            constants in ``params``, in this order (see :meth:`param_names`). An effect with a
            :class:`~solderpyro.effects.base.PlasticBand` (``copper_plasticity``) gets a second,
            banded discretisation; each member is solved on the banded one only if its band
            may yield (:meth:`~solderpyro.effects.Effect.yield_stress` finite), else on the
            baseline one.
        _band: internal: build the banded discretisation of this band.
    """

    def __init__(self, problem: Problem, field_points=None, dtype=torch.float64,
                 device="cpu", effects: EffectSet | Sequence[str | Effect] = (),
                 _band: PlasticBand | None = None) -> None:
        # what __reduce__ rebuilds from: the solver holds native (ctypes) factorizations that
        # do not pickle, so a copy (a Dask worker's) is built anew from its inputs
        self._init_args = (problem, field_points, dtype, str(device), effects, _band)
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
        spec = None if self.effects is None else self.effects.plastic_band()
        el_b = np.zeros(0, dtype=int) if spec is None else self._band_elements(spec, nonlin)
        el_all = el_nl  # the nonlinear elements: the solder, then a band's
        if _band is not None:
            el_lin = np.setdiff1d(el_lin, el_b)
            el_all = np.concatenate([el_nl, el_b])
        fixed = self._dirichlet()
        n_dof = 2 * mesh.n_node
        free = np.setdiff1d(np.arange(n_dof), fixed)
        nl_dofs = np.unique(edofs(mesh.elems[el_all]))
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
        # elastic elements whose stress is checked: the band itself on the baseline path, the
        # ring of elastic elements around it on the banded one
        el_p = el_b if _band is None else adjacent_elements(mesh, el_b, _band.material)
        probe = None
        if spec is not None and len(el_p):
            ed_p = edofs(mesh.elems[el_p]).ravel()
            probe = sp.csr_matrix((np.ones(len(ed_p)), (np.arange(len(ed_p)), ed_p)),
                                  shape=(len(ed_p), n_dof))
        cond = condense(K, loads, Hobs, r, c, probe)
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
        ed = gmap[edofs(mesh.elems[el_all])]
        B, wdet = q4_kinematics(mesh.nodes[mesh.elems[el_all]])
        n_s = len(el_nl)
        if problem.plane == "strain":  # the solder's only: a band keeps B (and its modes)
            B = bbar(B, wdet) if _band is None else np.concatenate(
                [bbar(B[:n_s], wdet[:n_s]), B[n_s:]])
        B = B * (ed >= 0)[:, None, None, :]
        self.edof = torch.as_tensor(np.maximum(ed, 0), device=self.tkw["device"])
        self.B, self.wdet = t(B), t(wdet)  # (n_e, n_qp, 3, 8), (n_e, n_qp)
        self.Bw = self.B * self.wdet[..., None, None]
        n_e = self.B.shape[0]
        self.Be = self.B.reshape(n_e, -1, 8)  # (n_e, n_qp*3, 8)
        self.BweT = self.Bw.reshape(n_e, -1, 8).transpose(1, 2).contiguous()  # (n_e, 8, n_qp*3)
        self.kidx = (self.edof[:, :, None] * self.n_r + self.edof[:, None, :]).reshape(-1)
        # native bordered-band factorization (CPU float64; the dense torch path otherwise)
        self._bb: BorderedBand | None = None
        self._edof32 = torch.as_tensor(np.maximum(ed, 0).astype(np.int32))  # fused native path
        dof_D = np.nonzero(np.abs(cond.S).max(1) > 0)[0]  # where S is nonzero (the border)
        self._S_border = (torch.as_tensor(dof_D.astype(np.int32)), self.S[dof_D][:, dof_D].cpu()
                          .contiguous())
        if self.tkw["device"].type == "cpu" and dtype == torch.float64:
            bb = BorderedBand(cond.S, ed, self.B, self.Bw)
            self._bb = bb if bb.worthwhile() else None
        self.el_solder = el_nl
        self.n_s = n_s  # solder elements come first in the element arrays
        self.band = None if _band is None else self._band_data(_band, el_b, wdet[n_s:])
        self._banded: SpecimenSolver | None = None
        self._peak: torch.Tensor | None = None  # the last _run's checked stresses, (b,) MPa
        self.band_spec = spec
        self._probe = (None if probe is None or spec is None
                       else self._probe_operator(spec, el_p, cond))
        if spec is not None and _band is None:
            self._banded = SpecimenSolver(problem, field_points, dtype, device,
                                          self.effects or (), _band=spec)
        self.stats = {"factor": 0, "iter": 0}
        self._fcache: dict[str, torch.Tensor] | None = None

    def __reduce__(self) -> tuple:
        """Pickle as the constructor's inputs (a copy is set up anew, e.g. once per Dask
        worker); the solver's results do not depend on its history."""
        return (type(self), self._init_args)

    def param_names(self, times=None) -> list[str]:
        """Names of the ``params`` columns: the nine Anand constants, then the effects'
        parameters (for output times ``times``, s: an observation effect may have one
        parameter per image; None: the effects' defaults)."""
        if self.effects is None:
            return list(ANAND_NAMES)
        fx = self.effects if times is None else self.effects.bind(times)
        return [*ANAND_NAMES, *fx.names]

    # ------------------------------------------------------------------ set-up helpers
    def _band_elements(self, spec: PlasticBand, nonlin: np.ndarray) -> np.ndarray:
        """Element indices of the band ``spec`` (``nonlin`` ``(n_layer,)``: nonlinear layers)."""
        mats = self.problem.materials
        if spec.material not in mats or mats[spec.material].nonlinear:
            raise ValueError(f"plastic band: {spec.material!r} is not a linear material of the "
                             f"problem ({', '.join(mats)})")
        el_b = band_elements(self.mesh, spec.material, nonlin, spec.depth)
        if len(el_b) == 0:
            raise ValueError(f"plastic band: no element of {spec.material!r} lies within "
                             f"{spec.depth} mm of the solder")
        return el_b

    def _band_data(self, spec: PlasticBand, el_b: np.ndarray, wdet_b: np.ndarray) -> BandData:
        """Material and incompatible modes of the band elements ``el_b`` (``wdet_b``
        ``(n_eb, n_qp)``)."""
        mat, pr = self.problem.materials[spec.material], self.problem
        G = Gw = None
        if pr.incompatible_modes:
            g = qm6_modes(self.mesh.nodes[self.mesh.elems[el_b]], wdet_b)
            G = torch.as_tensor(g, **self.tkw)
            Gw = torch.as_tensor(g * wdet_b[..., None, None], **self.tkw)
        return BandData(G, Gw, mat.E, mat.nu, spec.H, pr.plane, spec.material)

    def _probe_operator(self, spec: PlasticBand, el_b: np.ndarray, cond):
        """``(M_r (n_r, n_p), M_th (n_mat, n_p))``: in-plane stresses of the elastic (condensed)
        elements ``el_b`` at their points (``n_p = n_el*n_qp*3``),
        ``sigma = u @ M_r + eps_lin @ M_th``."""
        mat, pr = self.problem.materials[spec.material], self.problem
        D, d_th = (a.numpy() for a in plane_elastic(mat.E, mat.nu, pr.plane,
                                                     dtype=torch.float64))
        P = elastic_stress_operator(self.mesh.nodes[self.mesh.elems[el_b]], D,
                                    pr.incompatible_modes)  # (n_eb, n_qp, 3, 8)
        n_eb = len(el_b)
        Pm = np.zeros((P.shape[0] * P.shape[1] * 3, n_eb * 8))  # block diagonal
        for e in range(n_eb):
            Pm[e * 12:(e + 1) * 12, e * 8:(e + 1) * 8] = P[e].reshape(12, 8)
        M_th = np.stack([Pm @ cond.hx[k] - (d_th[None, :] * (k == spec.material)).repeat(
            4 * n_eb, 0).ravel() for k in self.lin_keys])
        t = lambda a: torch.as_tensor(np.ascontiguousarray(a), **self.tkw)  # noqa: E731
        return t((Pm @ cond.Hx).T), t(M_th)

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
        C_k = fx.back_stress_modulus(q)  # (b,) or None
        band = None
        if self.band is not None:
            eb = fx.thermal_strain(mats[self.band.material], T, T_ref, q)
            sy = fx.yield_stress(q)
            assert sy is not None
            band = (eb[:, None, None], sy[:, None, None])
        return _Thermo(T[:, None, None], eps_th[:, None, None], E[:, None, None], eps_lin, True,
                       None if C_k is None else C_k[:, None, None], band)

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
        With a band (:meth:`_material_band`) the arrays cover the band's points too.
        """
        if self.band is not None:
            return self._material_band(u, ezz, st, p, T_C, dt, tangent, guess, C3_fixed,
                                       condense)
        if tangent and not condense and C3_fixed is None:
            fused = self._material_fused(u, ezz, st, p, T_C, dt, guess)
            if fused is not None:
                return fused[:-1]
        eps = self._strain(u)
        if ezz is None:
            ezz = torch.zeros_like(eps[..., 0])
        th = self._as_thermo(T_C)
        kw = {"eps_th": th.eps_th, "E": th.E} if th.per_member else {}
        if th.C_k is not None:
            kw["C_k"] = th.C_k
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

    def _material_fused(self, u, ezz, st, p, T_C, dt, guess):
        """:meth:`_material` (with the factored tangent, not condensed) and the internal forces
        ``(b, n_r)`` appended, in one native call (:func:`solderpyro._native.solder_eval`); None
        where that path does not apply (another device or dtype, autograd, a band, or a solder
        law that overrides :meth:`~solderpyro.fem.problem.AnandSolder.update`)."""
        sol = self.solder
        if (self.band is not None or type(sol).update is not AnandSolder.update
                or self.tkw["device"].type != "cpu"
                or not _native.usable(u, ezz, st.eps_p, st.s, st.X, p, guess)):
            return None
        th = self._as_thermo(T_C)
        if not _native.usable(*(a for a in (th.T, th.eps_th, th.E, th.C_k))):
            return None
        T0 = self.problem.T_ref_C  # what AnandSolder.update passes to return_map_3d
        eps_th = th.eps_th if th.per_member else sol.thermal_strain(th.T, T0)
        E = th.E if th.per_member else sol.modulus(th.T)
        C_k = th.C_k
        if C_k is not None and not isinstance(C_k, torch.Tensor) and C_k == 0:
            C_k = None
        ps = self.problem.plane == "stress"
        sig_ip, szz, eps_p, s, X, dep, x, tg, f = _native.solder_eval(
            u, ezz if ps else None, self._edof32, self.B, self.Bw, self._S_border, st,
            p[:, None, None, :N_ANAND], th.T + 273.15, dt, eps_th, E, sol.nu, C_k, guess, ps)
        ezz_out = ezz.clone() if ezz is not None else torch.zeros_like(szz)
        st1 = PointState(eps_p, s, ezz_out, X)
        return sig_ip, None, szz, Tangent3D(*tg), st1, dep, x, f

    def _material_band(self, u, ezz, st, p, T_C, dt, tangent, guess, C3_fixed, condense):
        """:meth:`_material` with an elasto-plastic band: the solder's points as there (``ezz``,
        ``szz`` are the solder's), then the band's (:func:`~.band.band_update`, which solves
        its own ``eps_zz`` and modes). ``C3`` is a :class:`_BandTangent`; ``sigma_ip``,
        ``dep``, the state and ``x`` cover all points (solder elements first)."""
        n = self.n_s
        eps = self._strain(u)
        if ezz is None:
            ezz = torch.zeros_like(eps[:, :n, :, 0])
        th = self._as_thermo(T_C)
        kw = {"eps_th": th.eps_th, "E": th.E}
        if th.C_k is not None:
            kw["C_k"] = th.C_k
        st_s, st_b = _split_state(st, n)
        sig, st1, C3, dep, x = self.solder.update(
            _full_strain(eps[:, :n], ezz), st_s, p[:, None, None, :N_ANAND], th.T,
            self.problem.T_ref_C, dt, guess=None if guess is None else guess[:, :n],
            tangent="factored" if tangent else False, **kw)
        sig_ip, szz = sig[..., IP], sig[..., ZZ]
        C3 = C3 if C3_fixed is None else C3_fixed.solder
        if self.problem.plane == "stress":
            cz = _col_zz(C3)
            sig_ip = sig_ip - cz[..., IP] / cz[..., ZZ, None] * szz[..., None]
        sb, Cb, st1b, dgb, xb = band_update(self.band, eps[:, n:], st_b, *th.band,
                                            None if guess is None else guess[:, n:], tangent)
        C3m = _BandTangent(C3, Cb) if tangent else None
        C = self._condense(C3m) if tangent and condense else None
        return (torch.cat([sig_ip, sb], 1), C, szz, C3m, _cat_state(st1, st1b),
                torch.cat([dep, dgb], 1), torch.cat([x, xb], 1))

    def _condense(self, C3):
        """In-plane tangent ``(..., 3, 3)`` from the 3-D one (plane stress or strain)."""
        if isinstance(C3, _BandTangent):
            return torch.cat([self._condense(C3.solder), C3.band], 1)
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
        if self.band is not None and self.band.G is not None:  # condense the band's modes
            Ke[:, self.n_s:] -= mode_correction(self.band, self.B[self.n_s:],
                                                self.Bw[self.n_s:], C[:, self.n_s:])
        K = torch.empty(b, n, n, **self.tkw) if out is None else out
        K.copy_(self.S.expand(b, n, n))  # into existing memory: no fresh 47 MB pages per call
        K.view(b, n * n).index_add_(1, self.kidx, Ke.reshape(b, -1))
        return K

    def _native_linalg(self) -> bool:
        """Whether the Newton solves use the native bordered-band factorization."""
        return self._bb is not None and _native.enabled() and _native.library() is not None

    def _factor_cache(self, b):
        """Per-member factors kept across iterations and steps, a flag per member, and (dense
        path) a workspace of the same size (assembly, gathers). Native path: ``F`` ``(b, nbuf)``
        bordered-band factors (:class:`~.bordered.BorderedBand`); dense path: upper Cholesky
        factors ``U`` ``(b, n_r, n_r)`` (``K = U^T U``)."""
        n = self.n_r
        if self._native_linalg():
            assert self._bb is not None
            return {"F": torch.zeros(b, self._bb.nbuf, **self.tkw),
                    "have": torch.zeros(b, dtype=torch.bool, device=self.tkw["device"])}
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
        needs_grad = torch.is_grad_enabled() and (
            p.requires_grad or u.requires_grad or st.s.requires_grad
            or (st.X is not None and st.X.requires_grad))
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
                e0, s0 = self._strain(uk), st0
                if self.band is not None:
                    e0, s0 = e0[:, :self.n_s], _split_state(st0, self.n_s)[0]
                ezz = ezz_predictor(e0, s0, T1.eps_th, T1.E, sol.nu)
            fref = fext.abs().amax(1) + 1e-12
            b = uk.shape[0]
            x = None
            # modified Newton: start from this member's last factorization (kept across steps)
            cache = self._fcache
            if cache is None or gid is None:
                cache, gid = self._factor_cache(b), torch.arange(b, device=uk.device)
            native = "F" in cache
            Uc = cache["F"] if native else cache["U"]
            ws = Uc if native else cache["ws"]  # assembly / gather workspace (dense path)
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
                if k and native:
                    ii = self._factor_native(Uc, gid[ni], _rows(C3, ni))
                    info[ni] = ii
                    have[ni] = ii == 0
                    self.stats["factor"] += k
                elif k:
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
                self.stats["member_iter"] = self.stats.get("member_iter", 0) + na
                if native:
                    assert self._bb is not None
                    du = self._bb.solve(Uc, gid[act], -_rows(R, act))
                else:
                    Ua = Uc if whole and na == b else torch.index_select(Uc, 0, gid[act],
                                                                         out=ws[:na])
                    du = _chol_solve(Ua, -_rows(R, act))
                fin = torch.isfinite(du).all(1)
                bad[act] = ~fin
                if not bool(fin.all()):  # a non-finite update: the member stays where it is
                    act, du = act[fin], du[fin]
                    if len(act) == 0:
                        continue
                dz = self._dezz(du, _rows(szz, act), _rows(C3, act)) if ps else None
                ua, za, eva = self._line_search(
                    _rows(uk, act), None if ezz is None else _rows(ezz, act), du, dz,
                    _rows(rn, act), _rows(x, act), _take((st0,), act)[0], _rows(p0, act),
                    _rows(T1, act), dt, _rows(fext, act), _rows(fref, act), inplace=native)
                uk = _scatter(uk, ua, act, native)
                ezz = None if ezz is None else _scatter(ezz, za, act, native)
                ev = _put(ev, eva, act, native)
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

    def _factor_native(self, F, slots, C3):
        """Assemble and factor (bordered band) the tangents ``C3`` (factored, full, or with a
        band) of ``k`` members into the rows ``slots`` of ``F``; returns ``info`` ``(k,)``."""
        bb = self._bb
        assert bb is not None
        ps = self.problem.plane == "stress"
        if isinstance(C3, _BandTangent):
            dKe = None
            if self.band is not None and self.band.G is not None:
                dKe = mode_correction(self.band, self.B[self.n_s:], self.Bw[self.n_s:],
                                      C3.band)
            if isinstance(C3.solder, Tangent3D):
                t = C3.solder
                return bb.factor(F, slots, (t.K, t.g2, t.coef, t.nb), C3.band, self.n_s, dKe,
                                 ps)
            Cip = torch.cat([condense_zz(C3.solder, self.problem.plane), C3.band], 1)
            return bb.factor(F, slots, None, Cip, 0, dKe, ps)
        if isinstance(C3, Tangent3D):
            return bb.factor(F, slots, (C3.K, C3.g2, C3.coef, C3.nb), None, self.n_s, None, ps)
        return bb.factor(F, slots, None, self._condense(C3), 0, None, ps)

    def _eval(self, u, ezz, st, p, T1, dt, guess, fext, fref):
        fused = self._material_fused(u, ezz, st, p, T1, dt, guess)
        if fused is not None:
            sig, C, szz, C3, st1, dep, x, f = fused
            R = f - fext  # f = S u + internal forces
        else:
            sig, C, szz, C3, st1, dep, x = self._material(u, ezz, st, p, T1, dt, guess=guess,
                                                          condense=False)
            R = self._residual(u, sig, fext)
        rn = R.abs().amax(1) / (fref + self._fint_scale(sig))
        rn = torch.where(torch.isfinite(rn), rn, torch.full_like(rn, float("inf")))
        return sig, C, szz, C3, st1, dep, x, R, rn

    def _line_search(self, u, ezz, du, dz, rn0, x0, st, p, T1, dt, fext, fref, n_max=8,
                     inplace=False):
        """Backtracking on the residual norm, per member (a full step is taken when it helps).

        ``rn0`` ``(b,)``: the members' residual norms before the step; ``x0``: their last local
        solution (warm start). Returns ``(u, ezz, ev)`` at each member's accepted step (the
        last halving is accepted unconditionally). ``inplace``: the evaluations' arrays may be
        written in place (native path: fresh, contiguous arrays).
        """
        alpha = torch.ones_like(rn0)
        accepted = torch.zeros_like(rn0, dtype=torch.bool)
        u_new, z_new, ev_new = u, ezz, None
        for k in range(n_max):
            a = alpha[:, None]
            ut = u + a * du
            zt = ezz + a[:, :, None] * dz if dz is not None else None
            evt = self._eval(ut, zt, st, p, T1, dt, x0, fext, fref)
            good = ~accepted & ((evt[-1] < rn0) | (k == n_max - 1))
            if ev_new is None and bool(good.all()):
                return ut, zt, evt
            u_new = torch.where(good[:, None], ut, u_new)
            if dz is not None:
                z_new = torch.where(good[:, None, None], zt, z_new)
            gi = torch.nonzero(good).squeeze(1)
            ev_new = evt if ev_new is None else _put(ev_new, _take(evt, gi), gi, inplace)
            accepted = accepted | good
            if bool(accepted.all()):
                break
            alpha = torch.where(accepted, alpha, 0.5 * alpha)
            self.stats["ls"] = self.stats.get("ls", 0) + 1
        return u_new, z_new, ev_new

    def _dezz(self, du, szz, C3):
        """Newton update of eps_zz that accompanies a displacement update ``du`` (plane stress)."""
        if (isinstance(C3, Tangent3D) and self.band is None
                and _native.usable(du, szz, C3.K, C3.g2, C3.coef, C3.nb)):
            return _native.dezz(du, szz, self._edof32, self.B, (C3.K, C3.g2, C3.coef, C3.nb))
        deps = self._strain(du)  # linear in u
        if isinstance(C3, _BandTangent):  # the solder's points only
            deps, C3 = deps[:, :self.n_s], C3.solder
        rz = C3.row_zz() if isinstance(C3, Tangent3D) else C3[..., ZZ, :]
        return -(szz + (rz[..., IP] * deps).sum(-1)) / rz[..., ZZ]

    def _band_vm(self, u, th: _Thermo) -> torch.Tensor:
        """Largest von Mises stress ``(b,)`` MPa at the points of the checked elastic elements
        (:meth:`_probe_operator`); in plane strain with ``sigma_zz = nu (sigma_xx + sigma_yy)
        - E eps_th``."""
        assert self._probe is not None and self.band_spec is not None
        M_r, M_th = self._probe
        with torch.no_grad():
            sig = (u.detach() @ M_r + th.eps_lin.detach() @ M_th).reshape(u.shape[0], -1, 3)
            sx, sy, txy = sig[..., 0], sig[..., 1], sig[..., 2] * 0.5 ** 0.5
            sz = torch.zeros_like(sx)
            if self.problem.plane == "strain":
                mat = self.problem.materials[self.band_spec.material]
                eps = th.eps_lin[..., self.lin_keys.index(self.band_spec.material)]
                sz = mat.nu * (sx + sy) - mat.E * torch.as_tensor(eps).reshape(-1, 1)
            j2 = 0.5 * ((sx - sy) ** 2 + (sy - sz) ** 2 + (sz - sx) ** 2) + 3.0 * txy * txy
            return j2.sqrt().amax(1)

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
        extra: dict = {}
        # native kernels: they get torch's threads, torch's own (small) operations run on one
        native = self._native_linalg() and not (params.requires_grad
                                                and torch.is_grad_enabled())
        with _native.kernel_threads() if native else contextlib.nullcontext():
            return self._solve(params, grid, times, t_zero, progress, extra)

    def _solve(self, params, grid, times, t_zero, progress, extra) -> SolveResult:
        """:meth:`solve` after validation (``_prepare``): the time loop(s) and the outputs."""
        try:
            if self._banded is None:
                out, alive, reasons, nsub = self._run(params, grid, times, t_zero, progress)
            else:
                out, alive, reasons, nsub = self._run_split(params, grid, times, t_zero,
                                                            progress, extra)
            if self._fx is not None:
                out = self._fx.observe(out, self.x_out, self.problem.origin[0],
                                       params[:, N_ANAND:])
        finally:
            self._fcache = None  # free the factors
            self._fx = None
        return SolveResult(torch.tensor(times, **self.tkw), list(self.names), out, alive,
                           reasons, len(grid) - 1, nsub, extra)

    def _run_split(self, params, grid, times, t_zero, progress, extra):
        """:meth:`_run` with an elasto-plastic band: members whose band may yield (finite
        yield stress) on the banded discretisation, the others on this (baseline) one, so
        each member's result depends on its own parameters only. ``extra`` receives, ``(B,)``
        MPa, the largest von Mises stress over the grid steps of the band's (elastic) points
        for the baseline members (``band_elastic_vm``; a warning when it reaches the band's
        elastic limit: the off value would not be elastic) and of the elastic elements around
        the band for the banded members (``outside_band_vm``; a warning when it reaches the
        member's yield stress: the band is too shallow); NaN for the other members."""
        fx, spec, banded = self._fx, self.band_spec, self._banded
        assert fx is not None and spec is not None and banded is not None
        sy = fx.yield_stress(params[:, N_ANAND:])  # (B,)
        assert sy is not None
        plastic = torch.isfinite(sy.detach())
        nan = torch.full((len(params),), float("nan"), **self.tkw)
        parts, peak_e, peak_b = [], nan, nan.clone()
        ie, ib = torch.nonzero(~plastic).squeeze(1), torch.nonzero(plastic).squeeze(1)
        if len(ie):
            parts.append(self._run(params[ie], grid, times, t_zero, progress))
            peak_e[ie] = self._peak
            if bool((self._peak >= spec.elastic_limit).any()):
                warnings.warn(f"the elastic stress of the {spec.material} band reaches "
                              f"{self._peak.max().item():.1f} MPa >= its elastic limit "
                              f"{spec.elastic_limit:g} MPa: members at the off value would "
                              "yield; raise the limit", RuntimeWarning, stacklevel=3)
        if len(ib):
            banded._fx = fx
            try:
                parts.append(banded._run(params[ib], grid, times, t_zero, progress))
            finally:
                banded._fx, banded._fcache = None, None
            if banded._peak is not None:
                peak_b[ib] = banded._peak
                if bool((banded._peak >= sy.detach()[ib]).any()):
                    warnings.warn(f"the {spec.material} outside the plastic band reaches its "
                                  "yield stress (yielding there is not modelled): deepen the "
                                  f"band (depth {spec.depth:g} mm)", RuntimeWarning,
                                  stacklevel=3)
        extra["band_elastic_vm"], extra["outside_band_vm"] = peak_e, peak_b
        inv = torch.argsort(torch.cat([ie, ib]))
        out = torch.cat([o[0] for o in parts])[inv]
        alive = torch.cat([o[1] for o in parts])[inv]
        reasons = [r for o in parts for r in o[2]]
        return out, alive, [reasons[i] for i in inv.tolist()], sum(o[3] for o in parts)

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
        if pre is not None:  # the pre-history's grid, shared by the batch
            grid = np.concatenate([pre.grid(self.problem.stepping)[:-1], grid])
        self._fx = fx
        return params, grid, pre is not None

    def _run(self, params, grid, times, t_zero: bool, progress: bool):
        """The time loop; returns ``(V (B, n_time, n_out), alive (B,), reasons, n_substeps)``."""
        b = params.shape[0]
        cyc = self.problem.cycle
        u = torch.zeros(b, self.n_r, **self.tkw)
        kin = self._fx is not None and self._fx.kinematic
        st = initial_state((b, *self.wdet.shape), params[:, 0, None, None], kinematic=kin,
                           **self.tkw)
        if self.band is not None:  # the band's s is its equivalent plastic strain
            st.s[:, self.n_s:] = 0.0
        peak = None if self._probe is None else torch.zeros(b, **self.tkw)
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
            if peak is not None:
                peak = torch.maximum(peak, self._band_vm(u, self._thermo(t1, params)))
            if t_zero and t1 == 0.0:  # the Moire reference image: V relative to this state;
                V0 = self.observe(u, self._thermo(0.0, params))  # the cycle starts afresh
                vel, rate_prev = torch.zeros_like(u), float("nan")
                self._fcache["have"].zero_()
            if any(abs(t1 - tt) < 1e-9 for tt in times):
                v = self.observe(u, self._thermo(t1, params))
                v = v if V0 is None else v - V0
                v = torch.where(alive[:, None], v, torch.full_like(v, float("nan")))
                outs.append(v)
        self._peak = peak
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
        X2 = None if sa.X is None else (sa.X if st.X is None else st.X + k * (sa.X - st.X))
        st2 = PointState(st.eps_p + k * (sa.eps_p - st.eps_p), st.s + k * (sa.s - st.s),
                         sa.eps_zz, X2)
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


@dataclass
class _BandTangent:
    """Tangents of the solder's points (3-D, as from the Anand update) and of a band's points
    (in-plane ``(b, n_eb, n_qp, 3, 3)``, already condensed on their eps_zz)."""

    solder: Any
    band: torch.Tensor

    def index(self, idx) -> _BandTangent:
        return _BandTangent(self.solder.index(idx) if isinstance(self.solder, Tangent3D)
                            else self.solder[idx], self.band[idx])


def _split_state(st: PointState, n: int) -> tuple[PointState, PointState]:
    """The solder's (first ``n`` elements) and the band's part of a state ``(b, n_e, n_qp)``."""
    X = (None, None) if st.X is None else (st.X[:, :n], st.X[:, n:])
    return (PointState(st.eps_p[:, :n], st.s[:, :n], st.eps_zz[:, :n], X[0]),
            PointState(st.eps_p[:, n:], st.s[:, n:], st.eps_zz[:, n:], X[1]))


def _cat_state(a: PointState, b: PointState) -> PointState:
    """Inverse of :func:`_split_state` (the band keeps a zero back stress)."""
    X = None if a.X is None else torch.cat([a.X, torch.zeros_like(b.eps_p)], 1)
    return PointState(torch.cat([a.eps_p, b.eps_p], 1), torch.cat([a.s, b.s], 1),
                      torch.cat([a.eps_zz, b.eps_zz], 1), X)


def _rows(a, idx):
    """``a[idx]`` (tensor, ``PointState`` or ``Tangent3D``) for sorted, unique member indices
    ``idx``; ``a`` itself (no copy) when they are all of its members."""
    if isinstance(a, _Thermo):
        return a if not a.per_member or len(idx) == a.eps_lin.shape[0] else a.index(idx)
    if isinstance(a, PointState | Tangent3D | _BandTangent):
        n = (a.s.shape[0] if isinstance(a, PointState) else a.K.shape[0]
             if isinstance(a, Tangent3D) else a.band.shape[0])
        return a if len(idx) == n else a.index(idx)
    return a if len(idx) == a.shape[0] else a[idx]


def _take(ev, idx):
    """Members ``idx`` of a tuple of batched results."""
    return tuple(None if a is None else _rows(a, idx) for a in ev)


def _put(ev, sub, idx, inplace=False):
    """Write the members ``idx`` of a batched result tuple from ``sub`` (in place where
    ``inplace`` and the array allows it, see :func:`_scatter`)."""
    out = []
    for a, b in zip(ev, sub, strict=True):
        if a is None:
            out.append(None)
        elif isinstance(a, PointState):
            out.append(_scatter_state(a, b, idx, inplace))
        elif isinstance(a, Tangent3D):
            out.append(_scatter_tangent(a, b, idx, inplace))
        elif isinstance(a, _BandTangent):
            sol = (_scatter_tangent(a.solder, b.solder, idx, inplace)
                   if isinstance(a.solder, Tangent3D)
                   else _scatter(a.solder, b.solder, idx, inplace))
            out.append(_BandTangent(sol, _scatter(a.band, b.band, idx, inplace)))
        else:
            out.append(_scatter(a, b, idx, inplace))
    return tuple(out)


def _scatter_tangent(full: Tangent3D, part: Tangent3D, idx, inplace=False) -> Tangent3D:
    return Tangent3D(*(_scatter(getattr(full, f), getattr(part, f), idx, inplace)
                       for f in ("K", "g2", "coef", "nb")))


def _scatter(full, part, idx, inplace=False):
    """``full`` with the rows ``idx`` replaced by ``part``: a copy, or ``full`` itself written
    in place when ``inplace`` and ``full`` is a contiguous array (the caller owns it)."""
    if part.shape[0] == full.shape[0] and len(idx) == full.shape[0]:
        return part
    if inplace and full.is_contiguous() and part.dtype == full.dtype:
        return full.index_copy_(0, idx, part)
    out = full.clone()
    out[idx] = part
    return out


def _scatter_state(full: PointState, part: PointState, idx, inplace=False) -> PointState:
    X = None if full.X is None else _scatter(full.X, part.X, idx, inplace)
    return PointState(_scatter(full.eps_p, part.eps_p, idx, inplace),
                      _scatter(full.s, part.s, idx, inplace),
                      _scatter(full.eps_zz, part.eps_zz, idx, inplace), X)
