"""Command-line conventions: a fast --help / --version, exit status 2 for usage errors and 1 for
failures of the computation (the message naming the cause and the file), -q / -v, the user's
config directory."""

import subprocess
import sys
from pathlib import Path

import pytest

import solderpyro
from solderpyro.cli import HELP_DEFAULTS, main

ROOT = Path(__file__).resolve().parents[2]
TINY = ["experiment=quick", "loading.times_s=[0,600,900]", "loading.temps_C=[25,75,75]",
        "loading.output_times=[600,900]"]


def _cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-c",
                           "import sys; from solderpyro.cli import main; sys.exit(main())",
                           *args], capture_output=True, text=True, cwd=cwd, timeout=600)


def test_version_prints_the_package_version(tmp_path):
    r = _cli("--version", cwd=tmp_path)
    assert r.returncode == 0 and r.stdout.strip() == f"solderpyro {solderpyro.__version__}"


def test_help_imports_nothing_heavy():
    """--help builds every sub-command's parser without torch, Hydra or NumPy (what made it
    take seconds)."""
    code = ("import sys; from solderpyro.cli import build_parser; build_parser(); "
            "print(sorted(m for m in ('torch', 'hydra', 'numpy', 'scipy') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "[]", r.stderr


def test_help_defaults_are_the_settings_defaults():
    from solderpyro.config.settings import CalibrationSettings
    from solderpyro.design.loop import BASE_BUDGET, BUDGET_DIMS

    s = CalibrationSettings()
    assert HELP_DEFAULTS == {
        "budget": s.design.budget, "budget_base": BASE_BUDGET, "budget_dims": BUDGET_DIMS,
        "start": s.design.start, "batch": s.design.batch,
        "criterion": s.design.criterion, "optimizer": s.design.optimizer,
        "exact_mode": s.exact.mode, "exact_runs": s.exact.runs, "exact_rounds": s.exact.rounds,
        "exact_profile": s.exact.profile, "chains": s.sampler.chains,
        "warmup": s.sampler.warmup, "draws": s.sampler.draws}


@pytest.mark.parametrize("args", [["simulate", "--out", "x.csv", "--bogus"],
                                  ["simulate", "--out", "x.csv", "mesh=nope"],
                                  ["simulate", "--out", "x.csv", "--noise", "-1"],
                                  ["koh", "--sim", "nope.csv", "--obs", "o.csv", "--t", "t",
                                   "--y", "y", "--out", "o"]])
def test_usage_errors_exit_2(tmp_path, capsys, monkeypatch, args):
    monkeypatch.chdir(tmp_path)
    assert main(args) == 2
    assert "error:" in capsys.readouterr().err


def test_argparse_errors_exit_2(capsys):
    with pytest.raises(SystemExit) as e:
        main(["frobnicate"])
    assert e.value.code == 2


def test_a_bad_value_in_a_data_file_exits_1_naming_the_file(tmp_path, capsys):
    sim = tmp_path / "sim.csv"
    sim.write_text("x,t,y\n0,0.1,1\n0.5,abc,2\n1,0.3,3\n")
    (tmp_path / "obs.csv").write_text("x,y\n0.2,1\n")
    assert main(["koh", "--sim", str(sim), "--obs", str(tmp_path / "obs.csv"), "--x", "x",
                 "--t", "t", "--y", "y", "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert str(sim) in err and "line 3" in err and "abc" in err


def test_quiet_prints_no_info_and_verbose_prints_debug(tmp_path):
    args = ["simulate", "--times", "600", "--out", str(tmp_path / "x.csv"), *TINY]
    loud = _cli(*args)
    assert loud.returncode == 0 and "INFO solderpyro" in loud.stderr  # "wrote ... values"
    for q in (["-q", *args], [*args, "-q"], [*args, "--quiet"]):
        quiet = _cli(*q)
        assert quiet.returncode == 0 and "INFO" not in quiet.stderr, q


def test_user_config_dir_adds_a_group_option(tmp_path, capsys):
    conf = tmp_path / "myconf" / "mesh"
    conf.mkdir(parents=True)
    (conf / "mine.yaml").write_text("defaults:\n  - coarse\n  - _self_\nnx: 9\n")
    from solderpyro.config.compose import compose

    assert compose(["mesh=mine"], config_dir=tmp_path / "myconf").mesh.nx == 9
    out = tmp_path / "x.csv"
    assert main(["simulate", "--times", "600", "--out", str(out), "--config-dir",
                 str(tmp_path / "myconf"), "mesh=mine", *TINY]) == 0
    assert out.stat().st_size > 0
    # a file named like a packaged one would never be read: a usage error naming it
    (conf / "default.yaml").write_text("nx: 3\n")
    assert main(["simulate", "--out", str(out), "--config-dir", str(tmp_path / "myconf"),
                 *TINY]) == 2
    assert "mesh/default.yaml" in capsys.readouterr().err
    assert main(["simulate", "--out", str(out), "--config-dir", str(tmp_path / "none")]) == 2


@pytest.mark.parametrize("command", ["calibrate", "koh"])
def test_a_binary_data_file_exits_1_naming_the_file(tmp_path, capsys, command):
    """A binary file where a CSV is expected is a data file the computation cannot use, as a
    malformed CSV is (exit 1): the message names the file and the first byte that is not
    UTF-8 text, not a bare codec error."""
    data = tmp_path / "bin.csv"
    data.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 4)
    (tmp_path / "obs.csv").write_text("x,y\n0.2,1\n")
    args = (["calibrate", "--data", str(data), "--out", str(tmp_path / "o"), *TINY]
            if command == "calibrate" else
            ["koh", "--sim", str(data), "--obs", str(tmp_path / "obs.csv"), "--x", "x",
             "--t", "t", "--y", "y", "--out", str(tmp_path / "o")])
    assert main(args) == 1
    err = capsys.readouterr().err
    assert f"{data}: not a text file (byte 0x89 at offset 0 is not UTF-8)" in err, err
    assert "codec" not in err


def test_an_unknown_effect_is_a_usage_error_listing_the_valid_ones(tmp_path, capsys):
    from solderpyro.effects import EFFECTS

    assert main(["simulate", "--times", "seed", "--out", str(tmp_path / "s.csv"),
                 "effects=[bogus]"]) == 2
    err = capsys.readouterr().err
    assert "unknown effect 'bogus'" in err and all(n in err for n in EFFECTS)
    assert not (tmp_path / "s.csv").exists()
    run = tmp_path / "run"  # checked before the run is loaded: a run record is enough
    run.mkdir()
    (run / "run.json").write_text("{}")
    assert main(["diagnose", str(run), "--effects", "thermal_lag,bogus_effect"]) == 2
    err = capsys.readouterr().err
    assert "--effects: unknown effect(s) ['bogus_effect']" in err
    assert all(n in err for n in EFFECTS)
