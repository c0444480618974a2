"""Walk through one hidden-effect case: data with an effect the baseline model lacks ->
calibrate -> diagnose -> calibrate with the top-ranked effect -> before/after.

    python experiments/hidden_effect_case.py +case.effect=thermal_lag +case.field=true

Options (``+case.<key>=...``): ``effect`` (an effect name, or ``none`` for clean data; default
thermal_lag), ``field`` (full-field grid at the output times instead of A, B; default true),
``noise`` (um, 0.05), ``seed`` (0), ``draws`` (posterior draws of the diagnosis, 2),
``candidates`` (a list of effect names to test; default all). The calibration settings are
the ``calibration`` group's (``calibration.design.budget=80`` ...) and every other override
changes the model as usual. Outputs go to the Hydra run directory: data.csv,
base/ (calibration + diagnosis), with_<effect>/ (calibration + comparison.md).
See docs/diagnosis.md.
"""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
from omegaconf import DictConfig

from solderpyro.config.compose import build, calibration_settings, compose, task_overrides
from solderpyro.diagnose import diagnose
from solderpyro.diagnose.compare import compare
from solderpyro.diagnose.hidden import make_dataset
from solderpyro.io.measurements import read_measurements
from solderpyro.pipeline import calibrate_specimen
from solderpyro.specimen import output_points

log = logging.getLogger(__name__)


@hydra.main(config_path="pkg://solderpyro.conf", config_name="config", version_base=None)
def main(cfg: DictConfig) -> None:
    case = dict(cfg.get("case") or {})
    effect = str(case.get("effect", "thermal_lag"))
    field = bool(case.get("field", True))
    setup = build(cfg)
    out = Path(hydra.core.hydra_config.HydraConfig.get().runtime.output_dir)
    data = make_dataset(setup, None if effect == "none" else effect, out / "data.csv", field,
                        setup.times, noise=float(case.get("noise", 0.05)),
                        seed=int(case.get("seed", 0)))
    meas = read_measurements(data, valid_points=output_points(setup.problem))
    log.info("hidden effect %s: %s", effect, meas.meta.get("hidden_values", "-"))
    ov = task_overrides()
    s = calibration_settings(cfg, setup.surrogate)
    s.store = hydra.utils.to_absolute_path(s.store)
    calibrate_specimen(setup, meas, out / "base", s, record={"overrides": ov})
    cands = case.get("candidates")
    dg = diagnose(out / "base", n_draws=int(case.get("draws", 2)),
                  candidates=None if not cands else tuple(str(c) for c in cands))
    log.info("verdict: %s", dg.verdict)
    top = next((r["effect"] for r in dg.ranking if r["flagged"]), None)
    if top is None:
        log.info("no effect flagged: nothing to add")
        return
    ov2 = [o for o in ov if not o.startswith("effects=")] + [f"effects=[{top}]"]

    setup2 = build(compose(ov2))
    calibrate_specimen(setup2, meas, out / f"with_{top}", s, record={"overrides": ov2})
    r = compare(out / "base", out / f"with_{top}")
    log.info("RMS residual %.4g -> %.4g um (noise %.3g um); ELPD gain %.1f nats",
             r["before"]["rms_um"], r["after"]["rms_um"], float(case.get("noise", 0.05)),
             r["elpd_gain"])


if __name__ == "__main__":
    main()
