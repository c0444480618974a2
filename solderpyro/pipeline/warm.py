"""Where a recalibration starts (``solderpyro calibrate --warm-from RUN_DIR``).

From the related run's sampler state (its chains' last positions and adapted metric, by
coordinate name), and, where ``solderpyro diagnose`` refitted exactly the effects the new run
switches on, with every chain started at the end of that FE refit: the FE's own best fit of
the new model, where the new posterior is (:meth:`~solderpyro.calibration.mcmc.WarmStart.
placed`). The diagnosis is read from its file (:meth:`~solderpyro.config.rundir.RunDir.diagnosis`);
nothing here imports it.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

from solderpyro.calibration.mcmc import WarmStart
from solderpyro.config.rundir import RunDir

log = logging.getLogger("solderpyro")


def refit_point(run_dir: str | Path, effects: Sequence[str]) -> dict[str, float] | None:
    """The end of the diagnosis's FE refit of ``effects`` (beyond the run's own), or None.

    Args:
        run_dir: a calibrated, diagnosed run directory (:class:`~solderpyro.config.rundir.RunDir`,
            its diagnosis).
        effects: the new run's switched-on effects (registry names).
    Returns:
        ``name -> value`` (physical units; the calibrated parameters, the effects'
        parameters and ``sigma`` = the refit's RMS residual, um) of a converged refit whose
        effects are exactly the new ones, else None (no diagnosis, or no such refit).
    """
    try:
        run = RunDir.read(run_dir)
    except FileNotFoundError:
        return None
    diag = run.diagnosis()
    if diag is None:
        return None
    had = set(run.info.effects)
    new = set(effects) - had
    if not new:
        return None
    for step in diag.get("steps") or []:
        for rec in step:
            if set(rec.get("effects", [])) == new and rec.get("ok") and rec.get("x"):
                pt = {str(k): float(v) for k, v in rec["x"].items()}
                if rec.get("rms_after_um"):
                    pt["sigma"] = float(rec["rms_after_um"])
                return pt
    return None


def warm_start(run_dir: str | Path, effects: Sequence[str]) -> WarmStart:
    """The sampler state of ``run_dir`` for a run with ``effects`` switched on, with
    :attr:`~solderpyro.calibration.mcmc.WarmStart.point` set from :func:`refit_point`.

    Raises:
        FileNotFoundError: naming the missing sampler state.
    """
    from solderpyro.config.rundir import WARM_FILE

    ws = WarmStart.load(Path(run_dir) / WARM_FILE)
    ws.point = refit_point(run_dir, effects)
    if ws.point:
        log.info("warm start: the chains start at the diagnosis's FE refit with %s (%s)",
                 ", ".join(sorted(set(effects))),
                 ", ".join(f"{k}={v:.4g}" for k, v in ws.point.items()))
    return ws
