"""Where a recalibration starts: the diagnosis's FE refit of the new model (pipeline.warm)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from solderpyro.calibration.mcmc import WarmStart
from solderpyro.config.rundir import WARM_FILE, RunDir, RunInfo
from solderpyro.params import Box
from solderpyro.pipeline.warm import refit_point, warm_start


def _state(chains: int = 4) -> WarmStart:
    """A base run's state on (s0, QR, sigma): chains far apart, a dense metric."""
    q = np.array([[12.4, -2.0, -1.3], [-1.4, -0.3, -1.4], [-2.3, 0.8, -1.4], [-2.0, 0.7, -1.4]])
    inv = np.array([[0.37, 0.01, 0.0], [0.01, 0.003, 0.0], [0.0, 0.0, 2e-4]])
    return WarmStart(["s0", "QR", "sigma"], q[:chains], inv, 0.49)


def test_placed_starts_every_chain_at_the_point_and_keeps_the_metric_by_name() -> None:
    box = Box(("s0", "QR", "k_E"), (5.0, 7000.0, 0.0), (25.0, 13000.0, 0.03), (False,) * 3)
    ws = _state()
    ws.point = {"s0": 13.3, "QR": 12180.0, "k_E": 0.0173, "sigma": 0.049}
    p = ws.placed(box, sigma_log=True, jitter=0.02, seed=3)
    assert p.unit_names == ["s0", "QR", "k_E"]
    u = np.array([(13.3 - 5) / 20, (12180 - 7000) / 6000, 0.0173 / 0.03])
    logit = np.log(u) - np.log1p(-u)
    # every chain within 5 jitter sd of the point (logit scale), sigma at log(0.049)
    assert np.abs(np.log(p.unit) - np.log1p(-p.unit) - logit).max() < 5 * 0.02
    assert np.abs(p.q[:, 2] - math.log(0.049)).max() < 5 * 0.02
    assert p.unit[:, 0].std() > 0  # dispersed, for R-hat
    # the metric and coordinates by name are the base run's (the sampler takes them by name)
    assert p.coords == ws.coords and p.inv_metric is ws.inv_metric
    q, inv, _ = p.apply(["s0", "QR", "k_E", "sigma"], 4, dense=True)
    assert inv[0, 0] == pytest.approx(0.37) and inv[0, 1] == pytest.approx(0.01)
    assert inv[2, 2] == 1.0 and inv[2, 0] == 0.0
    assert inv[3, 3] == pytest.approx(2e-4)


def test_unit_for_reads_old_logit_states_and_defaults_to_the_middle() -> None:
    ws = _state()  # no unit positions: a state written before they were kept
    u = ws.unit_for(["QR", "new"], 4)
    np.testing.assert_allclose(u[:, 0], 1 / (1 + np.exp(-ws.q[:, 1])))
    np.testing.assert_array_equal(u[:, 1], 0.5)


def test_placed_without_a_point_is_unchanged_and_a_bound_stays_finite() -> None:
    box = Box(("s0", "QR"), (5.0, 7000.0), (25.0, 13000.0), (False, False))
    ws = _state()
    assert ws.placed(box, True) is ws
    ws.point = {"s0": 25.0, "QR": 7000.0}  # a refit that ended on two box faces
    p = ws.placed(box, sigma_log=False)
    assert np.isfinite(p.q).all() and ((p.unit > 0) & (p.unit < 1)).all()
    assert np.allclose(p.q[:, 2], ws.q[:, 2])  # sigma without a log site keeps its positions


def _run(tmp_path, effects_had, steps):
    RunDir(tmp_path, RunInfo(["s0", "QR"], [5.0, 7000.0], [25.0, 13000.0], effects_had, None,
                             [600.0], ["A"])).write()
    (tmp_path / "diagnosis.json").write_text(json.dumps({"steps": steps}))
    st = _state()
    np.savez(tmp_path / WARM_FILE, coords=np.array(st.coords), q=st.q,
             inv_metric=st.inv_metric, step_size=st.step_size)
    return tmp_path


def test_refit_point_takes_the_refit_of_exactly_the_new_effects(tmp_path) -> None:
    steps = [[{"effects": ["thermal_lag"], "ok": True, "rms_after_um": 0.3,
               "x": {"s0": 10.0, "tau": 100.0}},
              {"effects": ["moire_rigid_motion"], "ok": False, "rms_after_um": 0.05,
               "x": {"s0": 11.0}}],
             [{"effects": ["thermal_lag", "moire_rigid_motion"], "ok": True,
               "rms_after_um": 0.049, "x": {"s0": 12.0, "tau": 105.0}}]]
    d = _run(tmp_path, [], steps)
    assert refit_point(d, ["thermal_lag"]) == {"s0": 10.0, "tau": 100.0, "sigma": 0.3}
    assert refit_point(d, ["moire_rigid_motion", "thermal_lag"])["s0"] == 12.0
    assert refit_point(d, ["moire_rigid_motion"]) is None  # that refit failed
    assert refit_point(d, []) is None
    assert warm_start(d, ["cte_temperature"]).point is None
    assert warm_start(d, ["thermal_lag"]).point["tau"] == 100.0


def test_refit_point_counts_the_effects_the_run_already_had(tmp_path) -> None:
    steps = [[{"effects": ["moire_rigid_motion"], "ok": True, "rms_after_um": 0.05,
               "x": {"s0": 11.0}}]]
    d = _run(tmp_path, ["thermal_lag"], steps)
    assert refit_point(d, ["thermal_lag", "moire_rigid_motion"])["s0"] == 11.0
    (d / "diagnosis.json").unlink()
    assert refit_point(d, ["thermal_lag", "moire_rigid_motion"]) is None
