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
CAL = ["--runs", "16", "--chains", "1", "--warmup", "100", "--draws", "100", "--quiet"]


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
    assert dg["ranking"][0]["effect"] == "thermal_lag"
    for f in ("diagnosis.md", "diagnosis.html", "diagnosis_residuals.png",
              "diagnosis_ranking.png"):
        assert (runs / "lag" / f).stat().st_size > 100, f


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
