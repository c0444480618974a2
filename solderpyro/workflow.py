"""The specimen calibration end to end: DOE -> run store -> surrogate -> KOH/NUTS -> report.

:func:`calibrate_specimen` is what ``solderpyro calibrate`` runs. Data flow (one direction):
measurements (shared/data-format.md) -> the model outputs they observe (times x points) ->
Latin hypercube over the parameter box -> batched FE runs in a crash-safe
:class:`~solderpyro.store.RunStore` -> GP surrogate of the observed outputs (one GP per output,
or a PCA basis for full-field data) with leave-one-out validation -> modular KOH posterior with
NUTS -> summary table (seed Table V layout), InferenceData, figures and ``report.md``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from solderpyro.calibration import Priors, calibrate_modular, predict_observation_model
from solderpyro.calibration.mcmc import Posterior, format_summary, write_summary
from solderpyro.configure import Setup
from solderpyro.design import lhs
from solderpyro.fem.problem import reference_grid
from solderpyro.fem.solver import SpecimenSolver
from solderpyro.io.measurements import Measurements
from solderpyro.params import LIU2008, anand_tensor
from solderpyro.store import RunStore, run_doe
from solderpyro.surrogate import GPSurrogate, LooResult

log = logging.getLogger("solderpyro")
SUMMARY = ("parameter", "q2.5", "median", "mean", "q97.5")


@dataclass
class SpecimenCalibration:
    """What :func:`calibrate_specimen` produced (files are in ``out``)."""

    out: Path
    posterior: Posterior
    summary: list[dict]
    loo: LooResult
    n_runs_ok: int
    n_runs_failed: int


def observation_index(meas: Measurements, times: tuple[float, ...], names: tuple[str, ...]
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Where each measured row sits in the model output ``(n_time, n_out)``.

    Returns:
        ``(n_obs,)`` time indices and ``(n_obs,)`` output indices.

    Raises:
        ValueError naming the first row whose time or point is not a model output.
    """
    ti = np.searchsorted(np.asarray(times), meas.time_s)
    oi = np.empty(len(meas), dtype=int)
    lookup = {n: j for j, n in enumerate(names)}
    for r in range(len(meas)):
        t, p = float(meas.time_s[r]), str(meas.point[r])
        if ti[r] >= len(times) or abs(times[ti[r]] - t) > 1e-6:
            raise ValueError(f"measurement row {r + 1}: time {t} s is not an output time")
        if p not in lookup:
            raise ValueError(f"measurement row {r + 1}: point {p!r} is not a model output; "
                             f"valid: A, B or grid labels g_ii_jj")
        oi[r] = lookup[p]
    return ti, oi


def calibrate_specimen(setup: Setup, meas: Measurements, out: str | Path, n_runs: int = 50,
                       seed: int = 0, store_root: str | Path = "runs/store",
                       batch_size: int = 64, nuts: dict[str, Any] | None = None,
                       progress: bool = True, kernel: str = "gaussian", ard: bool = True,
                       mean: str = "constant") -> SpecimenCalibration:
    """Calibrate ``setup.space`` (default s0, QR, xi, m) against ``meas``.

    Args:
        setup: typed problem, parameter box and defaults (see :mod:`solderpyro.configure`).
        meas: measurements; times and points must be model outputs (A, B, grid labels).
        out: run directory (created). n_runs: LHS size (the seed: 50).
        store_root: the run store shared by calibrations of the same problem.
        nuts: options of :func:`~solderpyro.calibration.mcmc.run_nuts`.
        kernel, ard, mean: the GP surrogate's settings (see :class:`GPSurrogate`).

    Returns:
        :class:`SpecimenCalibration`; writes summary.csv, posterior.nc, figures, report.md.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if len(meas) == 0:
        raise ValueError("the measurement file has no rows")
    field = any(p not in setup.problem.points for p in meas.points())
    times = tuple(float(t) for t in meas.times())
    solver = SpecimenSolver(setup.problem, reference_grid() if field else None,
                            dtype=setup.dtype, device=setup.device)
    store = RunStore(store_root)
    h = store.register(setup.problem, times, field, setup.dtype)
    space = setup.space
    theta = lhs(space, n_runs, seed)  # (n_runs, n_theta)
    liu = anand_tensor({}, base=LIU2008, dtype=torch.float64)[None]
    params = torch.cat([space.full(theta), liu])  # the literature run rides along
    log.info("DOE: %d LHS runs over %s + the Liu 2008 constants", n_runs, ", ".join(space.names))
    doe = run_doe(solver, store, h, params, times, batch_size, progress)
    ti, oi = observation_index(meas, doe.times, doe.names)
    y_sim = doe.V[:, ti, oi]  # (n_runs + 1, n_obs)
    ok = doe.ok[:n_runs]
    if int(ok.sum()) < max(5, space.dim + 2):
        raise RuntimeError(f"only {int(ok.sum())} of {n_runs} FE runs converged: "
                           f"{sorted(set(r for r in doe.reasons if r))[:3]}")
    y_obs = torch.as_tensor(meas.value_um, dtype=torch.float64)
    output = "batched" if y_obs.shape[0] <= 16 else "pca"
    log.info("surrogate: %s GP on %d runs, %d observed outputs", output, int(ok.sum()),
             y_obs.shape[0])
    gp = GPSurrogate(space, output=output, kernel=kernel, ard=ard, mean=mean)
    gp.fit(theta[ok], y_sim[:n_runs][ok])
    loo = gp.loo()
    problems = gp.check(loo)
    sig = meas.sigma_um[np.isfinite(meas.sigma_um)]
    yr = float(y_obs.max() - y_obs.min())
    pr = Priors(sigma_max=max(10 * float(sig.max()) if sig.size else 0.0, 0.5 * yr, 1e-3))
    nk: dict[str, Any] = dict(chains=4, warmup=500, draws=1000, seed=seed, progress=progress)
    nk.update(nuts or {})
    log.info("NUTS: %d chains x %d draws (modular KOH, code uncertainty from the GP)",
             nk["chains"], nk["draws"])
    post, inp = calibrate_modular(gp, y_obs, space, priors=pr, **nk)
    rows = [r for r in post.summary()]
    order = list(space.names) + ["sigma"]
    rows.sort(key=lambda r: order.index(r["parameter"]) if r["parameter"] in order else 99)
    write_summary(rows, out / "summary.csv", SUMMARY)
    post.save(out / "posterior.nc")
    bands = predict_observation_model(post, inp, None, seed=seed)
    from solderpyro import report

    report.write(out, meas, rows, post, loo, problems, bands, y_sim[-1], doe, ti, oi, nk)
    print(format_summary(rows))
    return SpecimenCalibration(out, post, rows, loo, int(ok.sum()), int((~ok).sum()))
