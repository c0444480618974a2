"""`solderpyro sensitivity` at a tiny size: every file is written with the documented columns,
the store is reused on a rerun, and bad input exits non-zero naming it."""

import csv
import json

import pytest

from solderpyro.cli import main
from solderpyro.params import ANAND_NAMES

COLS = ["parameter", "dgsm", "dgsm_rank", "S1", "S1_lo", "S1_hi", "ST", "ST_lo", "ST_hi",
        "rank"]


#: coarse mesh, large steps, the first ramp and dwell of the reference cycle (Hydra overrides)
TINY = ["experiment=quick", "loading.times_s=[0,600,1500]", "loading.temps_C=[25,75,75]"]


@pytest.mark.filterwarnings("ignore::solderpyro.surrogate.gp.SurrogateWarning")
def test_sensitivity_command_contract(tmp_path, capsys):
    out, store = tmp_path / "sens", tmp_path / "store"
    args = ["sensitivity", "--out", str(out), "--runs", "12", "--grad-points", "4",
            "--times", "600,1500", "--store", str(store), "--sobol-samples", "256",
            "--bootstrap", "20", "--refits", "2", "--seed", "3", "--quiet", *TINY]
    assert main(args) == 0
    with open(out / "sensitivity.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == COLS and [r["parameter"] for r in rows] == list(ANAND_NAMES)
    assert sorted(int(r["rank"]) for r in rows) == list(range(1, 10))
    assert sorted(int(r["dgsm_rank"]) for r in rows) == list(range(1, 10))
    for r in rows:
        assert float(r["ST_lo"]) <= float(r["ST"]) <= float(r["ST_hi"])
        assert float(r["S1_lo"]) <= float(r["S1"]) <= float(r["S1_hi"])
    dg = {r["parameter"]: float(r["dgsm"]) for r in rows}
    # physics through the FE derivatives: Q/R moves exp(-Q/RT) by ~e^17 across its box, while
    # the hardening constants h0, n, a barely act in one ramp and dwell (measured: > 100x less)
    assert dg["QR"] > 10 * max(dg["h0"], dg["n"], dg["a"]) > 0
    js = json.loads((out / "sensitivity.json").read_text())
    assert js["outputs"] == ["V_A@600s", "V_B@600s", "V_A@1500s", "V_B@1500s"]
    assert js["dgsm_points"] == 4 and js["n_runs_ok"] >= 10
    assert js["verdict"]["text"].startswith("The top 4 by total index are")
    assert len(js["verdict"]["top"]) == 4 and isinstance(js["verdict"]["reproduced"], bool)
    assert len(js["per_parameter"]["QR"]["ST_refits"]) == 2  # the two GP refits
    assert js["per_parameter"]["QR"]["ST_se_surrogate"] >= 0
    assert (out / "sensitivity.png").stat().st_size > 10_000
    md = (out / "sensitivity.md").read_text()
    assert "the seed chose s0, QR, xi, m" in md and "sensitivity.png" in md
    assert "the seed chose" in capsys.readouterr().out
    # the DOE is in the store and its design is reproducible: the same LHS is served entirely
    # from the store (a solver that must not be called)
    from solderpyro.analysis.sensitivity import sensitivity_box
    from solderpyro.compute.runstore import RunStore
    from solderpyro.compute.store import DoeOptions, run_doe
    from solderpyro.config.compose import build, compose
    from solderpyro.design import lhs

    setup = build(compose(TINY))
    box = sensitivity_box(setup.space)
    st = RunStore(store)
    h = st.register(setup.problem, (600.0, 1500.0), False, setup.dtype)

    def no_solve(p, times):
        raise AssertionError("stored runs were recomputed")

    doe = run_doe(no_solve, st, h, box.full(lhs(box, 12, 3)), (600.0, 1500.0),
                  options=DoeOptions(progress=False))
    assert doe.n_reused == 12 and doe.n_computed == 0


@pytest.mark.parametrize("extra, needle", [
    (["nosuchgroup=1"], "nosuchgroup"),
    (["--runs", "5"], "--runs"),
    (["--grad-points", "1"], "--grad-points"),
    (["--sobol-samples", "1000"], "--sobol-samples"),
    (["--times", "9000"], "--times"),
    (["--box", "zeta=1:2"], "zeta"),
    (["--refits", "-1"], "--refits"),
])
def test_sensitivity_bad_input_exits_nonzero(tmp_path, capsys, extra, needle):
    rc = main(["sensitivity", "--out", str(tmp_path / "o"), "--store", str(tmp_path / "s"),
               *extra])
    assert rc != 0
    assert needle in capsys.readouterr().err
    assert not list((tmp_path / "s").glob("*/runs/*.json"))  # nothing was computed
