"""solderpyro.predict: one draw equals a direct FE run, nothing solved is lost, the transfer
rules (alloy, effects, temperature range) and the band's share from the constants."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from solderpyro.config.compose import build, compose
from solderpyro.config.rundir import Checks, Draws, RunDir, RunInfo
from solderpyro.io.measurements import from_arrays
from solderpyro.predict import predict
from solderpyro.predict.quantities import constants_share, regions

#: a quick run: the coarse mesh and steps (experiment=quick)
OVERRIDES = ["experiment=quick"]
NAMES = ["s0", "QR", "xi", "m"]


def _run_dir(path, effects=(), extra_cols=(), overrides=OVERRIDES, n=12, seed=0):
    """A run directory as calibrate leaves it, with ``n`` draws around Liu's constants."""
    rng = np.random.default_rng(seed)
    cols = [rng.uniform(11.0, 14.0, n), rng.uniform(9000.0, 10000.0, n),
            rng.uniform(1.4, 2.0, n), rng.uniform(0.25, 0.33, n),
            *[rng.uniform(lo, hi, n) for lo, hi in extra_cols]]
    theta = np.stack(cols, 1)
    names = NAMES + [f"p{i}" for i in range(len(extra_cols))]
    if effects:
        from solderpyro.effects import effect_set

        names = NAMES + list(effect_set(effects).names)
    info = RunInfo(parameters=names, lower=list(theta.min(0)), upper=list(theta.max(0)),
                   effects=list(effects), sigma_known=0.05, times_s=[600.0, 7800.0],
                   points=["A", "B"], overrides=list(overrides),
                   checks=Checks({"ok": True}))
    meas = from_arrays([600.0, 7800.0], ["A", "B"], [(15.0, 4.5), (15.0, -4.0)],
                       np.zeros((2, 2)), sigma_um=0.05)
    dr = Draws(theta=theta, sigma=np.full(n, 0.05), names=names, process=np.zeros((2, 4)),
               observed=np.zeros((2, 4)), y_obs=np.zeros(4), y_liu=np.zeros(4),
               sigma_pred=np.full(2, 0.05))
    RunDir(path, info).write(meas, dr)
    return theta


def test_predict_at_one_draw_equals_a_direct_fe_run(tmp_path):
    """predict's displacements and its interface-row inelastic work at one draw are those of
    the FE solved directly at that draw (the user's own path: SpecimenModel and the solver
    with a SolderRecorder), to rounding (1e-9 of the values: the same arithmetic in another
    batch)."""
    from solderpyro.fem.record import SolderRecorder
    from solderpyro.specimen import SpecimenModel

    theta = _run_dir(tmp_path / "run")
    pred = predict(tmp_path / "run", theta=theta[3:4], out=tmp_path / "p", progress=False,
                   layer_mm=0.25)
    setup = build(compose(OVERRIDES))
    model = SpecimenModel(setup.problem, setup.space, setup.times)
    th = torch.as_tensor(theta[3:4])
    V = model.run(th).V.numpy()
    np.testing.assert_allclose(pred.fields.V, V, rtol=0, atol=1e-9 * np.abs(V).max())
    rec = SolderRecorder(setup.problem.cycle.cycle_ends)
    with torch.no_grad():
        model.solver.solve(model.solver_rows(th), model.times, recorder=rec)
    W = rec.finish(torch.ones(1, dtype=torch.bool)).work[0, -1].numpy()  # (n_e, n_qp)
    slv = model.solver
    ys = np.asarray(slv.mesh.nodes)[np.asarray(slv.mesh.elems)[np.asarray(slv.el_solder)]][..., 1]
    top = ys.min(1) >= 0.5 - 0.25 - 1e-9  # the solder within 0.25 mm of the upper interface
    w = slv.wdet[:slv.n_s].numpy()
    direct = float((W * w)[top].sum() / w[top].sum())
    got = pred.bands[("dW", "upper_interface", 1)].median
    assert direct > 0
    assert abs(got - direct) <= 1e-9 * direct
    # each history point's accumulated equivalent inelastic strain never falls and ends at
    # the field's value there at the cycle's end
    f = pred.fields
    assert np.all(np.diff(f.p_hist[0], axis=0) >= 0)
    for j, h in enumerate(pred.points):
        e, q = h.index
        assert f.p_hist[0, -1, j] == f.eps_p_eq[0, -1, e, q] > 0
    # the whole joint's average lies between the two interface rows' and the largest value
    j = pred.bands[("dW", "joint", 1)].median
    assert j <= pred.bands[("dW", "max", 1)].median
    assert (tmp_path / "p" / "index.html").is_file()
    import arviz as az

    nc = az.from_netcdf(tmp_path / "p" / "predictions.nc").predictions
    assert nc["dW_upper_interface"].dims == ("chain", "draw", "cycle")
    assert nc["cycle"].values.tolist() == [1]
    assert float(nc["dW_upper_interface"].values[0, 0, 0]) == got


def test_a_rerun_reads_the_solved_chunks_and_solves_only_what_is_missing(tmp_path,
                                                                         monkeypatch):
    """Nothing solved is lost: a rerun reads every chunk from OUT/fields (no solve), and with
    one chunk file gone solves that chunk alone, to the same numbers."""
    import solderpyro.predict.forward as fw

    _run_dir(tmp_path / "run", n=4)
    first = predict(tmp_path / "run", n_draws=4, out=tmp_path / "p", chunk=2, progress=False)
    chunks = sorted((tmp_path / "p" / "fields").glob("chunk-*.npz"))
    assert len(chunks) == 2
    def no_solve(*args):
        raise AssertionError("solved again")

    with monkeypatch.context() as mp:
        mp.setattr(fw, "solve_fields", no_solve)
        again = predict(tmp_path / "run", n_draws=4, out=tmp_path / "p", chunk=2,
                        progress=False)
    np.testing.assert_array_equal(again.fields.work, first.fields.work)
    kept = chunks[1].stat().st_mtime_ns
    chunks[0].unlink()
    third = predict(tmp_path / "run", n_draws=4, out=tmp_path / "p", chunk=2, progress=False)
    assert chunks[0].is_file() and chunks[1].stat().st_mtime_ns == kept
    np.testing.assert_allclose(third.fields.work, first.fields.work, rtol=1e-12, atol=0)


def test_the_die_attach_under_jedec_cycles_leaves_the_specimens_effects_out(tmp_path):
    """The shipped die attach (Si / solder / Cu, plane strain) under three -40/125 degC
    cycles: the chamber's thermal lag stays with the calibration (a note says so), the
    solder's modulus law carries over, the temperatures below the calibration's 25 degC are
    named, and the hysteresis has stabilised by the third cycle (its work within 2 % of the
    second's: 0.03-0.5 % at Liu's constants, docs/assemblies.md)."""
    _run_dir(tmp_path / "run", effects=("thermal_lag", "modulus_temperature"),
             extra_cols=((60.0, 90.0), (0.0, 0.0), (0.002, 0.004), (0.0, 0.0), (0.01, 0.01)),
             n=3)
    pred = predict(tmp_path / "run", ["specimen=die_attach", "mesh=die_attach",
                                      "loading=jedec_m40_125"],
                   n_draws=3, out=tmp_path / "p", points={}, progress=False)
    assert pred.target.transfer
    assert pred.target.effects == ("modulus_temperature",)
    assert pred.target.names == ("s0", "QR", "xi", "m", "k_E", "n_E", "r_E")
    assert any("thermal_lag" in n and "left out" in n for n in pred.notes)
    assert any("-40" in n and "leave the range" in n for n in pred.notes)
    assert pred.temperature["target"] == (-40.0, 125.0)
    assert len(pred.cycle_ends) == 3
    w = pred.per_cycle[("dW", "upper_interface")]
    assert np.all(np.abs(w[:, 2] / w[:, 1] - 1) < 0.02)
    # three draws cannot split the band between six parameters
    assert np.isnan(pred.bands[("dW", "upper_interface", 3)].constants_share)


def test_another_alloy_is_refused_naming_both(tmp_path):
    """A target whose materials file names another alloy: a ValueError naming both."""
    cfg = tmp_path / "conf" / "materials"
    cfg.mkdir(parents=True)
    from importlib.resources import files

    text = (files("solderpyro") / "conf" / "materials" / "table3.yaml").read_text()
    (cfg / "other.yaml").write_text(text.replace("name: Sn37Pb", "name: SAC305"))
    from solderpyro.config.compose import config_dir_override

    _run_dir(tmp_path / "run", n=2)
    with pytest.raises(ValueError, match="Sn37Pb.*SAC305"):
        predict(tmp_path / "run", [config_dir_override(tmp_path / "conf"), "materials=other"],
                n_draws=2, out=tmp_path / "p", progress=False)


def test_the_constants_share_of_a_known_split():
    """q = x + y/2 with x (a constant) and y (an effect's parameter) independent, equally
    spread: the constants' share of Var q is 1/(1 + 1/4) = 0.8; with 4000 draws the estimate's
    sampling error is ~0.01 (delta method on two variances), bound 0.03. No other column:
    1 exactly."""
    rng = np.random.default_rng(1)
    x, y = rng.uniform(size=(2, 4000))
    assert abs(constants_share(x + 0.5 * y, x[:, None], y[:, None]) - 0.8) < 0.03
    assert constants_share(x ** 2, x[:, None], np.zeros((4000, 0))) == 1.0


def test_regions_are_fixed_thickness_interface_layers_and_the_joint():
    """Rows of 0.1, 0.1 and 0.2 mm between y = 0 and 0.4 mm, three columns: the 0.1 mm layers
    (a quarter of the joint) are the bottom row and nothing at the top (its row is thicker:
    the row is then the layer); a 0.2 mm layer takes two rows at the bottom."""
    el_y = np.array([[0.0, 0.1]] * 3 + [[0.1, 0.2]] * 3 + [[0.2, 0.4]] * 3)
    up, low, joint = regions(el_y, 0.0, 0.4, 4)
    assert up.mask[:, 0].tolist() == [False] * 6 + [True] * 3
    assert up.thickness_mm == pytest.approx(0.2, rel=1e-12) and "200 um" in up.label
    assert low.mask[:, 0].tolist() == [True] * 3 + [False] * 6
    assert low.thickness_mm == pytest.approx(0.1, rel=1e-12)
    assert joint.mask.all()
    _, low2, _ = regions(el_y, 0.0, 0.4, 4, layer_mm=0.2)
    assert low2.mask[:, 0].tolist() == [True] * 6 + [False] * 3


def test_the_command_line_checks_its_arguments(tmp_path, capsys):
    from solderpyro.cli import main

    assert main(["predict", str(tmp_path), "--draws", "3"]) == 2
    assert "run.json" in capsys.readouterr().err
    _run_dir(tmp_path / "run", n=2)
    assert main(["predict", str(tmp_path / "run"), "--draws", "0"]) == 2
    assert main(["predict", str(tmp_path / "run"), "--point", "a=1"]) == 2
    assert main(["predict", str(tmp_path / "run"), "specimen=nope"]) == 2


@pytest.mark.timeout(300)
@pytest.mark.usefixtures("keep_environment")
def test_on_dask_workers_the_chunks_and_their_fields_are_the_same(tmp_path):
    """With ``--cluster local:2`` each chunk is one Dask task; the fields equal the
    in-process ones (each member is solved independently of its batch, ~1e-15 relative;
    bound 1e-10 of the largest work density)."""
    pytest.importorskip("distributed")
    from solderpyro.compute.executor import DaskExecutor, use_executor

    _run_dir(tmp_path / "run", n=2)
    here = predict(tmp_path / "run", n_draws=2, out=tmp_path / "a", chunk=1, progress=False)
    with DaskExecutor.start("local:2") as ex, use_executor(ex):
        there = predict(tmp_path / "run", n_draws=2, out=tmp_path / "b", chunk=1,
                        progress=False)
    assert len(list((tmp_path / "b" / "fields").glob("chunk-*.npz"))) == 2
    tol = 1e-10 * float(np.nanmax(here.fields.work))
    np.testing.assert_allclose(there.fields.work, here.fields.work, rtol=0, atol=tol)
    np.testing.assert_array_equal(there.fields.theta, here.fields.theta)
