"""Time stepping of a batched solve and the recording of its outputs.

:class:`TimeLoop` runs a solver's batch through the time grid: SDIRK2 or backward-Euler steps
(:meth:`TimeLoop.time_step`, each stage one :meth:`~solderpyro.fem.solver.SpecimenSolver.step`),
recursive halving per member where a step fails or its inelastic strain increment exceeds
``dep_max`` (:meth:`TimeLoop.advance`), a displacement predictor from the previous step's rate,
V at the output times (relative to t = 0 after a pre-history), and the failure reasons. With an
elasto-plastic band, :meth:`TimeLoop.run_split` solves the members whose band may yield on the
banded discretisation and the others on the baseline one.
"""

from __future__ import annotations

import warnings
from typing import Any, NamedTuple

import torch

from solderpyro.fem.batch import scatter, scatter_state
from solderpyro.fem.thermo import N_ANAND, StepThermo
from solderpyro.materials.integrate import PointState, initial_state

SDIRK_GAMMA = 1.0 - 0.5 ** 0.5


class Members(NamedTuple):
    """The batch members a time step advances.

    Attributes:
        u: ``(b, n_r)`` retained displacements, mm; st: their Gauss-point state.
        p: ``(b, 9 + n_eff)`` Anand constants and effect parameters.
        vel: ``(b, n_r)`` displacement rate of the previous step (predictor, mm/s), or None.
        gid: ``(b,)`` their rows in the solve's factor cache, or None.
    """

    u: torch.Tensor
    st: PointState
    p: torch.Tensor
    vel: torch.Tensor | None = None
    gid: torch.Tensor | None = None

    def subset(self, idx) -> Members:
        """The members ``idx``."""
        return Members(self.u[idx], self.st.index(idx), self.p[idx],
                       None if self.vel is None else self.vel[idx],
                       None if self.gid is None else self.gid[idx])


class Outputs(NamedTuple):
    """What a time loop returns: ``V`` ``(B, n_time, n_out)`` um, ``alive`` ``(B,)``, the
    failure ``reasons`` (B strings) and the number of extra sub-steps."""

    V: torch.Tensor
    alive: torch.Tensor
    reasons: list
    n_substeps: int


class TimeLoop:
    """The time loop of a :class:`~solderpyro.fem.solver.SpecimenSolver` (``solver``: its
    ``step``, ``observe``, ``thermo``, ``newton``, ``fx``, ``probe``, discretisation sizes and
    problem are used)."""

    def __init__(self, solver: Any) -> None:
        self.solver = solver
        self.stepping = solver.problem.stepping
        self.nsub = 0

    def thermo_at(self, t: float, p: torch.Tensor) -> StepThermo:
        """The solver's inputs at time ``t`` (s) for the members ``p``."""
        return self.solver.thermo.at(t, p, self.solver.fx)

    def time_step(self, u, st, p, t0, t1, du0=None, gid=None):
        """Advance a batch from t0 to t1 with the configured scheme; see
        :meth:`SpecimenSolver.time_step <solderpyro.fem.solver.SpecimenSolver.time_step>`."""
        h = t1 - t0
        step = self.solver.step
        if self.stepping.scheme == "euler":
            return step(u, st, p, self.thermo_at(t1, p), h, du0=du0, gid=gid)
        g = SDIRK_GAMMA
        ua, sa, oka, da = step(u, st, p, self.thermo_at(t0 + g * h, p), g * h,
                               du0=None if du0 is None else g * du0, gid=gid)
        k = (1.0 - g) / g
        X2 = None if sa.X is None else (sa.X if st.X is None else st.X + k * (sa.X - st.X))
        # the second stage's Armstrong-Frederick recovery is lagged on the first stage's rate
        # (the latest one; extrapolating a rate like the state could make it negative)
        st2 = PointState(st.eps_p + k * (sa.eps_p - st.eps_p), st.s + k * (sa.s - st.s),
                         sa.eps_zz, X2, sa.p_rate)
        ub, sb, okb, db = step(ua, st2, p, self.thermo_at(t1, p), g * h, du0=k * (ua - u),
                               gid=gid)
        return ub, sb, oka & okb, torch.maximum(da, db)

    def advance(self, m: Members, t0: float, t1: float, depth: int = 0):
        """Advance the members ``m`` from t0 to t1 (s), halving the step for those that need
        it; returns ``(u1, st1, ok)``."""
        ts = self.stepping
        du0 = None if m.vel is None else m.vel * (t1 - t0)
        u1, st1, ok, dep = self.time_step(m.u, m.st, m.p, t0, t1, du0, m.gid)
        good = ok & (dep <= ts.dep_max) if depth < ts.max_depth else ok
        if bool(good.all()) or depth >= ts.max_depth:
            return u1, st1, ok
        idx = torch.nonzero(~good).squeeze(1)
        self.nsub += len(idx)
        tm = 0.5 * (t0 + t1)
        sub = m.subset(idx)
        ua, sa, oka = self.advance(sub, t0, tm, depth + 1)
        v = (ua - sub.u) / (tm - t0)
        ub, sb, okb = self.advance(Members(ua, sa, sub.p, v, sub.gid), tm, t1, depth + 1)
        okb = oka & okb
        return (scatter(u1, ub, idx), scatter_state(st1, sb, idx),
                scatter(ok, okb, idx))

    def run(self, params, grid, times, t_zero: bool, progress: bool,
            recorder: Any = None) -> Outputs:
        """The time loop over ``grid`` (s) for ``params`` ``(B, 9 + n_eff)``, V recorded at
        ``times``; ``t_zero``: V relative to t = 0 (a pre-history precedes it). The solver's
        ``peak`` receives the probe's largest stress ``(B,)`` MPa (None without a probe).
        ``recorder`` (a :class:`~solderpyro.fem.record.SolderRecorder` or None) takes the end
        of every grid step."""
        slv = self.solver
        b = params.shape[0]
        cyc = slv.problem.cycle
        u = torch.zeros(b, slv.n_r, **slv.tkw)
        kin = slv.fx is not None and slv.fx.kinematic
        rec = slv.fx is not None and slv.fx.recovery
        st = initial_state((b, *slv.wdet.shape), params[:, 0, None, None], kinematic=kin,
                           recovery=rec, **slv.tkw)
        if slv.band is not None:  # the band's s is its equivalent plastic strain
            st.s[:, slv.n_s:] = 0.0
        peak = None if slv.probe is None else torch.zeros(b, **slv.tkw)
        out = torch.full((b, len(times), len(slv.names)), float("nan"), **slv.tkw)
        alive = torch.ones(b, dtype=torch.bool, device=u.device)
        reasons = [""] * b
        self.nsub = 0
        slv.newton.fcache = slv.newton.factor_cache(b)
        vel, rate_prev = torch.zeros_like(u), float("nan")
        V0 = None
        it = range(1, len(grid))
        if progress:
            from tqdm.auto import tqdm
            it = tqdm(it, desc=f"FE cycle (B={b})", unit="step")
        outs = []
        if recorder is not None:
            recorder.start(slv, b, float(grid[0]))
        for k in it:
            t0, t1 = float(grid[k - 1]), float(grid[k])
            idx = torch.nonzero(alive).squeeze(1)
            if len(idx) == 0:
                break
            rate = (cyc(t1) - cyc(t0)) / (t1 - t0)
            v0 = vel[idx] if abs(rate - rate_prev) < 1e-12 else None
            u_a, st_a, ok = self.advance(Members(u[idx], st.index(idx), params[idx], v0, idx),
                                         t0, t1)
            vel = scatter(vel, (u_a - u[idx]) / (t1 - t0), idx)
            rate_prev = rate
            where = f"T={cyc(t1):.1f} C" if t1 > 0 else "pre-history"
            for j in torch.nonzero(~ok).squeeze(1).tolist():
                reasons[int(idx[j])] = (f"no convergence in the step to t={t1:g} s "
                                        f"({where}) after "
                                        f"{self.stepping.max_depth} halvings")
            u, st = scatter(u, u_a, idx), scatter_state(st, st_a, idx)
            alive = alive.clone()
            alive[idx] = ok
            if recorder is not None:
                recorder.step(t1, u, st, self.thermo_at(t1, params))
            if peak is not None:
                peak = torch.maximum(peak, slv.probe.peak_vm(u, self.thermo_at(t1, params)))
            if t_zero and t1 == 0.0:  # the Moire reference image: V relative to this state;
                V0 = slv.observe(u, self.thermo_at(0.0, params))  # the cycle starts afresh
                vel, rate_prev = torch.zeros_like(u), float("nan")
                slv.newton.fcache["have"].zero_()
            if any(abs(t1 - tt) < 1e-9 for tt in times):
                v = slv.observe(u, self.thermo_at(t1, params))
                v = v if V0 is None else v - V0
                v = torch.where(alive[:, None], v, torch.full_like(v, float("nan")))
                outs.append(v)
        slv.peak = peak
        for i in range(len(outs)):
            out = out.clone()
            out[:, i] = outs[i]
        return Outputs(out, alive, reasons, self.nsub)

    def run_split(self, params, grid, times, t_zero, progress, extra) -> Outputs:
        """:meth:`run` with an elasto-plastic band: members whose band may yield (finite
        yield stress) on the banded discretisation, the others on this (baseline) one, so
        each member's result depends on its own parameters only. ``extra`` receives, ``(B,)``
        MPa, the largest von Mises stress over the grid steps of the band's (elastic) points
        for the baseline members (``band_elastic_vm``; a warning when it reaches the band's
        elastic limit: the off value would not be elastic) and of the elastic elements around
        the band for the banded members (``outside_band_vm``; a warning when it reaches the
        member's yield stress: the band is too shallow); NaN for the other members."""
        slv = self.solver
        fx, spec, banded = slv.fx, slv.band_spec, slv.banded
        assert fx is not None and spec is not None and banded is not None
        sy = fx.yield_stress(params[:, N_ANAND:])  # (B,)
        assert sy is not None
        plastic = torch.isfinite(sy.detach())
        nan = torch.full((len(params),), float("nan"), **slv.tkw)
        parts, peak_e, peak_b = [], nan, nan.clone()
        ie, ib = torch.nonzero(~plastic).squeeze(1), torch.nonzero(plastic).squeeze(1)
        if len(ie):
            parts.append(self.run(params[ie], grid, times, t_zero, progress))
            peak_e[ie] = slv.peak
            if bool((slv.peak >= spec.elastic_limit).any()):
                warnings.warn(f"the elastic stress of the {spec.material} band reaches "
                              f"{slv.peak.max().item():.1f} MPa >= its elastic limit "
                              f"{spec.elastic_limit:g} MPa: members at the off value would "
                              "yield; raise the limit", RuntimeWarning, stacklevel=3)
        if len(ib):
            banded.fx = fx
            try:
                parts.append(TimeLoop(banded).run(params[ib], grid, times, t_zero, progress))
            finally:
                banded.fx, banded.newton.fcache = None, None
            if banded.peak is not None:
                peak_b[ib] = banded.peak
                if bool((banded.peak >= sy.detach()[ib]).any()):
                    warnings.warn(f"the {spec.material} outside the plastic band reaches its "
                                  "yield stress (yielding there is not modelled): deepen the "
                                  f"band (depth {spec.depth:g} mm)", RuntimeWarning,
                                  stacklevel=3)
        extra["band_elastic_vm"], extra["outside_band_vm"] = peak_e, peak_b
        inv = torch.argsort(torch.cat([ie, ib]))
        out = torch.cat([o.V for o in parts])[inv]
        alive = torch.cat([o.alive for o in parts])[inv]
        reasons = [r for o in parts for r in o.reasons]
        return Outputs(out, alive, [reasons[i] for i in inv.tolist()],
                       sum(o.n_substeps for o in parts))
