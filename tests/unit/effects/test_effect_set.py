"""Contract tests of the physical effects (solderpyro.effects): registry, off == baseline,
batch invariance with mixed effect values, gradients against finite differences, and the
config / run-store / model surfaces."""

import dataclasses
import json

import pytest
import torch

from solderpyro.compute.executor import InProcess
from solderpyro.compute.runstore import RunRecord, RunStore, config_hash, param_hash
from solderpyro.compute.store import DoeOptions, run_doe
from solderpyro.config.compose import build, compose
from solderpyro.effects import EFFECTS, Effect, EffectSet, effect_box, effect_set, get_effect
from solderpyro.fem.loading import SEED_TIMES, ThermalCycle, TimeStepping
from solderpyro.fem.mesh import Layer, MeshSpec
from solderpyro.fem.problem import Problem
from solderpyro.fem.solver import SpecimenSolver
from solderpyro.params import ANAND_NAMES, ParameterSpace, anand_tensor
from solderpyro.specimen import SpecimenModel

CONTRACT = ("modulus_temperature", "stress_free_temperature", "thermal_lag", "cte_temperature",
            "moire_rigid_motion", "kinematic_hardening", "copper_plasticity")
SHORT = ThermalCycle((0.0, 600.0, 1500.0), (25.0, 75.0, 75.0))
LAYERS = (Layer("copper", "copper", -4.0, 0.0, 4, 0.25, "top"),
          Layer("solder", "solder", 0.0, 0.5, 2),
          Layer("steel", "steel", 0.5, 4.5, 4, 0.25, "bottom"))
STEP = TimeStepping(dT_max=10.0, dwell_dt0=20.0, dt_max=450.0)
TIMES = (600.0, 1500.0)
F64 = torch.float64
#: an interior point of each effect's box (and of moire's first offset and second rotation);
#: k_E and tau large enough that their form parameters move the small problem's V measurably
#: (n_E, r_E, split: |dy| ~ 4e-2, 1e-1 per unit, > 3x the gradient test's "acts" bound; at
#: k_E = 3e-3, tau = 60 s they moved it by ~2e-3, below that bound); gamma_k = 100 recovers a
#: visible part of the C_k = 500 MPa back stress
INTERIOR = {"modulus_temperature": [1e-2, 0.6, 0.3],
            "stress_free_temperature": [120.0, 3000.0, 2.0], "thermal_lag": [200.0, 0.3],
            "cte_temperature": [1.5e-3, 0.5],
            "moire_rigid_motion": [0.3, -0.2, 20.0, -10.0], "kinematic_hardening": [500.0, 100.0],
            "copper_plasticity": [10.0]}


def small_problem(**kw):
    kw.setdefault("stepping", STEP)
    return Problem(layers=LAYERS, mesh=MeshSpec(nx=10), cycle=SHORT, **kw)


def with_anand(q, anand=None):
    """``(b, 9 + n)`` from effect values ``q`` ``(b, n)`` and the Liu constants."""
    q = torch.as_tensor(q, dtype=F64)
    return torch.cat([anand_tensor(anand, dtype=F64)[None].expand(q.shape[0], -1), q], 1)


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def baseline():
    """The baseline model at Liu's constants (module scope: set up before the float64 default
    of conftest, hence the explicit dtype)."""
    return SpecimenSolver(small_problem()).solve(anand_tensor(dtype=F64)[None], TIMES).V


# ------------------------------------------------------------------ registry and boxes

def test_registry_contract():
    """Every effect: a registered name, a Box with units, an off value inside the box, parameter
    names that clash with no Anand constant, and JSON-able settings."""
    assert set(CONTRACT) <= set(EFFECTS)
    for name, eff in EFFECTS.items():
        assert isinstance(eff, Effect) and eff.name == name and get_effect(name) is eff
        b = eff.params
        assert len(eff.off) == b.dim and all(u for u in b.units)
        assert all(lo <= v <= hi for v, lo, hi in zip(eff.off, b.lower, b.upper, strict=True))
        assert not set(b.names) & set(ANAND_NAMES)
        json.dumps(eff.settings())
    with pytest.raises(ValueError, match="valid effects: .*thermal_lag"):
        get_effect("thermal_lagg")


def test_effect_set_columns_and_binding_to_times():
    fx = EffectSet(["thermal_lag", "moire_rigid_motion", "cte_temperature"]).bind([900.0, 600.0])
    assert fx.names == ("tau", "split", "moire_c_1", "moire_c_2", "moire_w_1", "moire_w_2",
                        "c_alpha", "n_alpha")
    assert fx.off == (0.0,) * 7 + (1.0,) and fx.n_params == 8
    q = torch.arange(16.0).reshape(2, 8)
    assert [t.shape[1] for t in fx.split(q)] == [2, 4, 2]
    assert fx.box.units == ("s", "-", "um", "um", "urad", "urad", "1/K", "-")
    with pytest.raises(ValueError, match="listed twice"):
        EffectSet(["thermal_lag", "thermal_lag"])
    with pytest.raises(ValueError, match="tau must be >= 0"):
        EffectSet(["thermal_lag"]).check(torch.tensor([[-1.0, 0.0]]))


def test_box_overrides_and_errors():
    b = effect_box(["thermal_lag", "moire_rigid_motion"], SEED_TIMES,
                   {"thermal_lag": {"tau": (0.0, 120.0)}, "moire_rigid_motion": {"c": (-2, 2)}})
    assert b.upper[0] == 120.0 and b.upper[1] == 0.5  # split keeps its default box
    assert b.lower[2:6] == (-2.0,) * 4 and b.upper[6:] == (50.0,) * 4
    with pytest.raises(ValueError, match="no parameter 'taux'; valid: tau, split"):
        EFFECTS["thermal_lag"].with_box({"taux": (0, 1)})
    with pytest.raises(ValueError, match="lower 5 must be < upper 1"):
        EFFECTS["thermal_lag"].with_box({"tau": (5, 1)})
    with pytest.raises(ValueError, match="box keys c .* and w"):
        EFFECTS["moire_rigid_motion"].with_box({"moire_c_1": (0, 1)})
    with pytest.raises(ValueError, match="unknown effect 'nope'"):
        effect_box(["thermal_lag"], None, {"nope": {}})


# ------------------------------------------------------------------ (a) off == baseline

@pytest.mark.parametrize("name", CONTRACT)
def test_off_value_gives_the_baseline(name, baseline):
    """The off value reproduces the baseline model to 1e-12 of max|V| (rounding only: the
    effect's terms at their off value are exact zeros or ones; bit-identical measured)."""
    solver = SpecimenSolver(small_problem(), effects=(name,))
    off = EFFECTS[name].bind(TIMES).off
    V = solver.solve(with_anand([off]), TIMES).V
    err = (V - baseline).abs().max().item()
    assert err <= 1e-12 * baseline.abs().max().item(), (name, err)


# ------------------------------------------------------------------ (b) batch invariance

def test_batch_invariance_with_mixed_effect_values(baseline):
    """All effects on at once, each member with its own values (one all-off): every member of
    the batch equals its single run to 1e-11 of max|V|, and the all-off member is the
    baseline to 1e-12 of it (rounding only: a member's iterations do not depend on its batch,
    ~1 ulp of max|V| measured; a member that saw another's values would be off by far more)."""
    names = CONTRACT
    solver = SpecimenSolver(small_problem(), effects=names)
    fx = EffectSet(names).bind(TIMES)
    g = torch.Generator().manual_seed(3)
    lo, hi = fx.box.bounds(dtype=torch.float64)
    q = torch.cat([torch.tensor([fx.off]), lo + (hi - lo) * torch.rand(2, fx.n_params,
                                                                        generator=g)])
    P = with_anand(q)
    P[2, :9] = anand_tensor({"s0": 9.0, "xi": 3.0, "m": 0.1}, dtype=F64)  # another material, too
    batch = solver.solve(P, TIMES)
    assert bool(batch.ok.all())
    vmax = baseline.abs().max().item()
    assert (batch.V[0] - baseline[0]).abs().max() <= 1e-12 * vmax
    for i in range(1, len(P)):
        single = solver.solve(P[i:i + 1], TIMES).V[0]
        tol = 1e-11 * single.abs().max().item()
        assert torch.allclose(batch.V[i], single, rtol=0, atol=tol), (i, batch.V[i] - single)
        assert (batch.V[i] - baseline[0]).abs().max() > 0.1  # the members really differ


def test_batch_invariance_with_back_stress_and_yielding_copper(baseline):
    """kinematic_hardening and copper_plasticity together, members on both discretisations
    (off copper: baseline path; yielding copper, 10-12 MPa: banded) and with back stress: every
    member equals its single run to 1e-11 of max|V|, the all-off member is the baseline to
    1e-12 of it (batched products round differently; its single run is bit-identical, see the
    off test), and the copper really yields (V moves by > 0.01 um)."""
    solver = SpecimenSolver(small_problem(), effects=("kinematic_hardening", "copper_plasticity"))
    P = with_anand([[0.0, 0.0, 400.0], [800.0, 60.0, 400.0], [0.0, 0.0, 10.0],
                    [1500.0, 150.0, 12.0]])  # C_k, gamma_k, sigma_y_cu
    P[3, :9] = anand_tensor({"s0": 9.0, "xi": 3.0, "m": 0.1}, dtype=F64)
    batch = solver.solve(P, TIMES)
    vmax = baseline.abs().max().item()
    assert bool(batch.ok.all()) and (batch.V[0] - baseline[0]).abs().max() <= 1e-12 * vmax
    for i in range(1, len(P)):
        single = solver.solve(P[i:i + 1], TIMES).V[0]
        tol = 1e-11 * single.abs().max().item()
        assert torch.allclose(batch.V[i], single, rtol=0, atol=tol), (i, batch.V[i] - single)
    assert (batch.V[2] - baseline[0]).abs().max() > 0.01


# ------------------------------------------------------------------ (c) gradients

#: columns checked (moire: its first offset and its last rotation) and their FD steps
FD_COLS = {"tau": 0.03, "split": 5e-5, "k_E": 5e-7, "n_E": 1e-4, "r_E": 5e-5, "T_sf": 0.016,
           "cooldown": 0.3, "cooldown_shape": 2e-4, "c_alpha": 3e-7, "n_alpha": 1e-4,
           "moire_c_1": 2e-4, "moire_w_2": 1e-2, "C_k": 0.2, "gamma_k": 0.02}
#: form parameters (Effect.nuisance): at the off values they change nothing, exactly
FORM_PARAMS = ("cooldown", "cooldown_shape", "n_E", "r_E", "split", "gamma_k", "n_alpha")
#: one-sided differences at the off value, which is the box's lower edge for these
ONE_SIDED = ("tau", "C_k", "n_E", "r_E", "split", "gamma_k", "cooldown_shape")
#: all effects but copper_plasticity, whose derivative at its off value is 0 (tested apart)
SMOOTH = tuple(k for k in CONTRACT if k != "copper_plasticity")


def test_effect_gradients_match_finite_differences():
    """Autograd through the FE w.r.t. every effect's parameter(s), at the off values and at an
    interior point (all effects on together), against finite differences in float64: central,
    except at tau = 0 (the box's edge; tau < 0 is not admissible), where a second-order
    one-sided difference gives the one-sided derivative a score test at the off value uses.
    A fixed random projection of the outputs is differentiated (one backward pass); a wrong
    component of the Jacobian would show in it. Steps ~1e-4 of each box width: the FD
    truncation error is then < 1e-7 relative and the Newton noise (rtol 1e-10) far smaller.
    C_k = 0 is the box's lower edge as tau = 0 (C_k < 0 is rejected): one-sided there, and so
    are the form parameters n_E, r_E, split and gamma_k, whose off value is their box's lower
    edge too; at the off row every form parameter (cooldown, n_E, r_E, split, gamma_k) must
    leave V bit for bit unchanged and have a zero autograd derivative (its effect is off), at
    the interior row it is checked like the others."""
    fx = EffectSet(SMOOTH).bind(TIMES)
    solver = SpecimenSolver(small_problem(), effects=fx)
    q = torch.tensor([fx.off, [v for k in SMOOTH for v in INTERIOR[k]]], dtype=F64)
    P = with_anand(q).requires_grad_(True)
    w = torch.tensor([0.8, -0.3, 0.5, 1.1], dtype=F64)  # projection of the 4 outputs
    y = solver.solve(P, TIMES).V.reshape(2, -1) @ w  # (2,)
    grad = torch.autograd.grad(y.sum(), P)[0]  # rows are independent members
    rows, meta = [P[0].detach().clone()], []  # row 0: f(0) for the one-sided differences,
    # from the same no-grad solve (the graph's correction step moves V by ~1e-11 um, which
    # 3/(2h) would amplify); the form parameters' off rows come first, next to row 0: members
    # late in a large batch may round differently (~5e-14 um measured at rows 36-44 of 45),
    # and their bit-for-bit check needs row 0's rounding
    cases = [(nm, i) for first in (True, False) for nm in FD_COLS for i in range(2)
             if ((nm in FORM_PARAMS and i == 0) == first)]
    for name, i in cases:
        h = FD_COLS[name]
        c = 9 + fx.names.index(name)
        for st in (1.0, 2.0) if name in ONE_SIDED and i == 0 else (1.0, -1.0):
            r = P[i].detach().clone()
            r[c] += st * h
            rows.append(r)
        meta.append((name, c, i, h))
    yall = solver.solve(torch.stack(rows), TIMES).V.reshape(len(rows), -1) @ w
    y0, yh = yall[0], yall[1:].reshape(-1, 2)
    for (name, c, i, h), (ya, yb) in zip(meta, yh, strict=True):
        if name in ONE_SIDED and i == 0:  # (-3 f(0) + 4 f(h) - f(2h)) / 2h
            fd = (-3.0 * y0 + 4.0 * ya - yb) / (2.0 * h)
        else:
            fd = (ya - yb) / (2.0 * h)
        g = grad[i, c]
        print(f"{name:10s} member {i}: autograd {g.item(): .9e}  FD {fd.item(): .9e}")
        if name in FORM_PARAMS and i == 0:  # a form parameter does nothing where its effect
            assert ya == y0 and yb == y0    # is off (T_sf = 25: no cool-down to shape; k_E = 0:
            assert fd == 0.0 and g == 0.0   # no softening; tau = 0: no lag; C_k = 0: no back
            continue                        # stress to recover), bit for bit
        assert fd.abs() > 1e-6 * abs(1.0 / h)  # the effect acts (not a 0 == 0 check)
        assert torch.allclose(g, fd, rtol=1e-5, atol=0.0), (name, i, g, fd)


def test_copper_plasticity_gradient_matches_finite_differences():
    """d(V)/d(sigma_y_cu) through the banded FE (J2 return, local mode solve, global implicit
    correction) against central differences at 10 MPa, where the small problem's copper yields
    (its largest elastic von Mises stress is ~16 MPa). Rate-independent plasticity makes V
    piecewise smooth in sigma_y (a point switching between elastic and plastic in some step
    is a kink), so the step must not straddle a switch: h = 2.5e-3 MPa agrees with autograd to
    ~1e-8 (h = 0.04 MPa: 5e-5, h = 0.2 MPa: 2e-2, all converging to the autograd value). At
    the off value (400 MPa, the baseline path) the derivative is exactly 0, and so is the
    one-sided difference towards the banded path up to the Newton tolerance."""
    solver = SpecimenSolver(small_problem(), effects=("copper_plasticity",))
    P = with_anand([[400.0], [10.0]]).requires_grad_(True)
    w = torch.tensor([0.8, -0.3, 0.5, 1.1], dtype=F64)
    y = solver.solve(P, TIMES).V.reshape(2, -1) @ w
    g = torch.autograd.grad(y.sum(), P)[0][:, 9]
    h, h0 = 2.5e-3, 0.04
    rows = P.detach()[[0, 0, 0, 1, 1]].clone()
    rows[:, 9] += torch.tensor([0.0, -h0, -2.0 * h0, h, -h], dtype=F64)
    yh = solver.solve(rows, TIMES).V.reshape(5, -1) @ w
    fd0 = -(-3.0 * yh[0] + 4.0 * yh[1] - yh[2]) / (2.0 * h0)
    fd1 = (yh[3] - yh[4]) / (2.0 * h)
    print(f"off: autograd {g[0].item():.3e} FD {fd0.item():.3e}; 10 MPa: autograd "
          f"{g[1].item():.9e} FD {fd1.item():.9e}")
    assert g[0].item() == 0.0 and abs(fd0.item()) < 1e-6
    assert abs(fd1.item()) > 1e-3  # the copper yields: V depends on sigma_y
    assert torch.allclose(g[1], fd1, rtol=1e-6, atol=0.0), (g[1], fd1)


# ------------------------------------------------------------------ model, config, store

def test_model_theta_layout_and_names():
    space = ParameterSpace.seed()
    model = SpecimenModel(small_problem(), space, TIMES, effects=("thermal_lag",
                                                                   "moire_rigid_motion"))
    assert model.param_names == [*space.names, "tau", "split", "moire_c_1", "moire_c_2",
                                 "moire_w_1", "moire_w_2"]
    assert model.n_theta == 10 and model.effect_box.names == tuple(model.param_names[4:])
    theta = torch.tensor([[12.41, 9400.0, 1.5, 0.303, 30.0, 0.2, 0.1, 0.2, 5.0, -5.0]])
    V = model(theta)
    # the model's solver simulates the FE-side effect, the Moire offsets act after it: the
    # same operations as a solver with both on (which applies them to its own outputs)
    both = SpecimenSolver(small_problem(), effects=("thermal_lag", "moire_rigid_motion"))
    direct = both.solve(torch.cat([space.full(theta[:, :4]), theta[:, 4:]], 1), TIMES).V
    assert model.solver.param_names(TIMES) == [*ANAND_NAMES, "tau", "split"]
    assert V.shape == (1, 2, 2) and torch.equal(V, direct)
    with pytest.raises(ValueError, match=r"shape \(B, 10\) for s0, QR, xi, m, tau, split, "
                                         r"moire_c_1"):
        model(theta[:, :4])
    with pytest.raises(ValueError, match="tau must be >= 0"):
        model(torch.cat([theta[:, :4], -theta[:, 4:5], theta[:, 5:]], 1))


def test_config_effects_and_boxes():
    s = build(compose([]))
    assert s.effects == () and s.effect_box.dim == 0
    for name, box in s.effect_bounds.items():  # the config's boxes are the library defaults
        eff = EFFECTS[name]
        assert eff.with_box(box).params == eff.params, name
    s = build(compose(["effects=[thermal_lag,moire_rigid_motion]", "loading.output_times=extended",
                       "effect_box.thermal_lag.tau=[0,120]"]))
    assert s.effects == ("thermal_lag", "moire_rigid_motion")
    assert s.effect_box.names[0] == "tau" and s.effect_box.upper[0] == 120.0
    assert s.effect_box.names[1] == "split" and s.effect_box.upper[1] == 0.5
    assert s.effect_box.dim == 2 + 2 * 7
    with pytest.raises(ValueError, match="config effects: unknown effect 'lag'; valid effects: "
                                         "copper_plasticity, cte_temperature, .*thermal_lag"):
        build(compose(["effects=[lag]"]))
    with pytest.raises(ValueError, match="effect_box.thermal_lag: .*lower 9 must be < upper 1"):
        build(compose(["effect_box.thermal_lag.tau=[9,1]"]))


def test_store_hash_separates_effects_and_records_round_trip(tmp_path):
    pr = Problem()
    h0 = config_hash(pr, SEED_TIMES, False, torch.float64)
    assert h0 == config_hash(pr, SEED_TIMES, False, torch.float64, ())  # baseline unchanged
    h1 = config_hash(pr, SEED_TIMES, False, torch.float64, ("thermal_lag",))
    h2 = config_hash(pr, SEED_TIMES, False, torch.float64, ("thermal_lag", "cte_temperature"))
    h3 = config_hash(pr, SEED_TIMES, False, torch.float64,
                     (dataclasses.replace(EFFECTS["cte_temperature"], T0_C=30.0),))
    h4 = config_hash(pr, SEED_TIMES, False, torch.float64, ("stress_free_temperature",))
    assert len({h0, h1, h2, h3, h4}) == 5
    boxed = EFFECTS["thermal_lag"].with_box({"tau": (0.0, 60.0)})  # a prior is not an output
    assert config_hash(pr, SEED_TIMES, False, torch.float64, (boxed,)) == h1
    # a DOE with effect parameters: records carry them, and a rerun reuses them
    names = [*ANAND_NAMES, "tau", "split"]
    calls = []

    def fake(p, times):
        calls.append(len(p))
        V = p[:, 9, None, None].expand(-1, len(times), 2).clone()
        return type("R", (), {"V": V, "ok": torch.ones(len(p), dtype=torch.bool), "reasons": None,
                              "times": torch.tensor(times), "names": ["A", "B"]})()

    store = RunStore(tmp_path)
    h = store.register(pr, SEED_TIMES, False, torch.float64, ("thermal_lag",))
    assert store.meta(h)["inputs"]["effects"][0]["__dict__"]  # readable settings in meta.json
    P = with_anand([[0.0, 0.0], [30.0, 0.2], [30.0, 0.2]])
    r = run_doe(fake, store, h, P, SEED_TIMES, names,
                DoeOptions(progress=False, executor=InProcess(processes=1)))
    assert r.n_computed == 2 and r.V[1, 0, 0] == 30.0 and calls == [2]
    r = run_doe(fake, store, h, P, SEED_TIMES, names,
                DoeOptions(progress=False, executor=InProcess(processes=1)))
    assert r.n_reused == 3 and calls == [2]
    rec = store.get(h, P[1])
    assert isinstance(rec, RunRecord) and rec.params["tau"] == 30.0 and rec.values == P[1].tolist()
    assert rec.params["split"] == 0.2
    assert param_hash(P[1]) != param_hash(P[0]) and param_hash(P[0, :9]) != param_hash(P[0])
    with pytest.raises(ValueError, match=r"shape \(n, 11\)"):
        run_doe(fake, store, h, P[:, :10], SEED_TIMES, names, DoeOptions(progress=False))


def test_rebind_params_carries_each_image_to_its_time():
    """Moire c_k, w_k follow their image's time to a new set of output times (0 where an
    image was not observed); effects without per-time parameters pass through unchanged."""
    t0, t1 = (600.0, 2700.0), (600.0, 2400.0, 2700.0)
    fx = effect_set(("thermal_lag", "moire_rigid_motion"), t0)
    q = torch.tensor([[50.0, 0.3, 0.1, 0.2, 3.0, 4.0]])  # tau, split, c_1, c_2, w_1, w_2
    out = fx.rebind_params(q, t0, t1)
    fx1 = effect_set(("thermal_lag", "moire_rigid_motion"), t1)
    assert out.shape == (1, fx1.n_params)
    got = dict(zip(fx1.names, out[0].tolist(), strict=True))
    assert got == {"tau": 50.0, "split": 0.3, "moire_c_1": 0.1, "moire_c_2": 0.0, "moire_c_3": 0.2,
                   "moire_w_1": 3.0, "moire_w_2": 0.0, "moire_w_3": 4.0}
