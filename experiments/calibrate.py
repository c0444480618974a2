"""Calibrate the Anand constants against a measurement CSV, driven by the Hydra configs.

    python experiments/calibrate.py data.path=runs/demo/data.csv
    python experiments/calibrate.py data.path=FILE.csv calibration.design.budget=80
    python experiments/calibrate.py -m data.path=FILE.csv surrogate=gaussian,matern  # sweep
    python experiments/calibrate.py data.path=FILE.csv cluster=local cluster.local=local:4

Same workflow as ``solderpyro calibrate``; writes report.md, summary.csv, posterior.nc and the
figures into Hydra's run directory. The run store (calibration.store) is shared between runs.
"""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
from omegaconf import DictConfig

from solderpyro.compute.executor import executor_from_options
from solderpyro.config.compose import build, calibration_settings, task_overrides
from solderpyro.io.measurements import read_measurements
from solderpyro.pipeline import calibrate_specimen
from solderpyro.specimen import output_points

log = logging.getLogger(__name__)


@hydra.main(config_path="pkg://solderpyro.conf", config_name="config", version_base=None)
def main(cfg: DictConfig) -> None:
    if not cfg.data.path:
        raise SystemExit("set data.path=FILE.csv (a measurement CSV, docs/data-format.md)")
    setup = build(cfg)
    meas = read_measurements(hydra.utils.to_absolute_path(cfg.data.path),
                             valid_points=output_points(setup.problem))
    out = Path(hydra.core.hydra_config.HydraConfig.get().runtime.output_dir)
    s = calibration_settings(cfg, setup.surrogate)
    s.store = hydra.utils.to_absolute_path(s.store)
    cl = cfg.get("cluster") or {}
    with executor_from_options(cl.get("local"), cl.get("scheduler")):
        res = calibrate_specimen(setup, meas, out, s,
                                 record={"overrides": task_overrides(),
                                         "data": str(cfg.data.path)})
    log.info("report: %s", res.out / "report.html")


if __name__ == "__main__":
    main()
