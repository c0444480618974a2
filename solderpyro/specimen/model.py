"""The specimen's forward model: parameter rows -> the FE's outputs, as one ``torch.nn.Module``.

>>> import torch
>>> from solderpyro import SpecimenModel
>>> model = SpecimenModel()                       # reference case, seed times, points A and B
>>> theta = torch.tensor([[12.9, 10586.0, 2.04, 0.2]], dtype=torch.float64)  # s0, QR, xi, m
>>> V = model(theta)                              # (1, 4, 2): (B, n_time, n_out) in um

With physical effects (:mod:`solderpyro.effects`) their parameters follow the Anand ones:

>>> model = SpecimenModel(effects=("thermal_lag",))
>>> model.param_names
['s0', 'QR', 'xi', 'm', 'tau']

Effects on the FE side (material laws, initial state, temperature) enter the solver;
observation-side ones (``moire_rigid_motion``: the seam :data:`~.observed.OBSERVATION_SEAM`)
act on the FE's outputs after it, so rows that differ only in those share one FE run.

Two ways to evaluate it:

* ``model(theta)`` / :meth:`SpecimenModel.run` / :meth:`SpecimenModel.observed`: a direct
  solve, differentiable with respect to ``theta`` (implicit-function gradients through the
  solver).
* :meth:`SpecimenModel.runs` and the other ``*_runs`` methods: no gradient, each distinct row
  solved once; with a run store attached (:meth:`SpecimenModel.use_store`) every batch is stored
  as soon as it finishes (:func:`~solderpyro.compute.store.run_doe`, through the current executor)
  and stored runs are read back. :attr:`SpecimenModel.tally` counts the runs.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from solderpyro.compute.runstore import RunStore, param_hash
from solderpyro.compute.store import DoeOptions, run_doe
from solderpyro.effects import Effect, EffectSet
from solderpyro.fem.loading import SEED_TIMES
from solderpyro.fem.problem import Problem, reference_grid
from solderpyro.fem.solver import SolveResult, SpecimenSolver
from solderpyro.params import ANAND_NAMES, LIU2008, Box, ParameterSpace, check_anand_values
from solderpyro.specimen.observed import OBSERVATION_SEAM, observation_offset

if TYPE_CHECKING:
    from solderpyro.config.compose import Setup

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StoreUse:
    """How a :class:`SpecimenModel` runs through a run store.

    Attributes:
        store: the run store. batch: most members per batched FE solve (each batch is stored
            as soon as it finishes). progress: a tqdm bar over the batches.
        even_batches: split the rows not yet stored into equal batches of at most ``batch``
            (66 rows: two of 33, not 64 and 2).
    """

    store: RunStore
    batch: int = 64
    progress: bool = False
    even_batches: bool = False

    def __post_init__(self) -> None:
        if self.batch < 1:
            raise ValueError(f"StoreUse.batch must be >= 1, got {self.batch}")


@dataclass
class RunTally:
    """FE runs a model was asked for (counted by its ``*_runs`` methods).

    Attributes:
        n_rows: parameter rows asked for. n_ok / n_failed: of those, converged / not.
        n_reused: rows read from the store as it was before the call (direct: duplicates).
        n_computed: distinct parameter sets solved.
    """

    n_rows: int = 0
    n_ok: int = 0
    n_failed: int = 0
    n_reused: int = 0
    n_computed: int = 0

    def add(self, other: RunTally) -> None:
        """Count ``other``'s runs here too (e.g. a refined model's, made for this one)."""
        self.n_rows += other.n_rows
        self.n_ok += other.n_ok
        self.n_failed += other.n_failed
        self.n_reused += other.n_reused
        self.n_computed += other.n_computed


@dataclass
class ModelRuns:
    """Outputs of :meth:`SpecimenModel.runs` (and :meth:`SpecimenModel.fe_runs`), row for row.

    Attributes:
        V: ``(n, n_time, n_out)`` um, float64 on the CPU; NaN rows where a member failed.
        ok: ``(n,)`` bool. reasons: ``n`` strings (empty where converged).
        times: ``(n_time,)`` s, sorted. names: ``n_out`` output labels.
        n_computed: distinct parameter sets solved by this call; n_reused: rows read from the
            store as it was before the call (direct: duplicates of a row of the call).
    """

    V: torch.Tensor
    ok: torch.Tensor
    reasons: list[str]
    times: tuple[float, ...]
    names: tuple[str, ...]
    n_computed: int = 0
    n_reused: int = 0


class _SolverOnDemand:
    """The model's solver, set up on its first use (not at all when every run is stored);
    pickles as that solver (an executor's workers build their own)."""

    def __init__(self, model: SpecimenModel) -> None:
        self.model = model

    @property
    def tkw(self) -> dict[str, Any]:
        return self.model.solver.tkw

    @property
    def names(self) -> list[str]:
        return self.model.output_names

    def param_names(self, times: Any = None) -> list[str]:
        return self.model.solver_param_names

    def solve(self, params: torch.Tensor, times: Any, progress: bool = False) -> SolveResult:
        return self.model.solver.solve(params, times, progress=progress)

    def __reduce__(self) -> tuple:
        return self.model.solver.__reduce__()


class SpecimenModel(torch.nn.Module):
    """``theta (B, n_theta) -> V (B, n_time, n_out)`` in um, batched; and, given an
    observation index, ``theta -> (B, n_obs)``.

    ``theta`` holds the constants of ``space`` (physical units), then the effects'
    parameters in the order of ``effects``. The uncalibrated Anand constants (``space``'s
    defaults), the effects' column indices, the outputs' abscissae and the observation index
    are buffers: the module moves with ``.to(device, dtype)`` (the solver follows: one is set
    up per device and dtype, on first use).

    Args:
        problem: the FE problem (default: the reference case, docs/configuration.md).
        space: which Anand constants ``theta`` holds (default: s0, QR, xi, m with Liu's others).
        times: output times, s (sorted here; default: the seed's four points (a)-(d)).
        field: also report V on the reference case's 31 x 18 grid (after A, B).
        dtype, device: of the solve (float64 recommended; ``"cuda"`` works).
        observation: optional map ``V (B, n_time, n_out) -> V'`` applied to the outputs of
            :meth:`forward` (after the effects).
        effects: physical effects switched on: names of :data:`solderpyro.effects.EFFECTS`,
            :class:`~solderpyro.effects.Effect` instances (e.g. with a box override), or an
            :class:`~solderpyro.effects.EffectSet`. Their prior box is :attr:`effect_box`.
    """

    anand_defaults: torch.Tensor  # (9,) the Anand constants for the uncalibrated columns
    x_out: torch.Tensor  # (n_out,) mm, the outputs' abscissae
    anand_cols: torch.Tensor  # (space.n_theta,) long: their columns among ANAND_NAMES
    fe_cols: torch.Tensor  # (n_fe,) long: theta's FE-side columns
    obs_cols: torch.Tensor  # (n_theta - n_fe,) long: theta's observation-side columns
    obs_time: torch.Tensor  # (n_obs,) long: each observation's time index
    obs_out: torch.Tensor  # (n_obs,) long: each observation's output index

    def __init__(self, problem: Problem | None = None, space: ParameterSpace | None = None,
                 times: Sequence[float] = SEED_TIMES, field: bool = False,
                 dtype: torch.dtype = torch.float64, device: Any = "cpu",
                 observation: Any = None,
                 effects: EffectSet | Sequence[str | Effect] = ()) -> None:
        super().__init__()
        self.problem = problem or Problem()
        self.space = space or ParameterSpace.seed()
        self.times = tuple(sorted(float(t) for t in times))
        self.field = bool(field)
        fx = effects if isinstance(effects, EffectSet) else EffectSet(effects)
        self.effects: EffectSet = fx.bind(self.times)
        fe_e = [e for e in self.effects.effects if e.seam != OBSERVATION_SEAM]
        obs_e = [e for e in self.effects.effects if e.seam == OBSERVATION_SEAM]
        self.fx_fe: EffectSet | None = EffectSet(fe_e) if fe_e else None
        self.fx_obs: EffectSet | None = EffectSet(obs_e) if obs_e else None
        self.observation = observation
        k = self.space.n_theta
        fe_cols, obs_cols, j = list(range(k)), list[int](), k
        for e in self.effects.effects:
            (obs_cols if e.seam == OBSERVATION_SEAM else fe_cols).extend(range(j, j + e.n_params))
            j += e.n_params
        grid = reference_grid()
        self.output_names = [*self.problem.points, *(grid[0] if self.field else ())]
        pts = [tuple(map(float, p)) for p in self.problem.points.values()]
        if self.field:
            pts += [(float(x), float(y)) for x, y in grid[1]]
        defaults = getattr(self.space, "defaults", LIU2008)
        # float buffers keep a float64 master: a trip through float32 and back is exact
        self._masters: dict[str, torch.Tensor] = {
            "anand_defaults": torch.tensor([float(defaults[n]) for n in ANAND_NAMES],
                                           dtype=torch.float64),
            "x_out": torch.tensor([p[0] for p in pts], dtype=torch.float64)}
        for name, t in self._masters.items():
            self.register_buffer(name, t.clone())
        self.register_buffer("anand_cols", torch.tensor(
            [ANAND_NAMES.index(n) for n in self.space.names], dtype=torch.long))
        self.register_buffer("fe_cols", torch.tensor(fe_cols, dtype=torch.long))
        self.register_buffer("obs_cols", torch.tensor(obs_cols, dtype=torch.long))
        self.register_buffer("obs_time", torch.zeros(0, dtype=torch.long))
        self.register_buffer("obs_out", torch.zeros(0, dtype=torch.long))
        self._solvers: dict[tuple[torch.dtype, str], SpecimenSolver] = {}
        self._hashes: dict[torch.dtype, str] = {}
        self._offset: Any = None
        self.store_use: StoreUse | None = None
        self.tally = RunTally()
        self.last: SolveResult | None = None
        self.to(device=device, dtype=dtype)

    # ------------------------------------------------------------------ module plumbing
    def _apply(self, fn: Any, recurse: bool = True) -> SpecimenModel:
        """Move/cast the buffers (``nn.Module.to``); float buffers are re-cast from their
        float64 masters, so a round trip through a lower precision loses nothing."""
        super()._apply(fn, recurse)
        for name, master in self._masters.items():
            now = self._buffers[name]
            assert now is not None
            self._buffers[name] = master.to(device=now.device, dtype=now.dtype)
        return self

    @property
    def dtype(self) -> torch.dtype:
        """The module's floating dtype (of its buffers and its solver)."""
        return self.anand_defaults.dtype

    @property
    def device(self) -> torch.device:
        """The module's device (of its buffers and its solver)."""
        return self.anand_defaults.device

    @property
    def solver(self) -> SpecimenSolver:
        """The :class:`~solderpyro.fem.solver.SpecimenSolver` for the module's current device
        and dtype (FE-side effects only), set up on first use."""
        key = (self.dtype, str(self.device))
        if key not in self._solvers:
            self._solvers[key] = SpecimenSolver(
                self.problem, reference_grid() if self.field else None, dtype=self.dtype,
                device=self.device, effects=self.fx_fe or ())
        return self._solvers[key]

    # ------------------------------------------------------------------ names and boxes
    @property
    def param_names(self) -> list[str]:
        """Names of the ``theta`` columns: ``space.names`` then the effects' parameters."""
        return [*self.space.names, *self.effects.names]

    @property
    def n_theta(self) -> int:
        """Columns of ``theta``: ``space.n_theta`` plus the effects' parameters."""
        return self.space.n_theta + self.effects.n_params

    @property
    def n_fe(self) -> int:
        """Columns of the FE-side rows :meth:`fe_runs` takes: ``space.n_theta`` plus the
        FE-side effects' parameters."""
        return int(self.fe_cols.numel())

    @property
    def solver_param_names(self) -> list[str]:
        """Names of the solver's rows: the nine Anand constants, then the FE-side effects'
        parameters (what the run store keys a run by)."""
        return [*ANAND_NAMES, *(self.fx_fe.names if self.fx_fe is not None else ())]

    @property
    def effect_box(self) -> Box:
        """Prior box of the effects' parameters (bound to :attr:`times`)."""
        return self.effects.box

    @property
    def n_out(self) -> int:
        """Number of outputs per time (A, B, then the grid's 558 with ``field``)."""
        return len(self.output_names)

    @property
    def output_points(self) -> torch.Tensor:
        """``(n_out, 2)`` coordinates (mm) of the outputs."""
        pts = [self.problem.points[n] for n in self.problem.points]
        if self.field:
            pts += [tuple(p) for p in reference_grid()[1]]
        return torch.tensor(pts, dtype=torch.float64)

    # ------------------------------------------------------------------ the direct solve
    def solver_rows(self, theta_fe: torch.Tensor) -> torch.Tensor:
        """FE-side rows ``(B, n_fe)`` -> solver rows ``(B, 9 + n_fe_eff)``: the nine Anand
        constants (the space's defaults for those not calibrated), then the FE-side effects'
        parameters. Differentiable with respect to ``theta_fe``."""
        k = self.space.n_theta
        P = self.anand_defaults.to(theta_fe).expand(theta_fe.shape[0], -1).clone()
        P[:, self.anand_cols] = theta_fe[:, :k]
        return torch.cat([P, theta_fe[:, k:]], 1)

    def run(self, theta: torch.Tensor, progress: bool = False) -> SolveResult:
        """Solve for ``theta`` ``(B, n_theta)`` (physical units: the calibrated Anand
        constants, then the effects' parameters); returns the full result, its ``V``
        ``(B, n_time, n_out)`` um with the observation-side effects applied. Differentiable."""
        theta = torch.as_tensor(theta, dtype=self.dtype, device=self.device)
        if theta.ndim == 1:
            theta = theta[None]
        self.check(theta)
        res = self.solver.solve(self.solver_rows(theta[:, self.fe_cols]), self.times,
                                progress=progress)
        for i, why in enumerate(res.reasons):
            if why:
                log.warning("batch member %d (theta=%s) failed: %s", i, theta[i].tolist(), why)
        if self.fx_obs is not None:
            res.V = self.fx_obs.observe(res.V, self.x_out, float(self.problem.origin[0]),
                                        theta[:, self.obs_cols])
        self.last = res
        return res

    def forward(self, theta: torch.Tensor) -> torch.Tensor:
        """``(B, n_theta) -> (B, n_time, n_out)`` in um; NaN rows for failed members."""
        V = self.run(theta).V
        return V if self.observation is None else self.observation(V)

    def check(self, theta: torch.Tensor) -> None:
        """Validate ``theta`` ``(B, n_theta)``: shape, finite, each Anand constant's extremes,
        each effect's own rules. Raises ``ValueError`` naming the parameter."""
        if theta.ndim != 2 or theta.shape[-1] != self.n_theta:
            raise ValueError(f"theta must have shape (B, {self.n_theta}) for "
                             f"{', '.join(self.param_names)}; got {tuple(theta.shape)}")
        if not torch.isfinite(theta).all():
            raise ValueError("theta contains NaN or inf")
        for j, nm in enumerate(self.space.names):  # the extremes of each column decide
            check_anand_values({nm: theta[:, j].min().item()})
            check_anand_values({nm: theta[:, j].max().item()})
        self.effects.check(theta[:, self.space.n_theta:])

    # ------------------------------------------------------------------ the observation index
    def set_observations(self, time_index: Any, output_index: Any) -> SpecimenModel:
        """Which outputs are observed: ``(n_obs,)`` indices into :attr:`times` and into the
        outputs (:func:`~.observed.observation_index` of the measurements). Returns self."""
        ti = torch.as_tensor(np.asarray(time_index), dtype=torch.long).reshape(-1)
        oi = torch.as_tensor(np.asarray(output_index), dtype=torch.long).reshape(-1)
        if ti.shape != oi.shape:
            raise ValueError(f"observation index: {ti.numel()} time indices for {oi.numel()} "
                             "output indices")
        if ti.numel() and (int(ti.min()) < 0 or int(ti.max()) >= len(self.times)
                           or int(oi.min()) < 0 or int(oi.max()) >= self.n_out):
            raise ValueError(f"observation index outside (n_time, n_out) = "
                             f"({len(self.times)}, {self.n_out})")
        self.obs_time = ti.to(self.device)
        self.obs_out = oi.to(self.device)
        self._offset = None
        return self

    @property
    def index(self) -> tuple[np.ndarray, np.ndarray]:
        """``(time index (n_obs,), output index (n_obs,))`` of each observed value."""
        return self.obs_time.cpu().numpy(), self.obs_out.cpu().numpy()

    def _need_index(self) -> None:
        if self.obs_time.numel() == 0:
            raise ValueError("SpecimenModel: no observation index; call set_observations")

    def observed(self, theta: torch.Tensor) -> torch.Tensor:
        """``(B, n_theta) -> (B, n_obs)`` um at the observation index; differentiable."""
        self._need_index()
        return self.forward(theta)[:, self.obs_time, self.obs_out]

    def offset(self, q: torch.Tensor) -> torch.Tensor:
        """What the observation-side effects add at each observation, um: ``q (n_q,) ->
        (n_obs,)`` or ``(B, n_q) -> (B, n_obs)`` (zero columns without such effects)."""
        self._need_index()
        if self.fx_obs is None:
            return torch.zeros(*q.shape[:-1], int(self.obs_time.numel()), dtype=q.dtype)
        if self._offset is None:
            ti, oi = self.index
            self._offset = observation_offset(self.fx_obs, self.problem,
                                              tuple(self.output_names), len(self.times), ti, oi)
        return self._offset(q)

    # ------------------------------------------------------------------ runs (store or direct)
    def use_store(self, use: StoreUse | None) -> SpecimenModel:
        """Run the ``*_runs`` methods through ``use.store`` (None: solve directly). Returns
        self."""
        self.store_use = use
        self._hashes = {}
        return self

    @property
    def cfg_hash(self) -> str | None:
        """The run store's hash of this configuration (problem, times, field, dtype,
        FE-side effects; registered on first use), or None without a store."""
        if self.store_use is None:
            return None
        if self.dtype not in self._hashes:
            self._hashes[self.dtype] = self.store_use.store.register(
                self.problem, self.times, self.field, self.dtype, effects=self.fx_fe or ())
        return self._hashes[self.dtype]

    def solve_rows(self, P: torch.Tensor, progress: bool | None = None) -> ModelRuns:
        """The FE at solver rows ``P (n, 9 + n_fe_eff)`` (:meth:`solver_rows`), no gradient:
        through the store when one is attached, else each distinct row solved once; counted
        in :attr:`tally`. Observation-side effects not applied."""
        P = torch.as_tensor(P).detach().to(device="cpu", dtype=torch.float64)
        use = self.store_use
        res: Any
        if use is None:
            uniq, inv = torch.unique(P, dim=0, return_inverse=True)
            sol = self.solver.solve(uniq, self.times, progress=bool(progress))
            res = ModelRuns(sol.V.detach()[inv], sol.ok[inv],
                            [sol.reasons[i] for i in inv.tolist()], self.times,
                            tuple(sol.names), len(uniq), len(P) - len(uniq))
        else:
            h = self.cfg_hash
            assert h is not None
            batch = self._even_batch(h, P) if use.even_batches else use.batch
            opts = DoeOptions(batch, use.progress if progress is None else progress)
            doe = run_doe(_SolverOnDemand(self), use.store, h, P, self.times,
                          self.solver_param_names, opts)
            res = ModelRuns(doe.V, doe.ok, list(doe.reasons), tuple(doe.times),
                            tuple(doe.names), int(doe.n_computed), int(doe.n_reused))
        res.V = res.V.detach().cpu().to(torch.float64)
        res.ok = torch.as_tensor(res.ok).cpu().bool()
        res.V[~res.ok] = float("nan")
        res.reasons = [str(r) for r in res.reasons]
        t = self.tally
        t.n_rows += len(P)
        t.n_ok += int(res.ok.sum())
        t.n_failed += int((~res.ok).sum())
        t.n_reused += res.n_reused
        t.n_computed += res.n_computed
        return res

    def _even_batch(self, h: str, P: torch.Tensor) -> int:
        """Members per solve: the rows not yet stored split into equal batches of at most
        ``store_use.batch``."""
        assert self.store_use is not None
        store, b = self.store_use.store, self.store_use.batch
        first = {param_hash(r): i for i, r in enumerate(P)}
        n = sum(not store.path(h, P[i]).exists() for i in first.values())
        return max(1, math.ceil(n / max(1, math.ceil(n / b))))

    def fe_runs(self, theta_fe: torch.Tensor, progress: bool | None = None) -> ModelRuns:
        """The FE at FE-side rows ``theta_fe (n, n_fe)`` (the space's constants, then the
        FE-side effects' parameters, physical units), no gradient (:meth:`solve_rows`)."""
        th = torch.as_tensor(theta_fe).detach().to(device="cpu", dtype=torch.float64)
        if th.ndim != 2 or th.shape[1] != self.n_fe:
            names = [self.param_names[int(j)] for j in self.fe_cols]
            raise ValueError(f"FE-side rows must have shape (n, {self.n_fe}) for "
                             f"{', '.join(names)}; got {tuple(th.shape)}")
        return self.solve_rows(self.solver_rows(th), progress)

    def runs(self, theta: torch.Tensor, progress: bool | None = None) -> ModelRuns:
        """:meth:`fe_runs` at full rows ``theta (n, n_theta)`` with the observation-side
        effects applied to ``V`` after the FE (rows differing only in those share a run)."""
        th = torch.as_tensor(theta).detach().to(device="cpu", dtype=torch.float64)
        if th.ndim != 2 or th.shape[1] != self.n_theta:
            raise ValueError(f"theta must have shape (n, {self.n_theta}) for "
                             f"{', '.join(self.param_names)}; got {tuple(th.shape)}")
        res = self.fe_runs(th[:, self.fe_cols.cpu()], progress)
        if self.fx_obs is not None:
            res.V = self.fx_obs.observe(res.V, self.x_out.cpu().to(torch.float64),
                                        float(self.problem.origin[0]),
                                        th[:, self.obs_cols.cpu()])
        return res

    def fe_observed_runs(self, theta_fe: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The FE's observed outputs at FE-side rows ``theta_fe (m, n_fe)``: ``V (m, n_obs)``
        um, float64 (NaN rows where it did not converge), and ``ok (m,)``; observation-side
        effects not applied (what a surrogate of the FE learns)."""
        self._need_index()
        res = self.fe_runs(theta_fe)
        ti, oi = self.obs_time.cpu(), self.obs_out.cpu()
        return res.V[:, ti, oi].clone(), res.ok.clone()

    def observed_runs(self, theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``V (m, n_obs)`` um: the FE plus the observation-side offsets (:meth:`offset`) at
        full rows ``theta (m, n_theta)``; NaN rows where the FE did not converge; and
        ``ok (m,)``."""
        th = torch.as_tensor(theta).detach().to(device="cpu", dtype=torch.float64)
        if th.ndim != 2 or th.shape[1] != self.n_theta:
            raise ValueError(f"theta must have shape (n, {self.n_theta}) for "
                             f"{', '.join(self.param_names)}; got {tuple(th.shape)}")
        V, ok = self.fe_observed_runs(th[:, self.fe_cols.cpu()])
        if self.fx_obs is not None:
            with torch.no_grad():
                V = V + self.offset(th[:, self.obs_cols.cpu()])
        return V, ok


def _settings_key(fx: EffectSet | None) -> str:
    return json.dumps(fx.settings(), sort_keys=True, default=str) if fx is not None else ""


#: effect groups of fewer rows than this are pooled into one solve (:meth:`SpecimenModels.runs`,
#: ``keep``): 40 field rows of the reference case, five with each candidate on and five with
#: none, took 58.1 CPU s as eight solves against 52.8 s as one solve with every candidate on
#: (one thread): at a few rows a solve's cost per time step outweighs the candidates' own
POOL_ROWS = 16


@dataclass
class SpecimenModels:
    """The :class:`SpecimenModel` of each configuration (output times, field grid or not,
    effects switched on) of one setup, made on first use and kept; all share one run store
    (None: solved directly) and count their runs.

    Attributes:
        setup: the :class:`~solderpyro.config.compose.Setup` (problem, calibrated space, dtype,
            device). store: the run store or None. batch_size: members per batched FE solve
            (the rows not yet stored split into equal batches of at most this many).
    """

    setup: Setup
    store: RunStore | None = None
    batch_size: int = 64
    models: dict[tuple, SpecimenModel] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.batch_size < 1:
            raise ValueError(f"SpecimenModels: batch_size must be >= 1, got {self.batch_size}")

    def get(self, times: Sequence[float], field: bool, effects: EffectSet | None = None
            ) -> SpecimenModel:
        """The model over ``setup.space`` then ``effects``' parameters at ``times`` (s), with
        the 31 x 18 grid when ``field``."""
        fx = effects.bind(times) if effects is not None and len(effects) else None
        key = (tuple(sorted(float(t) for t in times)), bool(field), _settings_key(fx))
        if key not in self.models:
            s = self.setup
            m = SpecimenModel(s.problem, s.space, times, field, dtype=s.dtype,
                              device=s.device, effects=fx or ())
            if self.store is not None:
                m.use_store(StoreUse(self.store, self.batch_size, even_batches=True))
            self.models[key] = m
        return self.models[key]

    def runs(self, theta: torch.Tensor, times: Sequence[float], field: bool,
             effects: EffectSet | None = None, progress: bool = False,
             keep: int | None = None) -> ModelRuns:
        """:meth:`SpecimenModel.runs` of that configuration's model at ``theta
        (n, space.n_theta + n_eff)``.

        Args:
            keep: None: every row is solved with all of ``effects``. An int: the first
                ``keep`` effects always, each later one only in the rows where its parameters
                are not all at their "off" values (:attr:`~solderpyro.effects.Effect.off`, the
                baseline, where an effect changes nothing): the rows are grouped by the effects
                they switch on and each group is solved by its own model. A candidate's
                machinery costs even at "off" (every candidate of the diagnosis together
                doubled the CPU time of a batch of the reference case), so a set of many
                candidates, most of them off in any row, is solved this way. Groups of fewer
                than :data:`POOL_ROWS` rows are solved as one, with every effect any of them
                switches on: a solve's cost has a part per time step that does not grow with
                its rows, which the rows of a small group do not pay for.
        """
        if keep is None or effects is None or len(effects) <= keep:
            return self.get(times, field, effects).runs(theta, progress)
        return self._pruned(theta, times, field, effects, keep, progress)

    def _pruned(self, theta: torch.Tensor, times: Sequence[float], field: bool,
                effects: EffectSet, keep: int, progress: bool) -> ModelRuns:
        """:meth:`runs` with the effects after the first ``keep`` solved only where on."""
        n_a = theta.shape[1] - effects.n_params
        blocks = effects.split(theta[:, n_a:])  # (n, n_p) per effect
        on = np.ones((len(theta), len(effects)), bool)
        for k, e in enumerate(effects.effects[keep:], keep):
            off = torch.as_tensor(e.off, dtype=theta.dtype, device=theta.device)
            on[:, k] = (blocks[k] != off).any(1).cpu().numpy()
        groups: dict[tuple[bool, ...], list[int]] = {}
        for i, row in enumerate(map(tuple, on)):
            groups.setdefault(row, []).append(i)
        small = [g for g, idx in groups.items() if len(idx) < POOL_ROWS]
        if len(small) > 1:  # solved together, with every effect any of them switches on
            pool = tuple(bool(v) for v in np.any(np.array(small), axis=0))
            pooled = [i for g in small for i in groups.pop(g)]
            groups[pool] = sorted(groups.get(pool, []) + pooled)
        parts: dict[tuple[bool, ...], ModelRuns] = {}
        for g, idx in groups.items():
            sub = [k for k in range(len(effects)) if g[k]]
            fx = EffectSet([effects.effects[k] for k in sub]) if sub else None
            ix = torch.as_tensor(idx)
            rows = torch.cat([theta[ix, :n_a], *[blocks[k][ix] for k in sub]], 1)
            parts[g] = self.get(times, field, fx).runs(rows, progress)
        first = next(iter(parts.values()))
        V = torch.full((len(theta), *first.V.shape[1:]), float("nan"), dtype=first.V.dtype)
        ok = torch.zeros(len(theta), dtype=torch.bool)
        reasons = [""] * len(theta)
        for g, idx in groups.items():
            r, ix = parts[g], torch.as_tensor(idx)
            if r.times != first.times or r.names != first.names:
                raise RuntimeError("SpecimenModels.runs: the effect groups' outputs differ "
                                   f"({r.names[:3]}... at {r.times} against {first.times})")
            V[ix], ok[ix] = r.V, r.ok
            for j, i in enumerate(idx):
                reasons[i] = r.reasons[j]
        return ModelRuns(V, ok, reasons, first.times, first.names,
                         sum(r.n_computed for r in parts.values()),
                         sum(r.n_reused for r in parts.values()))

    @property
    def computed(self) -> int:
        """Parameter sets solved so far, over every configuration."""
        return sum(m.tally.n_computed for m in self.models.values())

    @property
    def reused(self) -> int:
        """Rows served without a solve (read from the store, or duplicates of a row of the
        same call), over every configuration."""
        return sum(m.tally.n_rows - m.tally.n_computed for m in self.models.values())
