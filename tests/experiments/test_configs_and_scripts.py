"""Every config composes into typed objects; every experiment script and CLI command runs tiny."""

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.stats import chi2

from solderpyro.cli import main
from solderpyro.config.compose import CONFIG_DIR, build, compose
from solderpyro.io.measurements import read_measurements

ROOT = Path(__file__).resolve().parents[2]
TINY = ["experiment=quick", "loading.times_s=[0,600,900]", "loading.temps_C=[25,75,75]",
        "loading.output_times=[600,900]"]


def _group_options():
    for group in sorted(p for p in CONFIG_DIR.iterdir() if p.is_dir()):
        for f in sorted(group.glob("*.yaml")):
            yield f"{group.name}={f.stem}" if group.name != "experiment" else f"+x={f.stem}"


#: options that need another group's matching option (a mesh has rows per layer name)
PAIRED = {"specimen=die_attach": ["mesh=die_attach"], "mesh=die_attach": ["specimen=die_attach"]}


@pytest.mark.parametrize("override", [o for o in _group_options() if not o.startswith("+x")])
def test_every_group_option_composes(override):
    setup = build(compose([override, *PAIRED.get(override, [])]))
    assert setup.problem.mesh.nx >= 1 and len(setup.times) >= 1


@pytest.mark.parametrize("exp", sorted(p.stem for p in (CONFIG_DIR / "experiment").glob("*.yaml")))
def test_every_experiment_composes(exp):
    cfg = compose([f"experiment={exp}"])
    build(cfg)


def test_defaults_are_the_reference_case():
    s = build(compose([]))
    assert s.problem.plane == "stress" and s.problem.T_ref_C == 25.0
    assert s.space.names == ("s0", "QR", "xi", "m")
    assert s.times == (600.0, 2700.0, 4800.0, 7800.0)
    assert s.problem.materials["solder"].E == pytest.approx(32e3)


@pytest.mark.parametrize("bad,msg", [
    (["mesh.nx=0"], "mesh.nx"), (["materials.solder.nu=0.7"], "materials.solder.nu"),
    (["nosuchkey=1"], "nosuchkey"), (["materials.anand.m=3"], "m=3"),
    (["solver.stepping.scheme=rk4"], "scheme"), (["solver.dtype=float16"], "solver.dtype")])
def test_bad_config_is_named(bad, msg):
    with pytest.raises(ValueError, match=msg):
        build(compose(bad))


def test_cli_simulate_contract(tmp_path):
    """simulate writes the measurement format; noise has the requested sigma; V_A > 0 at 75 C."""
    out = tmp_path / "sim.csv"
    rc = main(["simulate", "--theta", "s0=12.9,QR=10586,xi=2.04,m=0.2", "--times", "600,900",
               "--out", str(out), "--quiet", *TINY])
    assert rc == 0
    m = read_measurements(out)
    assert sorted(set(m.point)) == ["A", "B"] and len(m) == 4
    tab = m.to_table()
    assert tab[0, 0] > 5.0  # bending + expansion lifts A by several um at 75 C
    noisy = tmp_path / "noisy.csv"
    assert main(["simulate", "--theta", "s0=12.9,QR=10586,xi=2.04,m=0.2", "--times", "600,900",
                 "--noise", "0.05", "--seed", "3", "--out", str(noisy), "--quiet", *TINY]) == 0
    d = read_measurements(noisy).to_table() - tab
    assert 0 < np.abs(d).max() < 0.25 and np.allclose(read_measurements(noisy).sigma_um, 0.05)


def test_cli_field_grid(tmp_path):
    out = tmp_path / "field.csv"
    assert main(["simulate", "--times", "600", "--field", "--out", str(out), "--quiet",
                 *TINY]) == 0
    m = read_measurements(out)
    assert len(m) == 2 + 31 * 18
    tab = m.to_table()
    pts = m.points()
    # V is even in x (symmetric specimen): g_00_jj (x=-15) equals g_30_jj (x=+15)
    for j in (0, 9, 17):
        assert tab[0, pts.index(f"g_00_{j:02d}")] == pytest.approx(
            tab[0, pts.index(f"g_30_{j:02d}")], abs=1e-12)
    assert tab[0, pts.index("A")] == pytest.approx(tab[0, pts.index("g_30_17")], abs=1e-12)


@pytest.mark.parametrize("args,msg", [
    (["--theta", "bogus=1"], "unknown Anand parameter 'bogus'"),
    (["--theta", "m=5"], "m=5.0 is outside"),
    (["--theta", "s0"], "not name=value"),
    (["--times", "600,abc"], "times must be"),
    (["--noise", "-1"], "--noise must be > 0"),
    (["mesh.nx=abc"], "mesh.nx"),
    (["notanoverride"], "key=value"),
])
def test_cli_bad_input_exits_nonzero_naming_it(tmp_path, capsys, args, msg):
    rc = main(["simulate", "--out", str(tmp_path / "x.csv"), "--quiet", *args])
    assert rc != 0
    assert msg in capsys.readouterr().err


def test_experiment_script_runs_tiny(tmp_path):
    r = subprocess.run([sys.executable, str(ROOT / "experiments" / "simulate_reference.py"),
                        *TINY, f"hydra.run.dir={tmp_path}"], capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    m = read_measurements(tmp_path / "simulation.csv")
    assert len(m) == 4 and (tmp_path / "cycle.png").stat().st_size > 10_000


NUTS_TINY = ["--chains", "2", "--warmup", "60", "--draws", "60", "--quiet"]
# the adaptive design at its smallest: 10 LHS runs and one round (4 FE checks at posterior
# draws; the budget leaves no room for more); the FE-exact step off unless asked
CAL_TINY = ["--start", "10", "--budget", "14", "--q", "4", "--exact", "off", *NUTS_TINY]
# two rounds: 10 LHS + round 1 (4 checks, 4 acquired) + round 2 (4 checks)
DEMO_TINY = ["--start", "10", "--budget", "22", "--q", "4", *NUTS_TINY]


def _stored(store: Path) -> dict[str, np.ndarray]:
    """Every stored FE run's solver row (the nine Anand constants, then any effect
    parameters), by file name."""
    return {f"{p.parent.parent.name}/{p.name}":
            np.array(list(json.loads(p.read_text())["params"].values()), float)
            for p in store.glob("*/runs/*.json")}


# slow (3 min on CI's two cores): CI's wheel smoke runs the same demo from the installed wheel
@pytest.mark.slow
def test_demo_command_runs_tiny(tmp_path):
    """Simulate, then calibrate on synthetic data by the adaptive design (design.csv holds
    every FE run it made, the run store every FE run at all); `calibrate` on the same data and
    store proposes the same runs and reuses every one, then runs the FE-exact posterior and
    the profile intervals, whose FE runs are kept in the store too."""
    import csv

    from solderpyro.compute.runstore import param_hash
    from solderpyro.specimen import SpecimenModel

    assert main(["demo", "--out", str(tmp_path), *DEMO_TINY, "--exact", "off", *TINY]) == 0
    assert (tmp_path / "cycle.png").exists() and len(read_measurements(
        tmp_path / "simulation.csv")) > 4
    cal = tmp_path / "calibration"
    for f in ("report.md", "summary.csv", "posterior.nc", "fig8_literature.png",
              "fig9_posterior.png", "fig10_predictive.png", "surrogate_loo.png",
              "design.csv", "design_rounds.json", "design.png"):
        assert (cal / f).stat().st_size > 100, f
    setup = build(compose(TINY))
    box = setup.space
    info = json.loads((cal / "run.json").read_text())
    des = info["design"]
    assert "fe_best_fit" not in info and "local_region" not in info
    # the materials preset the run started from (table3.yaml's alloy entry)
    assert info["alloy"]["name"] == setup.alloy.name == "Sn37Pb"
    assert info["alloy"]["source"] == setup.alloy.source
    assert info["settings"]["design"]["budget"] == 22
    assert info["settings"]["exact"]["mode"] == "off"
    assert isinstance(info["trust"], str) and info["trust"]
    # the trust line names what to trust (no FE-exact step here: the surrogate posterior),
    # and says so when the chains disagree
    assert info["trust"].startswith("the surrogate posterior")
    import arviz as az

    rh = az.rhat(az.from_netcdf(str(cal / "posterior.nc")))
    rmax = max(float(rh[v].max()) for v in rh.data_vars)
    assert ("the chains disagree" in info["trust"]) == (rmax > 1.01), (rmax, info["trust"])
    assert des["reason"] in ("converged", "budget") and des["message"]
    # the design's arithmetic: 10 LHS runs; each round 4 checks, and 4 acquired runs when it
    # does not stop and the budget leaves room for them and the next round's checks; at 22
    # runs the next round's checks would exceed the budget: round 2 is the last
    with (cal / "design.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    kinds = [r["kind"] for r in rows]
    n_rounds = len(des["rounds"])
    assert n_rounds in (1, 2) and (des["reason"] == "converged" or n_rounds == 2)
    assert kinds[:10] == ["start"] * 10 and {r["round"] for r in rows[:10]} == {"0"}
    assert kinds.count("check") == 4 * n_rounds
    assert kinds.count("acquired") == 4 * (n_rounds - 1) == sum(
        r["acquired"] for r in des["rounds"])
    assert len(rows) == des["fe_runs"] == info["n_runs"] == 10 + 8 * n_rounds - 4 <= 22
    assert json.loads((cal / "design_rounds.json").read_text())["reason"] == des["reason"]
    X = torch.tensor([[float(r[n]) for n in box.names] for r in rows], dtype=torch.float64)
    lo_t, hi_t = (torch.tensor(b, dtype=torch.float64) for b in (box.lower, box.upper))
    assert bool(((X >= lo_t * (1 - 1e-7)) & (X <= hi_t * (1 + 1e-7))).all())  # in the box
    # nothing lost: every design run is in the store (design.csv keeps 8 significant digits),
    # and the store holds exactly what was computed: the Liu 2008 run, the design, the FE
    # check's 8 posterior draws (fewer only where a draw repeats) and two runs of the refined
    # FE (under its own problem hash): the discretization correction's at the last round's
    # best checked draw and the discretization check's at the best FE-checked posterior draw
    store = _stored(tmp_path / "store")
    S = np.stack(list(store.values()))
    to_rows = SpecimenModel(setup.problem, setup.space).solver_rows
    for x in to_rows(X).numpy():
        assert np.isclose(S, x, rtol=1e-7, atol=0.0).all(1).any(), x
    chk = info["fe_check"]
    assert chk["draws"] == 8 and len(rows) + 3 < len(store) <= len(rows) + 3 + chk["draws"]
    # the correction (default on): taken at a checked draw of the last round, kept with the
    # run, and the final posterior's data are the measured ones minus it
    disc = info["discretization"]
    at = disc["correction"]["at"]
    assert any(all(np.isclose(float(r[k]), v, rtol=1e-7) for k, v in at.items())
               for r in rows if r["kind"] == "check")
    z = np.load(cal / "discretization_correction.npz")
    y_meas = np.array(read_measurements(tmp_path / "data.csv").value_um)
    np.testing.assert_allclose(z["y_measured"], y_meas, rtol=0, atol=1e-12)
    y_post = np.asarray(az.from_netcdf(str(cal / "posterior.nc")).observed_data["y"])
    np.testing.assert_allclose(y_post.reshape(-1), y_meas - z["delta"], rtol=0, atol=1e-12)
    assert np.abs(z["delta"]).max() > 0 and disc["uncorrected_chi2"] > disc["shift_chi2"]
    assert len({k.split("/")[0] for k in store}) == 2  # the calibration's FE and the refined
    n = len(store)
    assert all(int(r["converged"]) for r in rows)
    # the report counts every FE run of the calibration (Liu, design, FE check, the
    # discretization check's): all computed
    assert (f"FE runs: {n} converged, 0 failed (0 reused from the run store, {n} computed)"
            in (cal / "report.md").read_text())
    out = tmp_path / "again"
    assert main(["calibrate", "--data", str(tmp_path / "data.csv"), "--out", str(out),
                 "--store", str(tmp_path / "store"), *DEMO_TINY, "--exact", "on",
                 "--exact-runs", "6", "--exact-rounds", "2", "--exact-profile", "3",
                 "--profile-ci", "calibration.discretization=check",
                 "calibration.exact.extra_rounds=0", *TINY]) == 0
    # the discretization only measured: the data not corrected, nothing recorded as such
    assert not (out / "discretization_correction.npz").exists()
    assert "correction" not in json.loads((out / "run.json").read_text())["discretization"]
    # the same settings and data: the same design, every run (and the FE check) from the store;
    # what was computed is the FE-exact step's runs, all of them stored
    m = re.search(r"\((\d+) reused from the run store, (\d+) computed\)",
                  (out / "report.md").read_text())
    assert m is not None and int(m.group(1)) >= n
    assert len(_stored(tmp_path / "store")) == n + int(m.group(2))
    info = json.loads((out / "run.json").read_text())
    assert info["design"]["reason"] == des["reason"]
    with (out / "design.csv").open(newline="") as fh:
        assert list(csv.DictReader(fh)) == rows
    # every FE run of the FE-exact step is in the store (the importance samples included)
    smp = np.load(out / "exact_samples.npz")
    inside = np.isfinite(smp["log_target"])
    assert inside.sum() >= 6 and smp["theta"].shape == (12, 4)
    solver_rows = to_rows(torch.as_tensor(smp["theta"][inside]))
    names = {p.name for p in (tmp_path / "store").glob("*/runs/*.json")}
    assert {f"{param_hash(r)}.json" for r in solver_rows} <= names
    # ... and the best fit's forward differences (2 starts x 4 parameters in its first step)
    assert len(_stored(tmp_path / "store")) >= n + 8 + int(inside.sum())
    ex = (out / "exact_posterior.csv").read_text().splitlines()
    assert ex[0] == ("parameter,q2.5,median,mean,q97.5,lo95,hi95,interval,surrogate_q2.5,"
                     "surrogate_median,surrogate_q97.5,ess,khat") and len(ex) == 6
    assert 1.0 <= float(ex[1].split(",")[-2]) <= 12.0  # Kish ESS of 12 weights
    assert "## FE-exact posterior" in (out / "report.md").read_text()
    assert (out / "exact_posterior.png").stat().st_size > 1000
    ex_info = info["exact"]
    assert info["settings"]["exact"] == {"mode": "on", "runs": 6, "rounds": 2, "profile": 3,
                                         "profile_ci": "on", "extra_rounds": 0}
    assert info["posterior"] == ("fe-exact" if ex_info["reliable"] else "surrogate")
    assert len(ex_info["rounds"]) == 2 and ex_info["samples"] == 12
    # the profile-likelihood intervals: one per calibrated parameter inside the box, each end
    # flagged when it is the box's bound; every profile fit's FE run is in the store
    pci = (out / "profile_ci.csv").read_text().splitlines()
    assert pci[0] == ("parameter,lower,upper,at_lower_bound,at_upper_bound,truncated,"
                      "posterior_q2.5,posterior_q97.5")
    assert [r.split(",")[0] for r in pci[1:]] == list(box.names)
    for r, lo_b, hi_b in zip(pci[1:], box.lower, box.upper, strict=True):
        f = r.split(",")
        lo, hi = float(f[1]), float(f[2])
        assert lo_b - 1e-9 <= lo <= hi <= hi_b + 1e-9
        assert f[3] in ("true", "false") and (f[3] == "true") == (abs(lo - lo_b) < 1e-6)
        assert (f[4] == "true") == (abs(hi - hi_b) < 1e-6)
    assert len(ex_info["profile_ci"]) == 4
    # 12 importance weights never reach ESS 50: the weights are not reliable, so every
    # reported interval holds its FE profile interval, or the profile adds < 5 % of its width
    assert not ex_info["reliable"]
    with (out / "summary.csv").open(newline="") as fh:
        summ = {r["parameter"]: r for r in csv.DictReader(fh)}
    for p in ex_info["profile_ci"]:
        r = summ[p["parameter"]]
        lo, hi = float(r["lo95"]), float(r["hi95"])
        if r["interval"] == "profile":
            assert lo <= p["lower"] and p["upper"] <= hi
        else:
            assert max(lo - p["lower"], 0) + max(p["upper"] - hi, 0) < 0.05 * (hi - lo)
    n_prof = sum(len(p["grid"]) for p in ex_info["profile_ci"])
    assert len(names) >= n + int(inside.sum()) + n_prof
    assert len(ex_info["profile"]["values"]) >= 3
    # the best fit starts at the FE check's best draw: Levenberg-Marquardt never goes uphill
    chk = info["fe_check"]
    assert ex_info["best_fit"]["chi2"] <= chk["chi2"] * (1 + 1e-9)
    # the FE check at posterior draws: its chi2 and RMS describe the same residuals, and the
    # report warns exactly when the FE misfits by more than 1.5 noise sd
    assert chk["n"] == len(read_measurements(tmp_path / "data.csv"))
    assert chk["chi2"] == pytest.approx(chk["n"] * chk["rms_over_sigma"] ** 2, rel=1e-9)
    assert chk["draws"] == 8 and chk["ok"] == (chk["rms_over_sigma"] <= 1.5 or chk["chi2"]
                                               <= chi2.ppf(0.999, chk["n"]))
    assert ("the FE itself misfits" in (out / "report.md").read_text()) == (not chk["ok"])
    rows = (out / "summary.csv").read_text().splitlines()
    assert rows[0] == "parameter,q2.5,median,mean,q97.5,lo95,hi95,interval"
    assert [r.split(",")[0] for r in rows[1:]] == ["s0", "QR", "xi", "m", "sigma"]
    for r in rows[1:]:  # the reported 95 % interval: central, from a box face, or widened
        _, q_lo, med, _, q_hi, lo, hi, kind = r.split(",")
        assert kind in ("central", "lower face", "upper face", "likelihood", "model form",
                        "profile")
        assert float(lo) <= float(med) <= float(hi)
        if kind == "central":
            assert (lo, hi) == (q_lo, q_hi)


def test_calibrate_rejects_points_not_in_the_model(tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text("time_s,temperature_C,point,x_mm,y_mm,quantity,value_um,sigma_um\n"
                   "600,75,A,15,4.5,V,1.0,0.05\n"
                   "600,75,Q,0,0,V,1.0,0.05\n")
    assert main(["calibrate", "--data", str(bad), "--out", str(tmp_path / "o"),
                 "--store", str(tmp_path / "s"), *CAL_TINY, *TINY]) == 1  # a bad data file
    err = capsys.readouterr().err
    assert "'Q'" in err and "line 3" in err and str(bad) in err


def test_calibrate_names_bad_design_and_exact_flags(tmp_path, capsys):
    """Bad settings are named before any FE run: the design's (budget below the start plus one
    round's checks, a start too small for a surrogate of 4 parameters, q = 0), the FE-exact
    step's, the sampler's; a bad choice is argparse's error."""
    good = tmp_path / "good.csv"
    good.write_text("time_s,temperature_C,point,x_mm,y_mm,quantity,value_um,sigma_um\n"
                    "600,75,A,15,4.5,V,7.7,0.05\n")
    for flags, name in ((["--budget", "5"], "design.budget"),  # default start 30
                        (["--start", "12", "--budget", "15"], "design.budget (15)"),
                        (["--start", "5"], "design.start must be >= 6"),
                        (["--q", "0"], "design.batch"),
                        (["--exact-runs", "1"], "runs=1"),
                        (["--exact-rounds", "0"], "rounds=0"),
                        (["--exact-profile", "1"], "profile=1"),
                        (["--chains", "0"], "sampler.chains"),
                        (["--batch", "0"], "batch must be >= 1")):
        assert main(["calibrate", "--data", str(good), "--out", str(tmp_path / "o"),
                     "--store", str(tmp_path / "s"), *NUTS_TINY, *flags, *TINY]) == 2, flags
        assert name in capsys.readouterr().err, flags
    for flags in (["--criterion", "entropy"], ["--exact", "8"], ["--optimizer", "grid"]):
        with pytest.raises(SystemExit) as e:
            main(["calibrate", "--data", str(good), "--out", str(tmp_path / "o"),
                  "--store", str(tmp_path / "s"), *NUTS_TINY, *flags, *TINY])
        assert e.value.code == 2 and f"argument {flags[0]}: invalid choice" in \
            capsys.readouterr().err, flags
    assert not (tmp_path / "s").exists() and not (tmp_path / "o").exists()  # nothing computed


def test_calibrate_experiment_script_runs_tiny(tmp_path):
    data = tmp_path / "data.csv"
    assert main(["simulate", "--theta", "s0=12.9,m=0.1", "--noise", "0.05", "--out", str(data),
                 "--quiet", *TINY]) == 0
    r = subprocess.run([sys.executable, str(ROOT / "experiments" / "calibrate.py"), *TINY,
                        f"data.path={data}", "calibration.design.start=8",
                        "calibration.design.budget=12", "calibration.sampler.chains=1",
                        "calibration.sampler.warmup=50", "calibration.sampler.draws=50",
                        "calibration.sampler.round_warmup=50",
                        "calibration.sampler.round_draws=50", "calibration.exact.mode=off",
                        f"calibration.store={tmp_path / 'store'}", "surrogate=matern",
                        f"hydra.run.dir={tmp_path / 'run'}"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    rows = (tmp_path / "run" / "summary.csv").read_text().splitlines()
    assert [x.split(",")[0] for x in rows[1:]] == ["s0", "QR", "xi", "m", "sigma"]
    assert (tmp_path / "run" / "report.md").exists()


def test_calibrate_full_field_tiny(tmp_path):
    """Full-field data (the 31 x 18 grid) go through the PCA surrogate and the low-rank
    likelihood; the run directory has everything a diagnosis needs."""
    data = tmp_path / "field.csv"
    assert main(["simulate", "--theta", "s0=12.9,m=0.1", "--field", "--noise", "0.05",
                 "--out", str(data), "--quiet", *TINY]) == 0
    m = read_measurements(data)
    assert len(m) > 1000
    out = tmp_path / "run"
    assert main(["calibrate", "--data", str(data), "--out", str(out), "--store",
                 str(tmp_path / "store"), *CAL_TINY, *TINY]) == 0
    info = json.loads((out / "run.json").read_text())
    assert info["surrogate_output"] == "pca" and info["overrides"] == TINY
    for f in ("report.html", "report.md", "summary.csv", "posterior.nc", "draws.npz",
              "data.csv", "fig10_predictive.png"):
        assert (out / f).stat().st_size > 100, f
    with np.load(out / "draws.npz") as z:
        assert z["process"].shape[1] == len(m) and z["theta"].shape[1] == 4
    html = (out / "report.html").read_text()
    assert "<table>" in html and 'src="fig10_predictive.png"' in html


# slow (2 min on CI's two cores): a benchmark script's plumbing, not the product's
@pytest.mark.slow
def test_hidden_effect_case_script_runs_tiny(tmp_path):
    """The walkthrough script: hidden thermal lag -> calibrate -> diagnose -> add -> compare.
    Three output times (6 values): with TINY's two, the 4 values leave the candidates no
    degree of freedom beyond the 4 Anand constants, and the diagnosis rightly tests none."""
    tiny3 = [o for o in TINY if not o.startswith("loading.")] + [
        "loading.times_s=[0,600,750,900]", "loading.temps_C=[25,75,75,75]",
        "loading.output_times=[600,750,900]"]
    r = subprocess.run([sys.executable, str(ROOT / "experiments" / "hidden_effect_case.py"),
                        *tiny3, "+case.effect=thermal_lag", "+case.field=false", "+case.draws=1",
                        "+case.candidates=[thermal_lag,cte_temperature]",
                        "calibration.design.start=12", "calibration.design.budget=16",
                        "calibration.sampler.chains=1", "calibration.sampler.warmup=80",
                        "calibration.sampler.draws=80", "calibration.sampler.round_warmup=80",
                        "calibration.sampler.round_draws=80", "calibration.exact.mode=off",
                        f"calibration.store={tmp_path / 'store'}",
                        f"hydra.run.dir={tmp_path / 'run'}"],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    run = tmp_path / "run"
    assert (run / "base" / "diagnosis.json").exists()
    dg = json.loads((run / "base" / "diagnosis.json").read_text())
    assert dg["misfit"] is True
    added = [p.name for p in run.glob("with_*")]
    assert len(added) == 1 and (run / added[0] / "comparison.md").exists()
