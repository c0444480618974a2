"""Simulate the reference specimen for one Anand parameter set, driven by the Hydra configs.

    python experiments/simulate_reference.py                          # reference case
    python experiments/simulate_reference.py mesh=fine specimen.plane=strain
    python experiments/simulate_reference.py -m mesh=coarse,default,fine   # a sweep (multirun)

Writes simulation.csv (docs/data-format.md) and cycle.png into Hydra's run directory.
"""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig

from solderpyro.cli import simulate_table
from solderpyro.config.compose import build
from solderpyro.io.measurements import from_arrays, write_measurements
from solderpyro.reporting.plots import plot_cycle

log = logging.getLogger(__name__)


@hydra.main(config_path="pkg://solderpyro.conf", config_name="config", version_base=None)
def main(cfg: DictConfig) -> None:
    setup = build(cfg)
    out = Path(hydra.core.hydra_config.HydraConfig.get().runtime.output_dir)
    t, names, pts, V = simulate_table(setup, {}, setup.times, field=False, progress=True)
    temps = np.array([setup.problem.cycle(x) for x in t])
    write_measurements(out / "simulation.csv",
                       from_arrays(t, names, pts, V, temperature_C=temps,
                                   meta={"generator": "experiments/simulate_reference.py"}))
    plot_cycle(t, V, names, temps, setup.problem.cycle).savefig(out / "cycle.png", dpi=120)
    for i, x in enumerate(t):
        log.info("t=%6.0f s  " + "  ".join(f"V_{n}={v:8.4f} um" for n, v in zip(names, V[i],
                                                                            strict=True)), x)
    log.info("outputs in %s", out)


if __name__ == "__main__":
    main()
