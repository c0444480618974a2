"""The typed run directory (solderpyro.config.rundir): round trip, version-1 files, clear
errors, and the commands reading it (compare, diagnose's load, the warm start, index.html)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from solderpyro.config.rundir import (
    RUN_JSON,
    SCHEMA,
    AlloyRecord,
    Checks,
    DesignSummary,
    Draws,
    RunDir,
    RunDirError,
    RunInfo,
    SurrogateRecord,
)
from solderpyro.io.measurements import from_arrays

TIMES = [600.0, 900.0, 1500.0]
#: the problem's points A and B (solderpyro/conf/specimen), as the measurements name them
POINTS = {"A": (15.0, 4.5), "B": (15.0, -4.0)}


def _info(**kw) -> RunInfo:
    base = dict(
        parameters=["s0", "QR"], lower=[5.0, 7000.0], upper=[25.0, 13000.0], effects=[],
        sigma_known=None, times_s=TIMES, points=list(POINTS),
        overrides=["experiment=quick"], data="lag.csv", store="runs/store", seed=3,
        settings={"sampler": {"chains": 2, "draws": 100, "warmup": 50}, "batch": 8},
        surrogate=SurrogateRecord("matern52", True, "linear", "pca", "unit", False, False),
        n_runs=20, design=DesignSummary({"reason": "converged", "fe_runs": 20, "budget": 110,
                                         "best_fit": {"x": {"s0": 12.0, "QR": 9000.0}},
                                         "rounds": [{"n": 16}]}),
        checks=Checks({"ok": True, "rms_um": 0.05, "rms_over_sigma": 1.02}, {"warn": False,
                      "message": "fine"}, 0.01, 0.95),
        timing_s={"problem": 1.5, "design": 20.0}, trust="the surrogate posterior",
        posterior="surrogate", exact={"ess": 120.0, "khat": 0.3, "reliable": True},
        extra={"note": "kept as it is"})
    base.update(kw)
    return RunInfo(**base)


def _run_dir(path, info: RunInfo | None = None, seed: int = 0) -> RunDir:
    """A small run directory as calibrate leaves it: run.json, data.csv, draws.npz,
    summary.csv (no posterior.nc)."""
    rng = np.random.default_rng(seed)
    truth = np.array([[1.0, -0.5], [1.4, -0.7], [2.0, -1.1]])
    meas = from_arrays(TIMES, list(POINTS), list(POINTS.values()),
                       truth + 0.05 * rng.standard_normal(truth.shape), sigma_um=0.05)
    n, n_pred = 40, 30
    proc = truth.reshape(-1) + 0.02 * rng.standard_normal((n_pred, 6))
    dr = Draws(theta=np.c_[rng.uniform(10, 14, n), rng.uniform(8000, 10000, n)],
               sigma=np.full(n, 0.05), names=["s0", "QR"], process=proc,
               observed=proc + 0.05 * rng.standard_normal(proc.shape),
               y_obs=np.asarray(meas.value_um, float), y_liu=truth.reshape(-1) + 0.3,
               sigma_pred=np.full(n_pred, 0.05))
    run = RunDir(path, info or _info()).write(meas, dr)
    rows = ["parameter,q2.5,median,mean,q97.5,lo95,hi95,interval,r_hat,ess_bulk"]
    for j, nm in enumerate(dr.names):
        q = np.quantile(dr.theta[:, j], [0.025, 0.5, 0.975])
        rows.append(f"{nm},{q[0]},{q[1]},{dr.theta[:, j].mean()},{q[2]},{q[0]},{q[2]},"
                    "central,1.0,400")
    (path / "summary.csv").write_text("\n".join(rows) + "\n")
    return run


def test_round_trip_equals_and_keeps_the_version_1_keys(tmp_path) -> None:
    run = _run_dir(tmp_path)
    back = RunDir.read(tmp_path)
    assert back.info == run.info and back.info.schema == SCHEMA
    raw = json.loads((tmp_path / RUN_JSON).read_text())
    assert raw["schema"] == SCHEMA
    # the keys of today's run.json, where the readers of older versions look for them
    assert {"overrides", "data", "settings", "seed", "store", "kernel", "ard", "mean",
            "surrogate_output", "surrogate_inputs", "inputs_T_C", "inputs_rate", "n_runs",
            "design", "loo_rmse_rel", "loo_coverage95", "fe_check", "discretization",
            "timing_s", "trust", "posterior", "exact", "parameters", "lower", "upper",
            "sigma_known", "effects", "times_s", "points", "note"} <= set(raw)
    assert raw["surrogate_output"] == "pca" and raw["fe_check"]["ok"] is True
    assert back.info.design.budget == 110 and DesignSummary({}).budget is None
    dr = back.draws()
    assert dr.names == ["s0", "QR"] and dr.theta.shape == (40, 2) and dr.process.shape == (30, 6)
    meas = back.measurements(valid_points=POINTS)
    np.testing.assert_array_equal(meas.value_um, dr.y_obs)
    assert back.summary()["QR"]["interval"] == "central"
    assert back.info.sampler == {"chains": 2, "draws": 100, "warmup": 50}
    assert back.diagnosis() is None and back.correction() is None


def test_a_run_json_without_schema_is_version_1(tmp_path) -> None:
    _run_dir(tmp_path)
    raw = json.loads((tmp_path / RUN_JSON).read_text())
    del raw["schema"]
    (tmp_path / RUN_JSON).write_text(json.dumps(raw))
    info = RunDir.read(tmp_path).info
    assert info.schema == 1
    assert info == _info(schema=1)
    # an early version-1 file: only the keys save_run wrote from the start
    early = {k: raw[k] for k in ("parameters", "lower", "upper", "effects", "sigma_known",
                                 "times_s", "points", "overrides")}
    (tmp_path / RUN_JSON).write_text(json.dumps(early))
    info = RunDir.read(tmp_path).info
    assert info.posterior == "surrogate" and info.surrogate is None and not info.checks.fe_ok
    assert info.design.reason is None and info.design.best_fit == {} and info.store is None


@pytest.mark.parametrize("edit, key", [
    (lambda d: d.pop("parameters"), "'parameters'"),
    (lambda d: d.pop("effects"), "'effects'"),
    (lambda d: d.update(schema=SCHEMA + 1), "'schema'"),
    (lambda d: d.update(schema="2"), "'schema'"),
    (lambda d: d.update(points="A"), "'points'"),
    (lambda d: d.update(design=[1]), "'design'"),
    (lambda d: d.update(alloy="SAC305"), "'alloy'"),
    (lambda d: d.update(alloy={"name": "SAC305"}), "'alloy.source'"),
])
def test_a_missing_key_or_unknown_schema_names_the_file_and_the_key(tmp_path, edit,
                                                                    key) -> None:
    RunDir(tmp_path, _info()).write()
    raw = json.loads((tmp_path / RUN_JSON).read_text())
    edit(raw)
    (tmp_path / RUN_JSON).write_text(json.dumps(raw))
    with pytest.raises(RunDirError) as err:
        RunDir.read(tmp_path)
    assert str(tmp_path / RUN_JSON) in str(err.value) and key in str(err.value)


def test_the_alloy_round_trips_and_is_optional(tmp_path) -> None:
    """``alloy`` (the materials file's solder and source) is written where set and read back;
    a run.json without it (older runs, a materials file without ``alloy``) reads as None, and
    the file keeps the same schema."""
    alloy = AlloyRecord("SAC305", "M. Motalab et al., ITherm 2012, 910-922")
    RunDir(tmp_path, _info(alloy=alloy)).write()
    raw = json.loads((tmp_path / RUN_JSON).read_text())
    assert raw["alloy"] == {"name": "SAC305", "source": "M. Motalab et al., ITherm 2012, 910-922"}
    assert raw["schema"] == SCHEMA
    back = RunDir.read(tmp_path).info
    assert back.alloy == alloy and back == _info(alloy=alloy) and "alloy" not in back.extra
    for edit in (lambda d: d.pop("alloy"), lambda d: d.update(alloy=None)):
        edit(raw)
        (tmp_path / RUN_JSON).write_text(json.dumps(raw))
        assert RunDir.read(tmp_path).info == _info()
    RunDir(tmp_path, _info()).write()
    assert "alloy" not in json.loads((tmp_path / RUN_JSON).read_text())
    assert RunDir.read(tmp_path).info.alloy is None


def test_missing_files_and_non_json_are_named(tmp_path) -> None:
    with pytest.raises(FileNotFoundError, match="run.json"):
        RunDir.read(tmp_path)
    RunDir(tmp_path, _info()).write()
    with pytest.raises(FileNotFoundError, match="data.csv"):
        RunDir.read(tmp_path, ("run.json", "data.csv"))
    (tmp_path / RUN_JSON).write_text("{not json")
    with pytest.raises(RunDirError, match="run.json: not JSON"):
        RunDir.read(tmp_path)


def test_compare_and_the_diagnosis_read_the_run_directory(tmp_path) -> None:
    """compare's metrics and figure, diagnose's loading, the warm start's refit point and
    index.html all read the record through RunDir (a version-1 file as well)."""
    from solderpyro.diagnose.compare import compare, run_metrics
    from solderpyro.diagnose.load import load_run, run_store
    from solderpyro.pipeline.warm import refit_point
    from solderpyro.reporting.index import write_index

    a = _run_dir(tmp_path / "a")
    b = _run_dir(tmp_path / "b", _info(effects=["thermal_lag"], sigma_known=0.05,
                                       posterior="fe-exact"), seed=0)
    m = run_metrics(a.path)
    assert m["elpd_method"] == "gaussian" and m["effects"] == [] and m["n"] == 6
    res = compare(a.path, b.path, tmp_path / "cmp")
    assert res["after"]["effects"] == ["thermal_lag"]
    assert any("fe-exact" in w for w in res["warnings"])
    assert (tmp_path / "cmp" / "comparison.png").stat().st_size > 1000

    run = load_run(a.path)
    assert run["info"] == a.info and run["run"].path == a.path
    assert run["draws"]["names"] == ["s0", "QR"] and len(run["meas"]) == 6
    assert run_store(run["info"], a.path).root.name == "store"

    (b.path / "diagnosis.json").write_text(json.dumps({"steps": [[{
        "effects": ["moire_rigid_motion"], "ok": True, "x": {"s0": 11.0}}]]}))
    assert refit_point(b.path, ["thermal_lag", "moire_rigid_motion"]) == {"s0": 11.0}

    page = write_index(a.path).read_text()
    assert "the surrogate posterior" in page and "run.json" in page

    raw = json.loads((a.path / RUN_JSON).read_text())
    raw["schema"] = SCHEMA + 1
    (a.path / RUN_JSON).write_text(json.dumps(raw))
    for read in (load_run, run_metrics):
        with pytest.raises(RunDirError, match="run.json: key 'schema'"):
            read(a.path)
