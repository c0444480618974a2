"""Sweeps: every job recorded as it ends, a rerun skips finished jobs, a failing job is recorded
with its error without stopping the others, and the same results on a Dask cluster."""

from __future__ import annotations

import json
import os
import sys

import cloudpickle
import pytest

from solderpyro.cli import main
from solderpyro.compute.executor import DaskExecutor, InProcess
from solderpyro.compute.sweep import sweep

cloudpickle.register_pickle_by_value(sys.modules[__name__])
# keep_environment: Dask's nanny writes its workers' settings into os.environ
pytestmark = pytest.mark.usefixtures("keep_environment")


def square(name: str) -> dict:
    """A job: ``int(name) ** 2``, and the process it ran in; ``'bad'`` raises."""
    if name == "bad":
        raise ValueError("no such dataset")
    return {"value": int(name) ** 2, "pid": os.getpid()}


def test_sweep_records_each_job_and_a_rerun_skips_finished_ones(tmp_path):
    rec = tmp_path / "sweep.json"
    res = sweep(["1", "2", "bad", "3"], square, rec, InProcess())
    assert [res[k]["value"] for k in ("1", "2", "3")] == [1, 4, 9]
    assert res["bad"]["ok"] is False and "ValueError: no such dataset" in res["bad"]["error"]
    assert all(r["wall_s"] >= 0 for r in res.values())
    assert json.loads(rec.read_text())["jobs"] == res

    def must_not_run(name: str) -> dict:
        raise AssertionError(f"job {name} ran again")

    again = sweep(["1", "2", "bad", "3"], must_not_run, rec, InProcess())
    assert again == res  # finished jobs (failed ones too) are not run again
    more = sweep(["1", "4"], square, rec, InProcess())
    assert more["4"]["value"] == 16 and more["1"] == res["1"]
    with pytest.raises(ValueError, match="distinct"):
        sweep(["1", "1"], square, rec)


def test_sweep_on_two_workers_gives_the_same_results_in_parallel(tmp_path):
    pytest.importorskip("distributed")
    with DaskExecutor.start("local:2") as ex:
        res = sweep([str(i) for i in range(6)], square, tmp_path / "s.json", ex)
    assert [res[str(i)]["value"] for i in range(6)] == [i * i for i in range(6)]
    assert len({r["pid"] for r in res.values()} - {os.getpid()}) == 2  # both workers, not us


def test_sweep_cli_names_missing_files(tmp_path, capsys):
    rc = main(["sweep", "--data", str(tmp_path / "nope.csv"), "--out", str(tmp_path / "o")])
    assert rc == 2
    assert "--data: no such measurement file" in capsys.readouterr().err
