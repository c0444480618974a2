"""`solderpyro diagnose` and `calibrate effects=[...]` at a tiny size (short cycle, coarse
mesh): the contract files, a hidden effect found, a clean dataset not flagged, the error falling."""

import json

import numpy as np
import pytest
import torch

from solderpyro.cli import main
from solderpyro.configure import build, compose
from solderpyro.diagnose.hidden import make_dataset

TINY = ["experiment=quick", "loading.times_s=[0,600,900,1500]",
        "loading.temps_C=[25,75,75,25]", "loading.output_times=[600,900,1500]"]
TIMES = (600.0, 900.0, 1500.0)
# one design round: 16 LHS runs + 4 FE checks (+ the final FE check's 8), as the 16-run LHS
# was; no FE-exact step (the lag data misfit: "auto" would run it)
CAL = ["--start", "16", "--budget", "20", "--exact", "off", "--chains", "1", "--warmup", "100",
       "--draws", "100", "--quiet"]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    torch.set_num_threads(1)
    d = tmp_path_factory.mktemp("diag")
    setup = build(compose(TINY))
    make_dataset(setup, "thermal_lag", d / "lag.csv", False, TIMES, values=np.array([120.0]))
    make_dataset(setup, None, d / "clean.csv", False, TIMES)
    for name in ("lag", "clean"):
        assert main(["calibrate", "--data", str(d / f"{name}.csv"), "--out", str(d / name),
                     "--store", str(d / "store"), *CAL, *TINY]) == 0
        assert main(["diagnose", str(d / name), "--draws", "1", "--quiet",
                     "--effects", "thermal_lag,cte_temperature"]) == 0
    return d


def test_diagnosis_contract_and_hidden_effect_found(runs):
    dg = json.loads((runs / "lag" / "diagnosis.json").read_text())
    assert dg["misfit"] is True
    ev = [r["evidence"] for r in dg["ranking"]]
    assert ev == sorted(ev, reverse=True) and {r["effect"] for r in dg["ranking"]} == {
        "thermal_lag", "cte_temperature"}
    assert all(isinstance(r["evidence"], float) for r in dg["ranking"])
    # 6 values: the hidden effect is first, or the data cannot tell it from the first (the FE
    # refits with either effect on fit to chi2 < 6 apart) and the tool says so, never picking
    # another effect alone
    top = dg["ranking"][0]["effect"]
    assert top == "thermal_lag" or any({top, "thermal_lag"} <= set(g)
                                       for g in dg["indistinguishable"]), dg["verdict"]
    for f in ("diagnosis.md", "diagnosis.html", "diagnosis_residuals.png",
              "diagnosis_ranking.png"):
        assert (runs / "lag" / f).stat().st_size > 100, f


def test_second_diagnosis_reuses_every_fe_run(runs):
    """Every FE run of a diagnosis goes through the run store: the same diagnosis again
    computes none (each stage's cost is in diagnosis.json's timing) and ranks identically."""
    first = json.loads((runs / "lag" / "diagnosis.json").read_text())
    t1 = first["timing"]
    assert {"load", "predictive_check", "best_fit", "fe_jacobians", "score_tests", "ladder",
            "profile_refits", "verdict", "write", "total"} <= set(t1)
    assert all(r["seconds"] >= 0 for r in t1.values())
    assert t1["total"]["fe_runs"] == sum(r["fe_runs"] for k, r in t1.items() if k != "total")
    assert t1["fe_jacobians"]["fe_runs"] > 0
    # the refits' first step starts where the Jacobians were taken: those rows are reused
    assert t1["profile_refits"]["fe_reused"] > 0
    assert "Cost per stage" in (runs / "lag" / "diagnosis.md").read_text()
    assert main(["diagnose", str(runs / "lag"), "--draws", "1", "--quiet",
                 "--effects", "thermal_lag,cte_temperature"]) == 0
    second = json.loads((runs / "lag" / "diagnosis.json").read_text())
    t2 = second["timing"]
    assert t2["total"]["fe_runs"] == 0, t2
    assert t2["total"]["fe_reused"] == t1["total"]["fe_runs"] + t1["total"]["fe_reused"]
    for key in ("misfit", "verdict", "ranking", "check", "indistinguishable", "suggestions",
                "separation"):
        assert second[key] == first[key], key


def test_clean_data_flag_nothing(runs):
    dg = json.loads((runs / "clean" / "diagnosis.json").read_text())
    assert dg["misfit"] is False
    assert not any(r["flagged"] for r in dg["ranking"])


def test_calibrate_with_the_effect_and_compare(runs):
    out = runs / "lag_on"
    assert main(["calibrate", "--data", str(runs / "lag.csv"), "--out", str(out),
                 "--store", str(runs / "store"), *CAL, *TINY, "effects=[thermal_lag]"]) == 0
    rows = [r.split(",")[0] for r in (out / "summary.csv").read_text().splitlines()[1:]]
    assert rows == ["s0", "QR", "xi", "m", "sigma", "tau"]
    assert main(["compare", str(runs / "lag"), str(out)]) == 0
    cmp = json.loads((out / "comparison.json").read_text())
    assert cmp["after"]["rms_um"] < cmp["before"]["rms_um"]
    assert cmp["elpd_gain"] > 0


def test_diagnose_rejects_a_directory_without_a_run(tmp_path, capsys):
    assert main(["diagnose", str(tmp_path)]) == 2
    assert "run.json" in capsys.readouterr().err


def test_separation_finds_where_two_fits_differ(tmp_path):
    """Two 'fits' that differ only by a Moire offset c_1 = 0.2 um in the first image: on the
    grid at that time they differ by exactly 0.2 um everywhere, nowhere else; the measured
    values (A, B) are left out of every option; identical fits separate nowhere."""
    from solderpyro.diagnose.run import APART_CHI2, separation
    from solderpyro.io.measurements import read_measurements

    torch.set_num_threads(1)
    setup = build(compose(TINY))
    meas = read_measurements(make_dataset(setup, None, tmp_path / "c.csv", False, TIMES))
    cands = ("thermal_lag", "moire_rigid_motion")
    theta = np.array([12.92, 10586.0, 2.04, 0.1])
    x = np.concatenate([theta, [0.0], np.zeros(6)])
    shifted = x.copy()
    shifted[5] = 0.2  # moire_c_1 (the 600 s image)
    fits = {"thermal_lag": {"x": x}, "moire_rigid_motion": {"x": shifted}}
    sep = separation(setup, (), cands, fits, list(cands), meas, 0.05)
    assert {o["measurement"] for o in sep["options"]} == {
        "full-field V (31 x 18 grid) at the measured times",
        "full-field V (31 x 18 grid) at the extended times"}  # A, B at 600 s were measured
    for o in sep["options"]:
        assert o["n_new"] in (558, 3 * 558)
        assert o["chi2_apart"] == pytest.approx(558 * (0.2 / 0.05) ** 2, rel=1e-9)
        assert o["max_diff_um"] == pytest.approx(0.2, rel=1e-9) and o["time_s"] == 600.0
    assert "measure full-field V" in sep["advice"]
    same = separation(setup, (), cands, {"thermal_lag": {"x": x}, "moire_rigid_motion":
                                         {"x": x}}, list(cands), meas, 0.05)
    assert all(o["chi2_apart"] < APART_CHI2 * 1e-9 for o in same["options"])
    assert "no measurement tried" in same["advice"]


def test_hidden_moire_dataset_at_other_times_than_its_ladder(tmp_path):
    """The hidden values of a per-image effect are sized at the ladder's times; a dataset at
    fewer times keeps each image's offset and rotation (regression: it used to fail)."""
    import ast

    from solderpyro.io.measurements import read_measurements

    torch.set_num_threads(1)
    setup = build(compose(TINY))
    full = read_measurements(make_dataset(setup, "moire_rigid_motion", tmp_path / "a.csv",
                                          False, TIMES)).meta
    sub = read_measurements(make_dataset(setup, "moire_rigid_motion", tmp_path / "b.csv",
                                         False, (600.0, 1500.0))).meta
    a, b = ast.literal_eval(full["hidden_values"]), ast.literal_eval(sub["hidden_values"])
    assert len(a) == 6 and len(b) == 4
    assert (b["moire_c_1"], b["moire_c_2"]) == (a["moire_c_1"], a["moire_c_3"])
    assert (b["moire_w_1"], b["moire_w_2"]) == (a["moire_w_1"], a["moire_w_3"])
