"""A finished run's final posterior model, rebuilt for the benchmarks that re-sample or time it
(``ridge_coords.py``, ``round_costs.py``)."""

from __future__ import annotations

import csv
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch


def rebuild(run: Path, store: str | None = None, data: str | None = None) -> SimpleNamespace:
    """Rebuild ``run``'s final surrogate from its converged design runs (``design.csv``, read
    back through the run store: no FE solve when the store holds them) and its posterior model.

    Args:
        run: a ``solderpyro calibrate`` run directory; store, data: its run store and
            measurement CSV (default: run.json's).
    Returns:
        ``sm`` (CalibrationProblem), ``gp``, ``inp`` (ObsInputs), ``fm`` (the flat model NUTS
        samples), ``post`` (posterior.nc's posterior group), ``T`` ``(N, p)`` its draws
        (physical, ``sm.space.names``), ``sig`` ``(N,)`` its noise sd draws.
    """
    import arviz as az

    from solderpyro.calibration.emulators import GPEmulator, ObservedEmulator
    from solderpyro.calibration.fastkoh import flat_model
    from solderpyro.calibration.koh import observation_model, prepare_observation
    from solderpyro.config.compose import build, compose
    from solderpyro.config.rundir import RunDir
    from solderpyro.config.settings import CalibrationSettings
    from solderpyro.io.measurements import read_measurements
    from solderpyro.pipeline.problem import CalibrationProblem
    from solderpyro.pipeline.surrogate import fit_surrogate

    info = RunDir.read(run).info
    setup = build(compose(info.overrides))
    sm = CalibrationProblem.build(setup, read_measurements(data or info.data),
                             store or info.store, 64, False)
    with (run / "design.csv").open() as f:
        rows = [r for r in csv.DictReader(f) if r["converged"] == "1"]
    names = list(sm.gp_box.names)
    X = torch.tensor([[float(r[n]) for n in names] for r in rows], dtype=torch.float64)
    V, ok = sm.fe(X)
    post = az.from_netcdf(str(run / "posterior.nc")).posterior
    sig = np.asarray(post["sigma"].values).reshape(-1)
    gp = fit_surrogate(sm, CalibrationSettings().surrogate, X[ok], V[ok], float(np.median(sig)))
    em = GPEmulator(gp)
    off = sm.offset()
    inp = prepare_observation(sm.y, em if off is None else ObservedEmulator(em, sm.n_fe, off),
                              sm.space)
    fm = flat_model(observation_model, (inp, sm.priors))
    T = np.stack([np.asarray(post[n].values).reshape(-1) for n in sm.space.names], 1)
    return SimpleNamespace(sm=sm, gp=gp, inp=inp, fm=fm, post=post, T=T, sig=sig)
