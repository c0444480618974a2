"""The diagnosis's FE runs through the run store (:class:`solderpyro.specimen.SpecimenModels`,
one :class:`~solderpyro.specimen.SpecimenModel` per configuration): stored runs are read back,
duplicates solved once, every solve counted; and the stage costs."""

import json
import logging

import numpy as np
import torch

from solderpyro.compute.runstore import RunStore, config_hash
from solderpyro.config.compose import build, compose
from solderpyro.diagnose.costs import STAGES, Costs
from solderpyro.diagnose.write import cost_lines
from solderpyro.effects import effect_set
from solderpyro.specimen import SpecimenModel, SpecimenModels

TINY = ["experiment=quick", "loading.times_s=[0,600,900,1500]",
        "loading.temps_C=[25,75,75,25]", "loading.output_times=[600,900,1500]"]
TIMES = (600.0, 900.0, 1500.0)


def test_fe_runs_through_the_store(tmp_path):
    setup = build(compose(TINY))
    fx = effect_set(("thermal_lag",), TIMES, setup.effect_bounds)
    # s0, QR, xi, m, then thermal_lag's tau (s) and split
    theta = torch.tensor([[12.92, 10586.0, 2.04, 0.1, 0.0, 0.0],
                          [13.5, 10400.0, 2.1, 0.12, 30.0, 0.25],
                          [12.92, 10586.0, 2.04, 0.1, 0.0, 0.0]], dtype=torch.float64)
    store = RunStore(tmp_path / "store")
    fe = SpecimenModels(setup, store, batch_size=2)
    a = fe.runs(theta, TIMES, False, fx)
    assert (fe.computed, fe.reused) == (2, 1)  # the duplicate row is solved once
    assert a.V.shape == (3, 3, 2) and a.ok.all() and a.times == TIMES
    np.testing.assert_array_equal(a.V[0].numpy(), a.V[2].numpy())
    # registered with the effects switched on, as the calibration registers its own runs
    h = config_hash(setup.problem, TIMES, False, setup.dtype, effects=fx)
    assert len(store.records(h)) == 2
    assert json.loads((store.root / h / "meta.json").read_text())["inputs"]["effects"]
    again = SpecimenModels(setup, store)
    b = again.runs(theta, TIMES, False, fx)
    assert (again.computed, again.reused) == (0, 3)
    np.testing.assert_array_equal(a.V.numpy(), b.V.numpy())
    # without a store: the same values, all computed
    direct = SpecimenModels(setup)
    c = direct.runs(theta[:2], TIMES, False, fx)
    assert (direct.computed, direct.reused) == (2, 0)
    np.testing.assert_allclose(c.V.numpy(), a.V[:2].numpy(), rtol=1e-10, atol=1e-12)
    # one model per configuration: the same times and effects give the same model
    assert again.get(TIMES, False, fx) is again.get(tuple(reversed(TIMES)), False, fx)


def test_observation_effects_share_the_fe_run(tmp_path):
    """Rows that differ only in an observation-side effect's parameters (Moire offsets) are one
    FE run, stored under the FE-side effects only (as the calibration stores its runs); the
    outputs equal the solver's with every effect on."""
    from solderpyro.fem.solver import SpecimenSolver

    setup = build(compose(TINY))
    fx = effect_set(("moire_rigid_motion", "thermal_lag"), TIMES, setup.effect_bounds)
    base = [12.92, 10586.0, 2.04, 0.1, *([0.0] * 6), 20.0, 0.25]  # ..., tau, split
    shifted = list(base)
    shifted[4] = 0.2  # moire_c_1: the 600 s image
    theta = torch.tensor([base, shifted], dtype=torch.float64)
    # the reference solver applies every effect itself: its rows are the Anand constants
    # (the model's solver rows without effects), then every effect's parameters
    k = setup.space.n_theta
    rows = torch.cat([SpecimenModel(setup.problem, setup.space).solver_rows(theta[:, :k]),
                      theta[:, k:]], 1)
    store = RunStore(tmp_path / "store")
    fe = SpecimenModels(setup, store)
    out = fe.runs(theta, TIMES, False, fx)
    assert (fe.computed, fe.reused) == (1, 1)
    dV = (out.V[1] - out.V[0]).numpy()
    np.testing.assert_allclose(dV[0], 0.2, rtol=0, atol=1e-12)
    np.testing.assert_allclose(dV[1:], 0.0, rtol=0, atol=1e-12)
    lag = effect_set(("thermal_lag",), TIMES, setup.effect_bounds)
    assert len(store.records(config_hash(setup.problem, TIMES, False, setup.dtype,
                                         effects=lag))) == 1
    ref = SpecimenSolver(setup.problem, dtype=setup.dtype, effects=fx).solve(rows, TIMES)
    np.testing.assert_allclose(out.V.numpy(), ref.V.numpy(), rtol=1e-10, atol=1e-10)


def test_candidates_at_off_are_left_out_of_a_row(tmp_path, monkeypatch):
    """``runs(..., keep=k)`` solves each row with the first ``k`` effects and only the later
    ones it switches on: the outputs equal those of one solve with every effect on (an effect
    at "off" changes nothing: the difference is round-off, ~1e-13 um on 16 um displacements of
    the reference case, bounded here by 1e-10 um), and the rows are stored under the effects
    each switched on."""
    setup = build(compose(TINY))
    fx = effect_set(("thermal_lag", "stress_free_temperature", "kinematic_hardening"), TIMES,
                    setup.effect_bounds)
    off = list(fx.off)
    a = [12.92, 10586.0, 2.04, 0.1]
    sf = list(off)
    sf[fx.names.index("T_sf")] = 120.0  # degC
    kin = list(off)
    kin[fx.names.index("C_k")] = 800.0  # MPa
    theta = torch.tensor([a + off, a + sf, a + kin, [13.5, 10400.0, 2.1, 0.12] + off],
                         dtype=torch.float64)
    theta[:, 4] = 30.0  # the kept effect (tau, s) on in every row
    import solderpyro.specimen.model as model_mod

    store = RunStore(tmp_path / "store")
    fe = SpecimenModels(setup, store)
    monkeypatch.setattr(model_mod, "POOL_ROWS", 1)  # every group its own solve
    pruned = fe.runs(theta, TIMES, False, fx, keep=1)
    assert pruned.ok.all() and fe.computed == 4
    assert len(fe.models) == 3  # the lag alone; with the stress-free temperature; with C_k
    full = SpecimenModels(setup).runs(theta, TIMES, False, fx)
    np.testing.assert_allclose(pruned.V.numpy(), full.V.numpy(), rtol=0, atol=1e-10)
    # small groups pooled: one solve with every effect any of them switches on
    monkeypatch.setattr(model_mod, "POOL_ROWS", 16)
    pooled_fe = SpecimenModels(setup)
    pooled = pooled_fe.runs(theta, TIMES, False, fx, keep=1)
    assert len(pooled_fe.models) == 1 and pooled_fe.computed == 4
    np.testing.assert_allclose(pooled.V.numpy(), full.V.numpy(), rtol=0, atol=1e-10)
    lag = effect_set(("thermal_lag",), TIMES, setup.effect_bounds)
    assert len(store.records(config_hash(setup.problem, TIMES, False, setup.dtype,
                                         effects=lag))) == 2
    # the state at "off" matters: a candidate moved off its baseline is solved with it
    assert not np.allclose(pruned.V[1].numpy(), pruned.V[0].numpy(), atol=1e-3)


def test_stage_costs(caplog):
    class Counter:
        computed, reused = 0, 0

    cost = Costs()
    with caplog.at_level(logging.INFO, logger="solderpyro"):
        with cost.stage("load"):
            pass
        cost.fe = Counter()  # type: ignore[assignment]
        with cost.stage("fe_jacobians"):
            Counter.computed, Counter.reused = 7, 2
        with cost.stage("profile_refits"):
            Counter.computed, Counter.reused = 10, 9
    t = cost.table()
    assert list(t) == ["load", "fe_jacobians", "profile_refits", "total"]
    assert (t["fe_jacobians"]["fe_runs"], t["fe_jacobians"]["fe_reused"]) == (7, 2)
    assert (t["profile_refits"]["fe_runs"], t["profile_refits"]["fe_reused"]) == (3, 7)
    assert (t["total"]["fe_runs"], t["total"]["fe_reused"]) == (10, 9)
    assert t["total"]["seconds"] >= sum(t[k]["seconds"] for k in STAGES if k in t) - 1e-2
    assert sum(STAGES["fe_jacobians"] in r.getMessage() for r in caplog.records) == 1
    md = "\n".join(cost_lines(t))
    assert "| **total** |" in md and STAGES["profile_refits"] in md
