"""Stage 1, the problem: what the calibration observes and how it runs the FE.

:class:`CalibrationProblem` gathers, once, everything the later stages share: the switched-on
effects, the forward model (:class:`~solderpyro.specimen.SpecimenModel` through the run store:
every run stored as its batch finishes, and reused by any later call, by this calibration or
another), the boxes (the FE's parameters, and those plus the observation-side effects), the
data (:class:`ObservedData`) and the noise prior.

The data flow one way: the problem is built on the measured data; the discretization
correction (:func:`~.adaptive.correct_discretization`) returns corrected data, and
:meth:`CalibrationProblem.with_data` the problem every later stage uses with them.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from solderpyro.calibration import Priors
from solderpyro.compute.runstore import RunStore
from solderpyro.config.compose import Setup
from solderpyro.effects import EffectSet
from solderpyro.io.measurements import Measurements
from solderpyro.params import LIU2008, Box, anand_tensor
from solderpyro.specimen import (
    RunTally,
    SpecimenModel,
    StoreUse,
    calibration_box,
    observation_index,
    split_effects,
)

log = logging.getLogger("solderpyro")


@dataclass(frozen=True, eq=False)
class ObservedData:
    """The data a calibration fits.

    Attributes:
        y: ``(n_obs,)`` um, what the likelihood sees: the measured values, or those minus the
            FE's estimated discretization error ``delta``.
        y_measured: ``(n_obs,)`` um, as measured.
        delta: ``(n_obs,)`` um taken off (None: not corrected).
        info: what the correction recorded (``at``: ``name -> value`` where it was taken,
            ``chi2``, ``sigma``); empty when not corrected.
    """

    y: torch.Tensor
    y_measured: torch.Tensor
    delta: np.ndarray | None = None
    info: Mapping[str, Any] = field(default_factory=dict)

    @classmethod
    def measured(cls, y: Any) -> ObservedData:
        """The measured values ``y (n_obs,)`` um, uncorrected."""
        t = torch.as_tensor(y, dtype=torch.float64).reshape(-1)
        return cls(t, t)

    def corrected(self, delta: Any, **info: Any) -> ObservedData:
        """The data with the FE's estimated discretization error taken off the measured
        values: ``y = y_measured - delta``, which is the likelihood of the corrected model
        ``FE(theta) + delta`` with the FE's own outputs (the store, the surrogate) untouched.

        Args:
            delta: ``(n_obs,)`` um, e.g. :func:`~.fe_check.discretization_error` at a point
                of the posterior. info: recorded with it (``at``: where it was taken, ...).
        Raises:
            ValueError: a wrong length or a non-finite value (a failed FE run).
        """
        d = np.asarray(delta, float).reshape(-1)
        n = int(self.y_measured.numel())
        if d.shape != (n,) or not np.all(np.isfinite(d)):
            raise ValueError(f"correct: delta must be {n} finite values, got shape {d.shape}")
        y = self.y_measured - torch.as_tensor(d, dtype=self.y_measured.dtype)
        return ObservedData(y, self.y_measured, d, dict(info))

    @property
    def is_corrected(self) -> bool:
        """Whether a discretization correction was taken off."""
        return self.delta is not None


@dataclass(frozen=True, eq=False)
class CalibrationProblem:
    """The specimen calibration's problem (built by :meth:`build`).

    Attributes:
        setup, meas: the typed problem and the measurements.
        times: ``(n_time,)`` measured times, s. full_field: full-field data (grid labels).
        fx, fx_fe, fx_obs: switched-on effects (all, FE-side, observation-side), or None.
        gp_box: what the FE runs vary (Anand constants, then FE-side effects' parameters).
        space: ``gp_box`` plus observation-side parameters: what the posterior is over.
        data: the data (:class:`ObservedData`); :attr:`y` is ``data.y``.
        priors: the noise prior (stated sigma if the file gives one for every row).
        model: the forward model over ``space`` at the measured times, with the measurements'
            observation index, through the run store.
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
    data: ObservedData
    priors: Priors
    model: SpecimenModel

    @classmethod
    def build(cls, setup: Setup, meas: Measurements, store_root: str, batch: int = 64,
              progress: bool = True) -> CalibrationProblem:
        """The problem of calibrating ``setup.space`` (plus switched-on effects) to ``meas``."""
        if len(meas) == 0:
            raise ValueError("the measurement file has no rows")
        field_ = any(p not in setup.problem.points for p in meas.points())
        times = tuple(float(t) for t in meas.times())
        fx, fx_fe, fx_obs = split_effects(setup, times)
        model = SpecimenModel(setup.problem, setup.space, times, field_, dtype=setup.dtype,
                              device=setup.device, effects=fx or ())
        model.use_store(StoreUse(RunStore(store_root), batch, progress))
        model.set_observations(*observation_index(meas, model.times,
                                                  tuple(model.output_names)))
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
                   calibration_box(setup, fx), ObservedData.measured(y), pr, model)

    def with_data(self, data: ObservedData) -> CalibrationProblem:
        """This problem with other data (the same model, store and run tally)."""
        return dataclasses.replace(self, data=data)

    @property
    def y(self) -> torch.Tensor:
        """``(n_obs,)`` um: the data the likelihood sees (``data.y``)."""
        return self.data.y

    @property
    def n_fe(self) -> int:
        """Number of FE-side parameters (``gp_box.dim``)."""
        return self.gp_box.dim

    @property
    def effects(self) -> tuple[str, ...]:
        """Names of the switched-on effects."""
        return self.fx.keys if self.fx is not None else ()

    @property
    def tally(self) -> RunTally:
        """Every FE run of the calibration so far (the model's)."""
        return self.model.tally

    @property
    def store(self) -> RunStore:
        """The run store."""
        assert self.model.store_use is not None
        return self.model.store_use.store

    @property
    def batch(self) -> int:
        """Members per batched FE solve."""
        assert self.model.store_use is not None
        return self.model.store_use.batch

    @property
    def index(self) -> tuple[np.ndarray, np.ndarray]:
        """``(time index (n_obs,), output index (n_obs,))`` of each measured value."""
        return self.model.index

    def fe(self, theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The FE's observed outputs at FE parameters ``theta (m, n_fe)`` (physical units):
        ``V (m, n_obs)`` um (NaN rows where it did not converge) and ``ok (m,)``; through the
        run store (observation-side effects not applied: these are what the surrogate
        learns)."""
        return self.model.fe_observed_runs(theta)

    def literature(self) -> torch.Tensor:
        """``(n_obs,)`` the FE with the Liu 2008 constants and every effect off, um."""
        liu = anand_tensor({}, base=LIU2008, dtype=torch.float64)[None]
        if self.fx_fe is not None:
            liu = torch.cat([liu, torch.tensor([self.fx_fe.off], dtype=torch.float64)], 1)
        res = self.model.solve_rows(liu)
        ti, oi = self.index
        return res.V[0, ti, oi].to(torch.float64)

    def offset(self) -> Any:
        """``q (n_q,) -> (n_obs,)``: what observation-side effects add (None without them)."""
        return None if self.fx_obs is None else self.model.offset

    def offsets(self, rows: torch.Tensor) -> torch.Tensor | None:
        """``(N, n_obs)`` observation-side additions at full parameter rows ``(N, space.dim)``
        (None without observation-side effects)."""
        if self.fx_obs is None:
            return None
        with torch.no_grad():
            return self.model.offset(rows.to(torch.float64)[:, self.n_fe:])

    def observed(self, rows: np.ndarray) -> np.ndarray:
        """``(b, n_obs)`` um: the FE plus observation-side effects at full parameter rows
        ``(b, space.dim)``; NaN rows where the FE did not converge. (What the FE check,
        the FE-exact posterior and the profiles evaluate.)"""
        th = torch.as_tensor(np.asarray(rows), dtype=torch.float64).reshape(-1, self.space.dim)
        return self.model.observed_runs(th)[0].numpy()
