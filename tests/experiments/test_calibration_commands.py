"""The calibration command contracts: `solderpyro example seed-math` and `solderpyro koh`."""

import csv
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from solderpyro.cli import main

ROOT = Path(__file__).resolve().parents[2]
TINY = ["--chains", "2", "--warmup", "60", "--draws", "60", "--quiet"]


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.reader(f))


def test_example_seed_math_contract(tmp_path):
    """Through experiments/seed_math.py, which is `solderpyro example seed-math`."""
    r = subprocess.run([sys.executable, str(ROOT / "experiments" / "seed_math.py"), "--out",
                        str(tmp_path), "--seed", "3", *TINY], capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    data = np.loadtxt(tmp_path / "data.csv", delimiter=",", skiprows=1)
    assert _rows(tmp_path / "data.csv")[0] == ["x", "y"]
    assert np.allclose(data[:, 0], np.arange(11) * 0.3)
    # the data are the true process plus N(0, 0.6^2) noise: residuals are plausible
    resid = data[:, 1] - (1.5 + 3.5 * np.exp(-1.7 * data[:, 0]))
    assert abs(resid.mean()) < 4 * 0.6 / np.sqrt(11) and 0.2 < resid.std() < 1.2
    for name, params in (("table1.csv", ["t", "sigma"]),
                         ("table2.csv", ["t", "sigma", "beta", "sigma_c", "theta"])):
        rows = _rows(tmp_path / name)
        assert rows[0] == ["parameter", "q2.5", "median", "q97.5"]
        assert [r[0] for r in rows[1:]] == params
        for row in rows[1:]:
            lo, med, hi = map(float, row[1:])
            assert lo <= med <= hi
    reg = _rows(tmp_path / "regression.csv")
    assert reg[0] == ["t", "sigma"] and 0.2 < float(reg[1][0]) < 1.2
    for fig in ("fig1_direct.png", "fig2_direct_posterior.png", "fig3_surrogate.png",
                "fig4_joint_predictive.png"):
        assert (tmp_path / fig).stat().st_size > 10_000
    assert "Table I" in r.stdout and "0.6557" in r.stdout  # printed beside the seed's numbers


def _tables(tmp_path, t_true=0.7):
    from scipy.stats import qmc

    u = qmc.LatinHypercube(d=2, seed=1).random(15)
    x, t = 3 * u[:, 0], 0.2 + 1.3 * u[:, 1]
    np.savetxt(tmp_path / "sim.csv", np.c_[x, t, 5 * np.exp(-t * x)], delimiter=",",
               header="x,t,y", comments="")
    xo = np.arange(11) * 0.3
    yo = 5 * np.exp(-t_true * xo) + 0.2 * np.random.default_rng(0).standard_normal(11)
    np.savetxt(tmp_path / "obs.csv", np.c_[xo, yo], delimiter=",", header="x,y", comments="")


@pytest.mark.parametrize("mode", ["joint", "modular"])
def test_koh_command_contract(tmp_path, mode):
    _tables(tmp_path)
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "solderpyro.cli", "koh", "--sim",
                        str(tmp_path / "sim.csv"), "--obs", str(tmp_path / "obs.csv"), "--x", "x",
                        "--t", "t", "--y", "y", "--out", str(out), "--mode", mode,
                        *TINY],
                       capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    rows = _rows(out / "summary.csv")
    assert rows[0] == ["parameter", "q2.5", "median", "mean", "q97.5"]
    got = {row[0]: list(map(float, row[1:])) for row in rows[1:]}
    assert {"t", "sigma"} <= set(got)
    lo, med, _, hi = got["t"]
    assert 0.2 <= lo <= med <= hi <= 1.5  # inside the runs' range (the default prior box)
    assert abs(med - 0.7) < 0.15  # the truth, with noise 0.2 on 11 points
    assert (out / "posterior.nc").stat().st_size > 1000


@pytest.mark.parametrize("args,msg,status", [
    (["--y", "yy"], "has no column(s) ['yy']", 1),  # the tables do not fit: a failure
    (["--mode", "full"], "--mode must be 'joint' or 'modular'", 2),  # a usage error
])
def test_koh_bad_input_exits_nonzero_naming_it(tmp_path, capsys, args, msg, status):
    _tables(tmp_path)
    base = {"--sim": str(tmp_path / "sim.csv"), "--obs": str(tmp_path / "obs.csv"),
            "--x": "x", "--t": "t", "--y": "y", "--out": str(tmp_path / "o")}
    base.update(dict(zip(args[::2], args[1::2], strict=True)))
    argv = ["koh"] + [v for kv in base.items() for v in kv] + TINY
    assert main(argv) == status
    assert msg in capsys.readouterr().err
    assert main(["koh", "--sim", str(tmp_path / "nope.csv"), "--obs", "o.csv", "--t", "t",
                 "--y", "y", "--out", str(tmp_path / "o")]) == 2
    assert "SIM file" in capsys.readouterr().err
