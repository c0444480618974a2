"""Calibrate the Anand constants against a measurement CSV, driven by the Hydra configs.

    python experiments/calibrate.py data.path=runs/demo/data.csv
    python experiments/calibrate.py data.path=FILE.csv surrogate=matern calibration.runs=80
    python experiments/calibrate.py -m data.path=FILE.csv surrogate=gaussian,matern  # sweep

Same workflow as ``solderpyro calibrate``; writes report.md, summary.csv, posterior.nc and the
figures into Hydra's run directory. The run store (calibration.store) is shared between runs.
"""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
from omegaconf import DictConfig

from solderpyro.configure import build, task_overrides
from solderpyro.io.measurements import read_measurements
from solderpyro.workflow import calibrate_specimen, output_points

log = logging.getLogger(__name__)


@hydra.main(config_path="../configs", config_name="config", version_base=None)
def main(cfg: DictConfig) -> None:
    if not cfg.data.path:
        raise SystemExit("set data.path=FILE.csv (a measurement CSV, shared/data-format.md)")
    setup = build(cfg)
    meas = read_measurements(hydra.utils.to_absolute_path(cfg.data.path),
                             valid_points=output_points(setup.problem))
    out = Path(hydra.core.hydra_config.HydraConfig.get().runtime.output_dir)
    c = cfg.calibration
    res = calibrate_specimen(setup, meas, out, n_runs=int(c.runs), seed=int(c.seed),
                             store_root=hydra.utils.to_absolute_path(c.store),
                             batch_size=int(c.batch),
                             nuts=dict(chains=int(c.chains), warmup=int(c.warmup),
                                       draws=int(c.draws)),
                             record={"overrides": task_overrides(), "data": str(cfg.data.path)},
                             **setup.surrogate)
    log.info("report: %s", res.out / "report.html")


if __name__ == "__main__":
    main()
