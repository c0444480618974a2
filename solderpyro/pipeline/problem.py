"""Stage 1, the problem: what the calibration observes and how it runs the FE.

:class:`SpecimenModel` gathers, once, everything the later stages share: the switched-on
effects, the FE solver and run store, the boxes (the FE's parameters, and those plus the
observation-side effects), which model outputs the measurements are, the noise prior, and the
FE itself as ``theta -> observed outputs`` through the run store (every run stored as its batch
finishes, and reused by any later call, by this calibration or another).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from solderpyro.calibration import Priors
from solderpyro.configure import Setup
from solderpyro.effects import EffectSet
from solderpyro.fem.problem import reference_grid
from solderpyro.fem.solver import SpecimenSolver
from solderpyro.io.measurements import Measurements
from solderpyro.params import LIU2008, Box, anand_tensor
from solderpyro.specimen import (
    calibration_box,
    fe_params,
    observation_index,
    observation_offset,
    split_effects,
)
from solderpyro.store import RunStore, run_doe

log = logging.getLogger("solderpyro")


@dataclass
class FeTally:
    """FE runs the calibration asked for: converged / failed, reused from the store /
    computed (for the report)."""

    n_ok: int = 0
    n_failed: int = 0
    n_reused: int = 0
    n_computed: int = 0

    def add(self, other: FeTally) -> None:
        """Count ``other``'s runs here too (e.g. a refined problem's, made for this
        calibration)."""
        self.n_ok += other.n_ok
        self.n_failed += other.n_failed
        self.n_reused += other.n_reused
        self.n_computed += other.n_computed


@dataclass
class SpecimenModel:
    """The specimen calibration's problem (built by :meth:`build`).

    Attributes:
        setup, meas: the typed problem and the measurements.
        times: ``(n_time,)`` measured times, s. full_field: full-field data (grid labels).
        fx, fx_fe, fx_obs: switched-on effects (all, FE-side, observation-side), or None.
        gp_box: what the FE runs vary (Anand constants, then FE-side effects' parameters).
        space: ``gp_box`` plus observation-side parameters: what the posterior is over.
        y: ``(n_obs,)`` measured values, um. priors: the noise prior (stated sigma if the file
            gives one for every row).
        solver, store, cfg_hash, batch, progress: how FE runs are made and kept.
        correction: after :meth:`correct`, ``{"delta": (n_obs,) um, "y_measured": (n_obs,),
            ...}`` and what the caller recorded (``"at"``: ``name -> value`` where it was
            taken): the FE's estimated discretization error taken off ``y`` (None before).
    """

    setup: Setup
    meas: Measurements
    times: tuple[float, ...]
    full_field: bool
    fx: EffectSet | None
    fx_fe: EffectSet | None
    fx_obs: EffectSet | None
    gp_box: Box
    space: Box
    y: torch.Tensor
    priors: Priors
    solver: SpecimenSolver
    store: RunStore
    cfg_hash: str
    batch: int = 64
    progress: bool = True
    tally: FeTally = field(default_factory=FeTally)
    _index: tuple[np.ndarray, np.ndarray] | None = None
    _names: tuple[str, ...] | None = None
    _offset: Any = None
    correction: dict[str, Any] | None = None

    @classmethod
    def build(cls, setup: Setup, meas: Measurements, store_root: str, batch: int = 64,
              progress: bool = True) -> SpecimenModel:
        """The problem of calibrating ``setup.space`` (plus switched-on effects) to ``meas``."""
        if len(meas) == 0:
            raise ValueError("the measurement file has no rows")
        field_ = any(p not in setup.problem.points for p in meas.points())
        times = tuple(float(t) for t in meas.times())
        fx, fx_fe, fx_obs = split_effects(setup, times)
        solver = SpecimenSolver(setup.problem, reference_grid() if field_ else None,
                                dtype=setup.dtype, device=setup.device, effects=fx_fe or ())
        store = RunStore(store_root)
        h = store.register(setup.problem, times, field_, setup.dtype, effects=fx_fe or ())
        y = torch.tensor(np.array(meas.value_um), dtype=torch.float64)
        sig = meas.sigma_um[np.isfinite(meas.sigma_um)]
        if sig.size == len(meas) and sig.size:  # the file states the noise: use it
            pr = Priors(sigma_known=float(np.median(sig)))
            log.info("noise: sigma_um from the data (%.3g um), known to ~10 %%", pr.sigma_known)
        else:
            yr = float(y.max() - y.min())
            pr = Priors(sigma_max=max(10 * float(sig.max()) if sig.size else 0.0, 0.5 * yr,
                                      1e-3))
        if fx is not None:
            log.info("effects on: %s (parameters %s)", ", ".join(fx.keys), ", ".join(fx.names))
        return cls(setup, meas, times, field_, fx, fx_fe, fx_obs, calibration_box(setup, fx_fe),
                   calibration_box(setup, fx), y, pr, solver, store, h, batch, progress)

    @property
    def n_fe(self) -> int:
        """Number of FE-side parameters (``gp_box.dim``)."""
        return self.gp_box.dim

    @property
    def effects(self) -> tuple[str, ...]:
        return self.fx.keys if self.fx is not None else ()

    def _solve(self, P: torch.Tensor) -> Any:
        res = run_doe(self.solver, self.store, self.cfg_hash, P, self.times, self.batch,
                      self.progress)
        t = self.tally
        t.n_ok += int(res.ok.sum())
        t.n_failed += int((~res.ok).sum())
        t.n_reused += int(res.n_reused)
        t.n_computed += int(res.n_computed)
        if self._index is None:
            self._index = observation_index(self.meas, res.times, res.names)
            self._names = tuple(res.names)
        return res

    def fe(self, theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The FE's observed outputs at FE parameters ``theta (m, n_fe)`` (physical units):
        ``V (m, n_obs)`` um (NaN rows where it did not converge) and ``ok (m,)``; through the
        run store (observation-side effects not applied: these are what the surrogate
        learns)."""
        res = self._solve(fe_params(self.setup, theta.to(torch.float64)))
        ti, oi = self.index
        V = res.V[:, ti, oi].to(torch.float64).clone()
        V[~res.ok] = float("nan")
        return V, res.ok.clone()

    @property
    def index(self) -> tuple[np.ndarray, np.ndarray]:
        """``(time index (n_obs,), output index (n_obs,))`` of each measured value."""
        if self._index is None:
            self.literature()
        assert self._index is not None
        return self._index

    def literature(self) -> torch.Tensor:
        """``(n_obs,)`` the FE with the Liu 2008 constants and every effect off, um."""
        liu = anand_tensor({}, base=LIU2008, dtype=torch.float64)[None]
        if self.fx_fe is not None:
            liu = torch.cat([liu, torch.tensor([self.fx_fe.off], dtype=torch.float64)], 1)
        res = self._solve(liu)
        ti, oi = self.index
        return res.V[0, ti, oi].to(torch.float64)

    def offset(self) -> Any:
        """``q (n_q,) -> (n_obs,)``: what observation-side effects add (None without them)."""
        if self.fx_obs is None:
            return None
        if self._offset is None:
            ti, oi = self.index
            assert self._names is not None
            self._offset = observation_offset(self.fx_obs, self.setup.problem, self._names,
                                              len(self.times), ti, oi)
        return self._offset

    def offsets(self, rows: torch.Tensor) -> torch.Tensor | None:
        """``(N, n_obs)`` observation-side additions at full parameter rows ``(N, space.dim)``
        (None without observation-side effects)."""
        off = self.offset()
        if off is None:
            return None
        with torch.no_grad():
            return off(rows.to(torch.float64)[:, self.n_fe:])

    def correct(self, delta: np.ndarray, **info: Any) -> None:
        """Take the FE's estimated discretization error off the observations:
        ``y <- y_measured - delta``, which is the likelihood of the corrected model
        ``FE(theta) + delta`` with the FE's own outputs (the store, the surrogate) untouched.

        Args:
            delta: ``(n_obs,)`` um, e.g. :func:`~.fe_check.discretization_error` at a point of
                the posterior (measured: on the reference case's field data it is nearly the
                same all along the posterior's ridge, docs/calibration.md).
            info: recorded with it (``at``: where it was taken, ...).
        Raises:
            ValueError: a wrong length or a non-finite value (a failed FE run).
        """
        d = np.asarray(delta, float).reshape(-1)
        if d.shape != (int(self.y.numel()),) or not np.all(np.isfinite(d)):
            raise ValueError(f"correct: delta must be {int(self.y.numel())} finite values, got "
                             f"shape {d.shape}")
        raw = self.y if self.correction is None else self.correction["y_measured"]
        self.y = raw - torch.as_tensor(d, dtype=raw.dtype)
        self.correction = {"delta": d, "y_measured": raw, **info}

    def observed(self, rows: np.ndarray) -> np.ndarray:
        """``(b, n_obs)`` um: the FE plus observation-side effects at full parameter rows
        ``(b, space.dim)``; NaN rows where the FE did not converge. (What the FE check,
        the FE-exact posterior and the profiles evaluate.)"""
        th = torch.as_tensor(np.asarray(rows), dtype=torch.float64).reshape(-1, self.space.dim)
        V, _ = self.fe(th[:, :self.n_fe])
        off = self.offsets(th)
        return (V if off is None else V + off).numpy()
