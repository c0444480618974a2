"""benchmarks/forms.py: the hidden forms are what they say, inside or outside the library's
families (the lag cascade against the library's closed forms, one parameter per form)."""

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import pytest  # noqa: E402
from forms import FORMS, LagCascade, ModulusLinear, cascade_lag  # noqa: E402

from solderpyro.effects.thermal_lag import lag  # noqa: E402
from solderpyro.fem.loading import REFERENCE_CYCLE  # noqa: E402

F64 = torch.float64
TIMES = (100.0, 600.0, 1500.0, 4700.0, 7000.0, 7800.0)
TAU = torch.tensor([0.0, 60.0, 250.0], dtype=F64)
RATE = 5.0 / 60.0  # K/s, the reference cycle's ramps


def test_the_matrix_exponential_cascade_is_the_library_lag_at_one_and_two_stages():
    """One stage is the library's first-order lag, two equal stages its split = 1/2 (and
    the benchmark's second-order form): 1e-11 of r tau (the matrix exponential's rounding
    over the cycle's segments, ~1e-12 of it measured)."""
    C = REFERENCE_CYCLE
    half = torch.full_like(TAU, 0.5)
    for t in TIMES:
        one, two = cascade_lag(C, t, TAU, 1), cascade_lag(C, t, TAU, 2)
        tol = 1e-11 * RATE * float(TAU.max())
        assert (one - lag(C, t, TAU)).abs().max() <= tol, t
        assert (two - lag(C, t, TAU, half)).abs().max() <= tol, t
        form = LagCascade(stages=2).temperature(torch.zeros_like(TAU), t, C, TAU[:, None])
        assert (form + two).abs().max() <= tol, t
        assert one[0] == 0 and two[0] == 0


def test_three_stages_are_outside_the_two_stage_family():
    """Settled on a ramp, every cascade trails by r tau; early in the first ramp three equal
    stages lag more than any split of two (the lag is r E[min(D, t)] with D the cascade's
    delay, larger when D varies less), by more than 0.1 K at tau = 250 s."""
    C = REFERENCE_CYCLE
    tau = torch.tensor([250.0], dtype=F64)
    three = cascade_lag(C, 60.0, tau, 3).item()
    splits = torch.linspace(0.0, 0.5, 51, dtype=F64)
    best_two = lag(C, 60.0, tau.expand(51), splits).max().item()
    assert three > best_two + 0.1, (three, best_two)
    settled = cascade_lag(C, 7800.0, torch.tensor([20.0], dtype=F64), 3).item()
    assert abs(settled + RATE * 20.0) < 1e-9  # cooling: the specimen is r tau above


def test_every_form_has_one_parameter_its_size():
    """Each form carries its size alone (its truth); the library's form parameters have no
    truth in a form's data and are not counted."""
    for name, (eff, library, fixed) in FORMS.items():
        n = 2 if library == "stress_free_temperature" else 1  # T_sf and its cool-down
        assert eff.params.dim == n, name
        assert fixed is None or len(fixed) == n, name


def test_a_form_keeps_its_size_alone_whatever_box_the_config_gives():
    """The config's box of the library effect names its form parameters too: a form takes the
    bounds of its own parameter and drops the library's form parameters (a misspelt name
    still raises); its check is the library's, on the size, the form parameters at "off"."""
    lag2 = LagCascade(stages=2).with_box({"tau": (0.0, 400.0), "split": (0.0, 0.5)})
    assert lag2.params.names == ("tau",) and lag2.params.upper == (400.0,)
    assert lag2.off == (0.0,)
    with pytest.raises(ValueError, match="tau must be >= 0"):
        lag2.check(torch.tensor([[-1.0]], dtype=F64))
    lag2.check(torch.tensor([[120.0]], dtype=F64))
    mod = ModulusLinear().with_box({"k_E": (0.0, 0.01), "n_E": (0.0, 1.0)})
    assert mod.params.names == ("k_E",) and mod.params.units == ("1/K",)
    with pytest.raises(ValueError, match="no parameter 'k'"):
        ModulusLinear().with_box({"k": (0.0, 0.01)})


def test_the_armstrong_frederick_form_is_the_library_at_its_fixed_recovery():
    """kinematic_af is sized by C_k alone; its hooks are the library's at gamma_k = 50 (the
    library's default form, Prager, is gamma_k = 0: its data need the form moved), and through
    the FE (a small specimen, a 25 -> 75 degC cycle) the form at C_k = 1000 MPa equals the
    library at (1000, 50) bit for bit (the same operations) and differs from Prager by
    > 1e-3 um (0.003 um measured on this short cycle; ~0.2 um on the reference cycle)."""
    from forms import KinematicAF  # noqa: PLC0415

    from solderpyro.effects import EFFECTS  # noqa: PLC0415
    from solderpyro.fem.loading import ThermalCycle, TimeStepping  # noqa: PLC0415
    from solderpyro.fem.mesh import Layer, MeshSpec  # noqa: PLC0415
    from solderpyro.fem.problem import Problem  # noqa: PLC0415
    from solderpyro.fem.solver import SpecimenSolver  # noqa: PLC0415
    from solderpyro.params import anand_tensor  # noqa: PLC0415

    eff, library, fixed = FORMS["kinematic_af"]
    lib = EFFECTS[library]
    assert isinstance(eff, KinematicAF) and fixed is None
    assert eff.params.names == ("C_k",) and eff.off == (0.0,) and eff.gamma_k == 50.0
    q = torch.tensor([[0.0], [300.0], [2000.0]], dtype=F64)
    ql = torch.cat([q, torch.full_like(q, 50.0)], 1)
    assert torch.equal(eff.back_stress_modulus(None, q), lib.back_stress_modulus(None, ql))
    assert torch.equal(eff.back_stress_recovery(None, q), lib.back_stress_recovery(None, ql))
    assert eff.with_box({"C_k": (0.0, 1000.0), "gamma_k": (0.0, 200.0)}).params.names == ("C_k",)
    with pytest.raises(ValueError, match="C_k must be >= 0 MPa"):
        eff.check(torch.tensor([[-1.0]], dtype=F64))
    prob = Problem(layers=(Layer("copper", "copper", -4.0, 0.0, 4, 0.25, "top"),
                           Layer("solder", "solder", 0.0, 0.5, 2),
                           Layer("steel", "steel", 0.5, 4.5, 4, 0.25, "bottom")),
                   mesh=MeshSpec(nx=10), cycle=ThermalCycle((0.0, 600.0, 1500.0),
                                                            (25.0, 75.0, 75.0)),
                   stepping=TimeStepping(dT_max=10.0, dwell_dt0=20.0, dt_max=450.0))
    anand = anand_tensor(dtype=F64)[None]
    times = (600.0, 1500.0)
    V_form = SpecimenSolver(prob, effects=(eff,)).solve(
        torch.cat([anand, torch.tensor([[1000.0]], dtype=F64)], 1), times).V
    V_lib = [SpecimenSolver(prob, effects=(lib,)).solve(
        torch.cat([anand, torch.tensor([[1000.0, g]], dtype=F64)], 1), times).V[0]
        for g in (50.0, 0.0)]  # single-member solves, as the form's (batches round apart)
    assert torch.equal(V_form[0], V_lib[0])
    assert (V_lib[0] - V_lib[1]).abs().max() > 1e-3


def test_a_recalibration_rerun_twice_keeps_the_commit_its_reused_stages_ran_at(tmp_path,
                                                                                 monkeypatch):
    """forms_benchmark.run with an earlier record (``--recalibrate``) keeps that record's base
    and diagnosis seconds and says where they ran: the earlier record's commit, or, where that
    record reused them in turn, the commit it names."""
    import diagnosis_cases
    import forms_benchmark as fb

    monkeypatch.setattr(fb, "make_data", lambda case, path: 0.0)
    monkeypatch.setattr(diagnosis_cases, "run_case",
                        lambda *a, **k: {"case": "x", "wall_s": {"recalibrate": 5.0}})
    monkeypatch.setenv("BENCH_COMMIT", "ccc")
    case = fb.Case("x", (), "truth", 1)
    first = fb.run(case, str(tmp_path), {"commit": "aaa",
                                         "wall_s": {"calibrate": 1.0, "diagnose": 2.0}})
    assert first["commit"] == "ccc" and first["reused"]["commit"] == "aaa"
    again = fb.run(case, str(tmp_path), first)
    assert again["reused"] == {"stages": ["calibrate", "diagnose"], "commit": "aaa"}
    assert again["wall_s"] == {"calibrate": 1.0, "diagnose": 2.0, "recalibrate": 5.0}
