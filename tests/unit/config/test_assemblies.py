"""Your own assembly and cycle in YAML (docs/assemblies.md): the shipped die-attach example
(specimen=die_attach mesh=die_attach loading=jedec_m40_125), a profile from a CSV file,
repeated cycles, and the errors that name the offending key."""

import logging

import numpy as np
import pytest

from solderpyro.config.compose import build, compose
from solderpyro.fem.loading import REFERENCE_CYCLE, SEED_TIMES, time_grid
from solderpyro.fem.mesh import XSegment

DIE = ["specimen=die_attach", "mesh=die_attach", "loading=jedec_m40_125"]
PERIOD = 3780.0  # s: 25 -> 125 -> -40 -> 25 degC at 10 degC/min, two 15 min dwells


def test_the_die_attach_example_composes(caplog):
    """The CSV log (127 rows, 30 s apart) simplifies to its 6 corners, repeated 3 times; the
    output times are the cycle ends, which are on the time grid; the die's silicon comes from
    the specimen file; the solder and the die end at 3 mm, the substrate at 5 mm."""
    with caplog.at_level(logging.INFO, logger="solderpyro.config.compose"):
        setup = build(compose(DIE))
    assert "127 rows simplified to 6 knots" in caplog.text
    pr = setup.problem
    c = pr.cycle
    assert c.times[:6] == (0.0, 600.0, 1500.0, 2490.0, 3390.0, PERIOD)
    assert c.temps_C[:6] == (25.0, 125.0, 125.0, -40.0, -40.0, 25.0)
    assert len(c.times) == 16 and c.cycle_ends == (PERIOD, 2 * PERIOD, 3 * PERIOD)
    assert setup.times == c.cycle_ends and pr.T_ref_C == 25.0 == c(0.0)
    g = time_grid(c, setup.times, pr.stepping)
    assert all(np.abs(g - t).min() < 1e-9 for t in c.cycle_ends)
    si = pr.materials["silicon"]
    assert (si.E, si.nu, si.alpha) == (169e3, 0.28, 2.6e-6) and not si.nonlinear
    assert pr.materials["solder"].nonlinear and pr.plane == "strain"
    assert [(lay.name, lay.x1) for lay in pr.layers] == [
        ("substrate", None), ("solder", 3.0), ("die", 3.0)]
    assert pr.half_length == 5.0
    assert pr.mesh.x_segments == (XSegment(16, 0.1, "right"), XSegment(5, 0.3, "left"))


def test_the_reference_loading_is_unchanged():
    setup = build(compose([]))
    assert setup.problem.cycle == REFERENCE_CYCLE and setup.times == SEED_TIMES
    assert setup.problem.cycle.cycle_ends == (7800.0,)


@pytest.mark.parametrize("text, match", [
    ("time_s,temp_C\n0,25\n600,x\n", r"loading.profile_csv: .*line 3, column temp_C: 'x'"),
    ("time_s,temp_C\n0,25\n600,125\n600,25\n", r"loading.profile_csv: .*line 4, column time_s"),
    ("t,temp_C\n0,25\n600,125\n", r"loading.profile_csv: .*no column time_s"),
    ("time_s,temp_C\n0,25\n", r"loading.profile_csv: .*at least 2"),
])
def test_bad_profile_rows_name_the_key_line_and_column(tmp_path, text, match):
    p = tmp_path / "log.csv"
    p.write_text(text)
    with pytest.raises(ValueError, match=match):
        build(compose([*DIE, f"loading.profile_csv={p}"]))


def test_relative_profile_path_is_looked_up_in_the_working_directory(tmp_path, monkeypatch):
    """A relative path is the working directory's file when there is one (here a two-step
    cycle), else the packaged conf/loading/ file; neither: the error names both places."""
    (tmp_path / "mine.csv").write_text("time_s,temp_C\n0,25\n600,85\n1200,25\n")
    monkeypatch.chdir(tmp_path)
    c = build(compose([*DIE, "loading.profile_csv=mine.csv"])).problem.cycle
    assert c.cycle_ends == (1200.0, 2400.0, 3600.0) and c(600.0) == 85.0
    assert build(compose(DIE)).problem.cycle.end == 3 * PERIOD  # the packaged one
    with pytest.raises(FileNotFoundError, match=r"loading.profile_csv=none.csv.*conf/loading"):
        build(compose([*DIE, "loading.profile_csv=none.csv"]))


def test_loading_errors_name_the_key(tmp_path):
    open_csv = tmp_path / "open.csv"
    open_csv.write_text("time_s,temp_C\n0,25\n600,125\n")
    with pytest.raises(ValueError, match=r"loading.cycles=3 .* 25 -> 125 degC"):
        build(compose([*DIE, f"loading.profile_csv={open_csv}"]))
    build(compose([*DIE, f"loading.profile_csv={open_csv}", "loading.cycles=1"]))
    with pytest.raises(ValueError, match="loading.cycles must be a positive integer"):
        build(compose([*DIE, "loading.cycles=0"]))
    with pytest.raises(ValueError, match="either profile_csv .* not both"):
        build(compose([*DIE, "+loading.times_s=[0,600]", "+loading.temps_C=[25,75]"]))
    with pytest.raises(ValueError, match="loading.output_times=seed: the reference cycle"):
        build(compose([*DIE, "loading.output_times=seed"]))
    with pytest.raises(ValueError, match=r"loading.stress_free_C=183 differs .* \(25 degC\)"):
        build(compose([*DIE, "loading.stress_free_C=183"]))
    # repeated inline knots, output times defaulting to the cycle ends
    s = build(compose(["loading.times_s=[0,600,1200]", "loading.temps_C=[25,75,25]",
                       "+loading.cycles=2", "~loading.output_times"]))
    assert s.problem.cycle.times == (0.0, 600.0, 1200.0, 1800.0, 2400.0)
    assert s.times == (1200.0, 2400.0)


def test_specimen_errors_name_the_key():
    with pytest.raises(ValueError, match=r"specimen.points.D=\[4.0, 0.3\] mm lies off"):
        build(compose([*DIE, "specimen.points.D=[4.0,0.3]"]))
    with pytest.raises(ValueError, match="specimen.materials.copper: the materials group"):
        build(compose([*DIE, "+specimen.materials.copper={E_GPa:1,nu:0.3,cte_ppm:1}"]))
    with pytest.raises(ValueError, match=r"specimen.materials.silicon.nu=0.6"):
        build(compose([*DIE, "specimen.materials.silicon.nu=0.6"]))
    with pytest.raises(ValueError, match=r"specimen.layers: layer 'die': x1 = 9 mm"):
        build(compose([*DIE, "specimen.layers.2.x1_mm=9.0"]))
    with pytest.raises(ValueError, match=r"mesh.x_segments\[1\].toward"):
        build(compose([*DIE, "mesh.x_segments.1.toward=up"]))


def test_coarsened_halves_the_spans_along_x():
    """The half-resolution model of the die attach halves each span's elements along x (16, 5
    -> 8, 2) and each layer's rows."""
    from solderpyro.config.compose import coarsened

    pr = build(compose(coarsened(DIE))).problem
    assert [s.nx for s in pr.mesh.x_segments] == [8, 2]
    assert [lay.ny for lay in pr.layers] == [3, 1, 2]
