"""The material evaluation at the Gauss points of the nonlinear elements of a solve.

:class:`PointEvaluator` turns retained displacements and the out-of-plane strain into the
solder's (and an elasto-plastic band's) stresses, consistent tangents and new state: strains
from the B-matrices, the solder law's update (:meth:`~solderpyro.fem.problem.AnandSolder.update`)
or, on the CPU in float64 without autograd, one fused native call that also gives the internal
forces (:func:`solderpyro._native.solder_eval`), the plane-stress condensation on eps_zz, and
the band's J2 update (:func:`~solderpyro.fem.band.band_update`). The solder's elements come
first in the element arrays, a band's after them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from solderpyro import _native
from solderpyro.fem.band import BandData, band_update
from solderpyro.fem.problem import AnandSolder, SolderStep
from solderpyro.fem.thermo import N_ANAND, MemberStep
from solderpyro.materials.elastic import IP, ZZ, condense_zz
from solderpyro.materials.integrate import (
    PointInputs,
    PointState,
    Tangent3D,
    full_strain,
    lagged_prager,
)


@dataclass
class BandTangent:
    """Tangents of the solder's points (3-D, as from the Anand update) and of a band's points
    (in-plane ``(b, n_eb, n_qp, 3, 3)``, already condensed on their eps_zz)."""

    solder: Any
    band: torch.Tensor

    def index(self, idx) -> BandTangent:
        """The tangents of the members ``idx``."""
        return BandTangent(self.solder.index(idx) if isinstance(self.solder, Tangent3D)
                           else self.solder[idx], self.band[idx])


def col_zz(C3):
    """``C3[..., :, ZZ]`` of a 3-D tangent (tensor or :class:`Tangent3D`)."""
    return C3.col_zz() if isinstance(C3, Tangent3D) else C3[..., :, ZZ]


def split_state(st: PointState, n: int) -> tuple[PointState, PointState]:
    """The solder's (first ``n`` elements) and the band's part of a state ``(b, n_e, n_qp)``."""
    X = (None, None) if st.X is None else (st.X[:, :n], st.X[:, n:])
    r = (None, None) if st.p_rate is None else (st.p_rate[:, :n], st.p_rate[:, n:])
    return (PointState(st.eps_p[:, :n], st.s[:, :n], st.eps_zz[:, :n], X[0], r[0]),
            PointState(st.eps_p[:, n:], st.s[:, n:], st.eps_zz[:, n:], X[1], r[1]))


def cat_state(a: PointState, b: PointState) -> PointState:
    """Inverse of :func:`split_state` (the band keeps a zero back stress and lagged rate)."""
    X = None if a.X is None else torch.cat([a.X, torch.zeros_like(b.eps_p)], 1)
    r = None if a.p_rate is None else torch.cat([a.p_rate, torch.zeros_like(b.s)], 1)
    return PointState(torch.cat([a.eps_p, b.eps_p], 1), torch.cat([a.s, b.s], 1),
                      torch.cat([a.eps_zz, b.eps_zz], 1), X, r)


class PointEvaluator:
    """Stresses, tangents and state at the Gauss points of the nonlinear elements.

    Args:
        problem: the :class:`~solderpyro.fem.problem.Problem` (plane, T_ref_C).
        solder: its solder law.
        layer: the elements' operators (:class:`solderpyro._native.SolderLayer`: int32 dofs,
            ``B``, ``Bw`` ``(n_e, n_qp, 3, 8)``, the border of ``S``, plane stress).
        edof: ``(n_e, 8)`` retained dof of each element dof (int64).
        n_s: the number of solder elements (first in the element arrays).
        band: the band's :class:`~solderpyro.fem.band.BandData`, or None (no band).
        tkw: torch dtype and device.
    """

    def __init__(self, problem, solder, layer: _native.SolderLayer, edof: torch.Tensor,
                 n_s: int, band: BandData | None, tkw: dict) -> None:
        self.problem, self.solder, self.layer = problem, solder, layer
        self.edof, self.n_s, self.band, self.tkw = edof, n_s, band, tkw
        self.B = layer.B
        self.Be = self.B.reshape(self.B.shape[0], -1, 8)  # (n_e, n_qp*3, 8)

    def strain(self, u):
        """In-plane strains ``(b, n_e, n_qp, 3)``: one small matrix product per element, with
        the batch as the columns (much cheaper than one 3x8 product per point)."""
        b = u.shape[0]
        ue = u[:, self.edof].permute(1, 2, 0)  # (n_e, 8, b)
        return torch.bmm(self.Be, ue).permute(2, 0, 1).reshape(b, *self.B.shape[:3])

    def _solder_step(self, step: MemberStep, **kw) -> SolderStep:
        """The solder law's :class:`~solderpyro.fem.problem.SolderStep` of ``step``."""
        return SolderStep(step.th.T, self.problem.T_ref_C, step.dt, C_k=step.th.C_k,
                          gamma_k=step.th.gamma_k, **kw)

    def material(self, u, ezz, st, step: MemberStep, guess=None, tangent=True, C3_fixed=None,
                 condense=True):
        """Solder update at all Gauss points for displacements ``u`` ``(b, n_r)`` (mm) and
        out-of-plane strain ``ezz`` ``(b, n_s, n_qp)`` (None: zero), from the start-of-step
        state ``st``, for the members' ``step``.

        Returns ``(sigma_ip, C_ip, sigma_zz, C3, new_state, dep, x)``: in plane stress the
        in-plane stress and tangent are condensed on eps_zz (the residual of sigma_zz = 0 is
        eliminated with the Newton update of eps_zz, so the global iteration drives it to zero).
        ``C3_fixed``: use this 3-D tangent instead of the update's. With ``condense=False`` the
        in-plane tangent ``C_ip`` is not formed (None); the Newton loop condenses ``C3`` only
        for the members it refactors (:meth:`condense`). With a band the arrays cover the
        band's points too (:meth:`_material_band`).
        """
        if self.band is not None:
            return self._material_band(u, ezz, st, step, guess, tangent, C3_fixed, condense)
        if tangent and not condense and C3_fixed is None:
            fused = self.material_fused(u, ezz, st, step, guess)
            if fused is not None:
                return fused[:-1]
        eps = self.strain(u)
        if ezz is None:
            ezz = torch.zeros_like(eps[..., 0])
        th = step.th
        ss = (self._solder_step(step, eps_th=th.eps_th, E=th.E) if th.per_member
              else self._solder_step(step))
        sig, st1, C3, dep, x = self.solder.update(
            full_strain(eps, ezz), st, step.p[:, None, None, :N_ANAND], ss, guess=guess,
            tangent="factored" if tangent else False)
        sig_ip, szz = sig[..., IP], sig[..., ZZ]
        C3 = C3 if C3_fixed is None else C3_fixed
        C = None
        if self.problem.plane == "stress":
            cz = col_zz(C3)
            cz = cz[..., IP] / cz[..., ZZ, None]
            sig_ip = sig_ip - cz * szz[..., None]
        if tangent and condense:
            C = self.condense(C3)
        return sig_ip, C, szz, C3, st1, dep, x

    def material_fused(self, u, ezz, st, step: MemberStep, guess):
        """:meth:`material` (with the factored tangent, not condensed) and the internal forces
        ``(b, n_r)`` appended, in one native call (:func:`solderpyro._native.solder_eval`); None
        where that path does not apply (another device or dtype, autograd, a band, or a solder
        law that overrides :meth:`~solderpyro.fem.problem.AnandSolder.update`)."""
        sol = self.solder
        if (self.band is not None or type(sol).update is not AnandSolder.update
                or self.tkw["device"].type != "cpu"
                or not _native.usable(u, ezz, st.eps_p, st.s, st.X, st.p_rate, step.p,
                                      guess)):
            return None
        th = step.th
        if not _native.usable(*(a for a in (th.T, th.eps_th, th.E, th.C_k, th.gamma_k))):
            return None
        T0 = self.problem.T_ref_C  # what AnandSolder.update passes to return_map_3d
        eps_th = th.eps_th if th.per_member else sol.thermal_strain(th.T, T0)
        E = th.E if th.per_member else sol.modulus(th.T)
        C_k = th.C_k
        if C_k is not None and not isinstance(C_k, torch.Tensor) and C_k == 0:
            C_k = None
        inputs = PointInputs(th.T + 273.15, step.dt, eps_th, E, sol.nu, C_k, th.gamma_k)
        st, inputs, carry = lagged_prager(st, inputs)  # Armstrong-Frederick: (a X_n, a C_k)
        sig_ip, szz, eps_p, s, X, dep, x, tg, f = _native.solder_eval(
            u, ezz if self.layer.plane_stress else None, self.layer, st,
            step.p[:, None, None, :N_ANAND], inputs, guess)
        ezz_out = ezz.clone() if ezz is not None else torch.zeros_like(szz)
        st1 = PointState(eps_p, s, ezz_out, X, dep / step.dt if carry else None)
        return sig_ip, None, szz, Tangent3D(*tg), st1, dep, x, f

    def _material_band(self, u, ezz, st, step: MemberStep, guess, tangent, C3_fixed, condense):
        """:meth:`material` with an elasto-plastic band: the solder's points as there (``ezz``,
        ``szz`` are the solder's), then the band's (:func:`~.band.band_update`, which solves
        its own ``eps_zz`` and modes). ``C3`` is a :class:`BandTangent`; ``sigma_ip``,
        ``dep``, the state and ``x`` cover all points (solder elements first)."""
        assert self.band is not None
        n = self.n_s
        eps = self.strain(u)
        if ezz is None:
            ezz = torch.zeros_like(eps[:, :n, :, 0])
        th = step.th
        st_s, st_b = split_state(st, n)
        sig, st1, C3, dep, x = self.solder.update(
            full_strain(eps[:, :n], ezz), st_s, step.p[:, None, None, :N_ANAND],
            self._solder_step(step, eps_th=th.eps_th, E=th.E),
            guess=None if guess is None else guess[:, :n],
            tangent="factored" if tangent else False)
        sig_ip, szz = sig[..., IP], sig[..., ZZ]
        C3 = C3 if C3_fixed is None else C3_fixed.solder
        if self.problem.plane == "stress":
            cz = col_zz(C3)
            sig_ip = sig_ip - cz[..., IP] / cz[..., ZZ, None] * szz[..., None]
        eps_th_b, sigma_y_b = th.band
        sb, Cb, st1b, dgb, xb = band_update(self.band, eps[:, n:], st_b, eps_th_b, sigma_y_b,
                                            None if guess is None else guess[:, n:], tangent)
        C3m = BandTangent(C3, Cb) if tangent else None
        C = self.condense(C3m) if tangent and condense else None
        return (torch.cat([sig_ip, sb], 1), C, szz, C3m, cat_state(st1, st1b),
                torch.cat([dep, dgb], 1), torch.cat([x, xb], 1))

    def condense(self, C3):
        """In-plane tangent ``(..., 3, 3)`` from the 3-D one (plane stress or strain)."""
        if isinstance(C3, BandTangent):
            return torch.cat([self.condense(C3.solder), C3.band], 1)
        return condense_zz(C3.full() if isinstance(C3, Tangent3D) else C3, self.problem.plane)

    def dezz(self, du, szz, C3):
        """Newton update of eps_zz ``(b, n_s, n_qp)`` that accompanies a displacement update
        ``du`` ``(b, n_r)`` (plane stress), from ``sigma_zz`` ``szz`` (MPa) and the 3-D
        tangent ``C3``."""
        if (isinstance(C3, Tangent3D) and self.band is None
                and _native.usable(du, szz, C3.K, C3.g2, C3.coef, C3.nb)):
            return _native.dezz(du, szz, self.layer.edof, self.B, (C3.K, C3.g2, C3.coef, C3.nb))
        deps = self.strain(du)  # linear in u
        if isinstance(C3, BandTangent):  # the solder's points only
            deps, C3 = deps[:, :self.n_s], C3.solder
        rz = C3.row_zz() if isinstance(C3, Tangent3D) else C3[..., ZZ, :]
        return -(szz + (rz[..., IP] * deps).sum(-1)) / rz[..., ZZ]
