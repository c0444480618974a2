"""Batched, implicit FE solver of the layered specimen with Anand solder.

One solve advances ``B`` parameter sets together. The mesh, the elastic bars and their
condensation (:mod:`solderpyro.fem.assembly`) are shared by the whole batch; per member only the
solder layer is nonlinear, and its retained system is solved with a batched dense Cholesky.

:class:`SpecimenSolver` sets up the discretisation and composes the parts of a solve, one
module each: the step's temperature-dependent inputs (:mod:`solderpyro.fem.thermo`), the
material evaluation at the Gauss points (:mod:`solderpyro.fem.points`), the Newton iteration of
a step with its line search (:mod:`solderpyro.fem.newton`), and the time stepping with the
output recording (:mod:`solderpyro.fem.stepping`); the fixed operators are set up by
:mod:`solderpyro.fem.operators`.

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
effect. A back stress adds ``X`` to the Gauss-point state, and its Armstrong-Frederick
recovery the last step's inelastic strain rate ``p_rate``. A plastic band
(:mod:`solderpyro.fem.band`) needs a second discretisation whose retained system includes the
band: it is built once, and each member is solved on it only if its band may yield, else on the
baseline one. Without effects the solver runs the baseline path unchanged.

Native path (CPU, float64, no autograd; :mod:`solderpyro._native`): one C call per Newton
evaluation does the strains, the Anand update, the plane-stress condensation and the internal
forces (:meth:`~solderpyro.fem.points.PointEvaluator.material_fused`), and the retained tangent
is assembled, factored and solved in its bordered-band form (:mod:`solderpyro.fem.bordered`)
instead of dense; the algorithm and its decisions are the same, results agree to rounding
(~1e-13 um). Everything else (other devices, autograd's correction step,
``SOLDERPYRO_NATIVE=0``, no compiler) runs the torch code.
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import torch

from solderpyro import _native
from solderpyro.effects import Effect, EffectSet
from solderpyro.effects.base import PlasticBand
from solderpyro.fem.assembly import condense, linear_system
from solderpyro.fem.band import adjacent_elements
from solderpyro.fem.bordered import BorderedBand
from solderpyro.fem.elements import bbar, edofs, q4_kinematics
from solderpyro.fem.loading import time_grid
from solderpyro.fem.mesh import build_mesh
from solderpyro.fem.newton import NewtonStep, RetainedOperators
from solderpyro.fem.operators import (
    BandProbe,
    band_data,
    band_element_indices,
    dirichlet,
    observation,
)
from solderpyro.fem.points import PointEvaluator
from solderpyro.fem.problem import Problem
from solderpyro.fem.record import SolderRecorder
from solderpyro.fem.stepping import SDIRK_GAMMA, TimeLoop
from solderpyro.fem.thermo import N_ANAND, MemberStep, ThermoFields
from solderpyro.materials.integrate import PointState
from solderpyro.params import ANAND_NAMES

__all__ = ["SDIRK_GAMMA", "SolveResult", "SpecimenSolver"]


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
            banded discretisation (:attr:`banded`); each member is solved on the banded one
            only if its band may yield (:meth:`~solderpyro.effects.Effect.yield_stress`
            finite), else on the baseline one.
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
        #: the effects bound to the running solve's times (None outside a solve)
        self.fx: EffectSet | None = None
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
        el_b = (np.zeros(0, dtype=int) if spec is None
                else band_element_indices(mesh, problem.materials, spec, nonlin))
        el_all = el_nl  # the nonlinear elements: the solder, then a band's
        if _band is not None:
            el_lin = np.setdiff1d(el_lin, el_b)
            el_all = np.concatenate([el_nl, el_b])
        fixed, self.node_O = dirichlet(mesh, problem.origin)
        n_dof = 2 * mesh.n_node
        free = np.setdiff1d(np.arange(n_dof), fixed)
        r = np.intersect1d(free, np.unique(edofs(mesh.elems[el_all])))
        self.n_r = len(r)
        # observation operator: V(P) - V(O)
        names, pts = list(problem.points), np.array(list(problem.points.values()), float)
        if field_points is not None:
            names += list(field_points[0])
            pts = np.concatenate([pts, np.asarray(field_points[1], float)])
        self.names = names
        self.x_out = torch.as_tensor(pts[:, 0].copy(), **self.tkw)  # (n_out,) mm
        K, loads = linear_system(mesh, problem, el_lin)
        # elastic elements whose stress is checked: the band itself on the baseline path, the
        # ring of elastic elements around it on the banded one
        el_p = el_b if _band is None else adjacent_elements(mesh, el_b, _band.material)
        probe = None
        if spec is not None and len(el_p):
            ed_p = edofs(mesh.elems[el_p]).ravel()
            probe = sp.csr_matrix((np.ones(len(ed_p)), (np.arange(len(ed_p)), ed_p)),
                                  shape=(len(ed_p), n_dof))
        cond = condense(K, loads, observation(mesh, pts, problem.mesh.half, self.node_O), r,
                        np.setdiff1d(free, r), probe)
        t = lambda a: torch.as_tensor(np.ascontiguousarray(a), **self.tkw)  # noqa: E731
        self.S = t(cond.S)
        self.lin_keys = list(cond.g)
        self.G = torch.stack([t(cond.g[k]) for k in cond.g])  # (n_mat, n_r)
        self.Hobs = t(cond.H)  # (n_out, n_r)
        self.hobs = torch.stack([t(cond.h[k]) for k in cond.h])  # (n_mat, n_out)
        self.n_s = len(el_nl)  # solder elements come first in the element arrays
        self.el_solder = el_nl
        wdet = self._set_up_elements(r, el_all, cond, _band)
        self.band = (None if _band is None
                     else band_data(mesh, problem, _band, el_b, wdet[self.n_s:], self.tkw))
        self.band_spec = spec
        #: the elastic-stress check of the band (baseline) or around it (banded), or None
        self.probe = (None if probe is None or spec is None
                      else BandProbe(mesh, problem, spec, el_p, cond, self.lin_keys, self.tkw))
        self.peak: torch.Tensor | None = None  # the last run's checked stresses, (b,) MPa
        self._compose(cond)
        #: the banded discretisation of a plastic band (None without one)
        self.banded: SpecimenSolver | None = None
        if spec is not None and _band is None:
            self.banded = SpecimenSolver(problem, field_points, dtype, device,
                                         self.effects or (), _band=spec)

    def _set_up_elements(self, r: np.ndarray, el_all: np.ndarray, cond, band) -> np.ndarray:
        """Element data of the nonlinear elements on the retained dofs ``r``: a fixed dof
        points at dof 0 with a zero B-matrix column, so it contributes nothing to strains,
        forces or tangents. Returns their ``w det J`` ``(n_e, n_qp)`` (mm^2)."""
        mesh, n_s = self.mesh, self.n_s
        gmap = np.full(2 * mesh.n_node, -1)
        gmap[r] = np.arange(self.n_r)
        ed = gmap[edofs(mesh.elems[el_all])]
        B, wdet = q4_kinematics(mesh.nodes[mesh.elems[el_all]])
        if self.problem.plane == "strain":  # the solder's only: a band keeps B (and its modes)
            B = bbar(B, wdet) if band is None else np.concatenate(
                [bbar(B[:n_s], wdet[:n_s]), B[n_s:]])
        B = B * (ed >= 0)[:, None, None, :]
        t = lambda a: torch.as_tensor(np.ascontiguousarray(a), **self.tkw)  # noqa: E731
        self.edof = torch.as_tensor(np.maximum(ed, 0), device=self.tkw["device"])
        self.B, self.wdet = t(B), t(wdet)  # (n_e, n_qp, 3, 8), (n_e, n_qp)
        self.Bw = self.B * self.wdet[..., None, None]
        n_e = self.B.shape[0]
        self.BweT = self.Bw.reshape(n_e, -1, 8).transpose(1, 2).contiguous()  # (n_e, 8, n_qp*3)
        self.kidx = (self.edof[:, :, None] * self.n_r + self.edof[:, None, :]).reshape(-1)
        # native bordered-band factorization (CPU float64; the dense torch path otherwise)
        self.bb: BorderedBand | None = None
        dof_D = np.nonzero(np.abs(cond.S).max(1) > 0)[0]  # where S is nonzero (the border)
        self.layer = _native.SolderLayer(
            torch.as_tensor(np.maximum(ed, 0).astype(np.int32)), self.B, self.Bw,
            (torch.as_tensor(dof_D.astype(np.int32)), self.S[dof_D][:, dof_D].cpu().contiguous()),
            self.problem.plane == "stress")
        if self.tkw["device"].type == "cpu" and self.tkw["dtype"] == torch.float64:
            bb = BorderedBand(cond.S, ed, self.B, self.Bw)
            self.bb = bb if bb.worthwhile() else None
        return wdet

    def _compose(self, cond) -> None:
        """The parts of a solve: the step's inputs, the Gauss-point evaluation and the Newton
        step."""
        self.thermo = ThermoFields(self.problem, self.solder, self.lin_keys,
                                   None if self.band is None else self.band.material, self.tkw)
        self.points = PointEvaluator(self.problem, self.solder, self.layer, self.edof, self.n_s,
                                     self.band, self.tkw)
        ops = RetainedOperators(self.S, self.G, self.B, self.Bw, self.BweT, self.edof,
                                self.kidx, self.n_s, self.band, self.bb)
        self.newton = NewtonStep(self.points, ops, self.problem, self.tkw)
        self.stats = self.newton.stats

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

    # ------------------------------------------------------------------ one step
    def f_ext(self, T_C) -> torch.Tensor:
        """Condensed thermal force ``(n_r,)`` N/mm of the elastic regions at temperature T
        (degC)."""
        return self.thermo.eps_th_lin(T_C) @ self.G

    def step(self, u, st: PointState, p, T1, dt, du0=None, gid=None):
        """One backward-Euler step for a batch.

        Args:
            u: ``(b, n_r)`` start-of-step retained displacements, mm.
            st: start-of-step Gauss-point state, leading shape ``(b, n_e, n_qp)``.
            p: ``(b, 9 + n_eff)`` Anand constants (then effect parameters); T1: end-of-step
                temperature, degC (float), or the inputs
                (:class:`~solderpyro.fem.thermo.StepThermo`); dt: step, s.
            du0: optional ``(b, n_r)`` predicted displacement increment (Newton's start).
            gid: optional ``(b,)`` indices of these members in the batch of the running solve;
                their factors are reused across steps (modified Newton).
        Returns:
            ``(u1, st1, ok (b,), dep_max (b,))``.
        """
        return self.newton.step(u, st, MemberStep(p, self.thermo.as_thermo(T1), dt), du0, gid)

    def time_step(self, u, st, p, t0, t1, du0=None, gid=None):
        """Advance a batch from t0 to t1 with the configured scheme; see :meth:`step`.

        SDIRK2 (gamma = 1 - 1/sqrt2): stage 1 is backward Euler to t0 + gamma*h; stage 2 is
        backward Euler over gamma*h to t1 from the start state extrapolated with the stage-1
        rates, ``y* = y0 + (1-gamma)/gamma * (y1 - y0)`` (internal variables only). The method is
        L-stable and stiffly accurate, so it keeps backward Euler's robustness for fast
        relaxation while its error falls as h^2.
        """
        return TimeLoop(self).time_step(u, st, p, t0, t1, du0, gid)

    def observe(self, u, T_C):
        """V relative to O at the output points, ``(b, n_out)`` in um.

        Args:
            u: ``(b, n_r)`` retained displacements, mm.
            T_C: temperature, degC (float), or the inputs
                (:class:`~solderpyro.fem.thermo.StepThermo`, per member).
        """
        off = self.thermo.as_thermo(T_C).eps_lin @ self.hobs  # (n_out,) or (b, n_out)
        return 1e3 * (u @ self.Hobs.T + off)

    # ------------------------------------------------------------------ time loop
    def solve(self, params: torch.Tensor, times, progress: bool = False,
              recorder: SolderRecorder | None = None) -> SolveResult:
        """Run the thermal cycle for a batch of Anand parameter sets (and effect parameters).

        Args:
            params: ``(B, 9 + n_eff)``: the Anand constants in ANAND_NAMES order (MPa, K, 1/s),
                then the effects' parameters in the order of :meth:`param_names` ``(times)``
                (``n_eff = 0`` without effects); may require grad, in which case the outputs
                are differentiable with respect to every column.
            times: output times, s (each in ``(0, cycle end]``).
            progress: show a tqdm bar over the time steps.
            recorder: gathers the solder's stress, inelastic strain and work at every grid
                step (:mod:`solderpyro.fem.record`); its fields are ``extra["solder"]``.
        Returns:
            :class:`SolveResult` with ``V`` of shape ``(B, n_time, n_out)`` in um. With an
            effect that simulates a pre-history, V is relative to the state at t = 0.
        Raises:
            ValueError: a ``recorder`` with an elasto-plastic copper band (its members are
                solved on two discretisations).
        """
        times = sorted(float(t) for t in times)
        params, grid, t_zero = self._prepare(params, times)
        extra: dict = {}
        # native kernels: they get torch's threads, torch's own (small) operations run on one
        native = self.newton.native_linalg() and not (params.requires_grad
                                                      and torch.is_grad_enabled())
        with _native.kernel_threads() if native else contextlib.nullcontext():
            return self._solve(params, grid, times, t_zero, progress, extra, recorder)

    def _solve(self, params, grid, times, t_zero, progress, extra,
               recorder: SolderRecorder | None = None) -> SolveResult:
        """:meth:`solve` after validation (``_prepare``): the time loop(s) and the outputs."""
        try:
            loop = TimeLoop(self)
            if self.banded is None:
                res = loop.run(params, grid, times, t_zero, progress, recorder)
                if recorder is not None:
                    extra["solder"] = recorder.finish(res.alive)
            elif recorder is not None:
                raise ValueError("recorder: the solder's fields are not recorded with an "
                                 "elasto-plastic copper band (copper_plasticity): solve "
                                 "without it")
            else:
                res = loop.run_split(params, grid, times, t_zero, progress, extra)
            out = res.V
            if self.fx is not None:
                out = self.fx.observe(out, self.x_out, self.problem.origin[0],
                                      params[:, N_ANAND:])
        finally:
            self.newton.fcache = None  # free the factors
            self.fx = None
        return SolveResult(torch.tensor(times, **self.tkw), list(self.names), out, res.alive,
                           res.reasons, len(grid) - 1, res.n_substeps, extra)

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
        self.fx = fx
        return params, grid, pre is not None

