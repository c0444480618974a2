"""Reading a calibration's run directory for a diagnosis: its files and its run store."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

from solderpyro.calibration.intervals import reported_interval
from solderpyro.config.rundir import RunInfo


def run_store(info: RunInfo, run_dir: Path) -> Any:
    """The run store of the calibration (its record's ``store``; a relative path is taken
    from the working directory, as ``calibrate`` took it), else ``run_dir/fe_store``."""
    from solderpyro.compute.runstore import RunStore

    root = info.store
    return RunStore(Path(root) if root else run_dir / "fe_store")


def load_run(run_dir: str | Path) -> dict[str, Any]:
    """Read what ``solderpyro calibrate`` left in ``run_dir`` for a diagnosis.

    Returns:
        dict with ``run`` (:class:`~solderpyro.config.rundir.RunDir`), ``info`` (its
        :class:`~solderpyro.config.rundir.RunInfo`), ``setup``
        (:class:`~solderpyro.config.compose.Setup`), ``meas`` (measurements), ``draws``
        (:meth:`~solderpyro.config.rundir.Draws.arrays`).
    Raises:
        FileNotFoundError naming the missing file; RunDirError naming the file and the key
        of a record this version cannot read.
    """
    from solderpyro.config.compose import build, compose
    from solderpyro.config.rundir import RUN_FILES, RunDir
    from solderpyro.specimen import output_points

    run = RunDir.read(run_dir, RUN_FILES)
    setup = build(compose(list(run.info.overrides)))
    meas = run.measurements(valid_points=output_points(setup.problem))
    return {"run": run, "info": run.info, "setup": setup, "meas": meas,
            "draws": run.draws().arrays()}


def reported_intervals(run_dir: str | Path) -> dict[str, tuple[float, float]] | None:
    """Parameter name -> the reported 95 % interval (physical units) of the run's
    ``summary.csv``; None where the run has none."""
    summ = Path(run_dir) / "summary.csv"
    if not summ.exists():
        return None
    with summ.open() as f:
        return {r["parameter"]: reported_interval(r) for r in csv.DictReader(f)}


def candidate_effects(run_effects: tuple[str, ...], candidates: tuple[str, ...] | None
                      ) -> tuple[str, ...]:
    """The effects a diagnosis tests: ``candidates``, by default every registered effect the
    run did not switch on.

    Raises:
        ValueError: naming an unknown effect and the valid ones.
    """
    from solderpyro.effects import EFFECTS

    if candidates is None:
        candidates = tuple(n for n in EFFECTS if n not in run_effects)
    unknown = [c for c in candidates if c not in EFFECTS]
    if unknown:
        raise ValueError(f"unknown effect(s) {unknown}; valid: {', '.join(EFFECTS)}")
    return candidates


def noise_sd(info: RunInfo, sigma_draws: Any) -> float:
    """The noise sd the FE is measured against, um: the data file's ``sigma_um`` where it
    states one, else the posterior median of sigma (``sigma_draws (N,)``)."""
    import numpy as np

    sig_known = info.sigma_known
    return float(sig_known) if sig_known else float(np.median(sigma_draws))
