"""Identifiability after the FE-exact posterior: which parameter lies along a ridge, the two
samples at its ends, and the measurement that would tell them apart
(pipeline.fe_exact.identifiability)."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from solderpyro.config.compose import build, compose
from solderpyro.diagnose.decide import APART_CHI2
from solderpyro.effects import effect_set
from solderpyro.exact.posterior import weighted_quantiles
from solderpyro.fem.problem import reference_grid
from solderpyro.fem.solver import SpecimenSolver
from solderpyro.io.measurements import from_arrays
from solderpyro.pipeline.fe_exact import identifiability, ridge_ends
from solderpyro.specimen import SpecimenModel, calibration_box

TINY = ["experiment=quick", "loading.times_s=[0,600,900]", "loading.temps_C=[25,75,75]",
        "loading.output_times=[600,900]"]
TIMES = (600.0, 900.0)


def test_ridge_ends_are_the_extremes_of_the_well_fitting_samples():
    """A ridge x1 = x0 in the unit square: the ends are the samples at the two ends of x0's
    95 % interval among those that fit at least as well as the weighted median sample; a
    sample far off the ridge (large ssr) is never chosen, however extreme its x0."""
    rng = np.random.default_rng(3)
    x = rng.uniform(0, 1, (4000, 2))
    ssr = 200.0 * (x[:, 1] - x[:, 0]) ** 2
    w = np.exp(-0.5 * ssr)
    w /= w.sum()
    x = np.vstack([x, [[0.001, 0.9]]])  # off the ridge, at the extreme of x0
    ssr, w = np.r_[ssr, 200.0 * 0.899**2], np.r_[w, 1e-30]
    i_lo, i_hi = ridge_ends(x, w / w.sum(), ssr, 0)
    lo, hi = weighted_quantiles(x[:, 0], w, (0.025, 0.975))
    med = weighted_quantiles(ssr, w, (0.5,))[0]
    assert i_lo != len(x) - 1
    for i in (i_lo, i_hi):
        assert ssr[i] <= med and lo <= x[i, 0] <= hi
    # the extremes of the qualifying samples: within 0.01 of the interval's ends (4000 samples)
    assert x[i_lo, 0] == pytest.approx(lo, abs=0.01) and x[i_hi, 0] == pytest.approx(hi, abs=0.01)
    with pytest.raises(ValueError, match="positive weight"):
        ridge_ends(x, np.zeros(len(x)), ssr, 0)


def _case(col: int, lo: float, hi: float, effects: tuple[str, ...] = (), n: int = 400):
    """The TINY case's point data (A, B at 600 and 900 s, Liu's constants) and a stand-in for
    an FE-exact posterior over the Anand constants and ``effects``' parameters (their box
    ``space``): column ``col`` uniform on ``[lo, hi]``, the other constants at Liu's, the
    effects off, every sample fitting equally well."""
    setup = build(compose(TINY + [f"effects=[{','.join(effects)}]"]))
    space = calibration_box(setup, effect_set(effects, TIMES) if effects else None)
    sol = SpecimenSolver(setup.problem)
    liu = np.array([setup.space.defaults[n] for n in setup.space.names], float)
    rows = SpecimenModel(setup.problem, setup.space).solver_rows(torch.tensor(liu[None]))
    V = sol.solve(rows, TIMES).V[0].numpy()
    pts = [setup.problem.points[k] for k in sol.names]
    meas = from_arrays(TIMES, list(sol.names), np.array(pts), V, sigma_um=0.05)
    X = np.zeros((n, space.dim))
    X[:, :len(liu)] = liu
    X[:, col] = np.random.default_rng(0).uniform(lo, hi, n)
    w = np.full(n, 1.0 / n)
    ex = SimpleNamespace(samples=X, result=SimpleNamespace(weights=lambda: w,
                                                           extra={"ssr": np.zeros(n)}))
    rows = []
    for k, nm in enumerate(space.names):
        q = weighted_quantiles(X[:, k], w, (0.025, 0.5, 0.975))
        rows.append({"parameter": nm, "q2.5": q[0], "median": q[1], "q97.5": q[2]})
    return setup, space, meas, ex, rows


def test_a_well_identified_posterior_flags_nothing_and_runs_no_fe():
    setup, space, meas, ex, rows = _case(0, 12.0, 13.0)
    info = identifiability(setup, (), space, rows, ex, meas, 0.05)
    assert info["weak"] == [] and "ends" not in info and "options" not in info
    with pytest.raises(ValueError, match="sigma"):
        identifiability(setup, (), space, rows, ex, meas, 0.0)


def test_a_weak_parameter_is_named_with_the_measurement_that_separates_its_ends():
    """s0 spread over [5.5, 24.5] MPa: weak (its 95 % interval, ~[6.0, 24.1], covers ~0.9 of
    the box); its ends' full-field V differs by what the FE, run independently at the two
    ends, says (to rounding)."""
    setup, space, meas, ex, rows = _case(0, 5.5, 24.5)
    info = identifiability(setup, (), space, rows, ex, meas, 0.05)
    assert [w["parameter"] for w in info["weak"]] == ["s0"]
    assert info["weak"][0]["share_of_box"] == pytest.approx(
        (rows[0]["q97.5"] - rows[0]["q2.5"]) / 20.0, rel=1e-12)
    assert info["weak"][0]["share_of_box"] > 0.85
    assert info["weak"][0]["bound_by_prior"] == []  # 5.5 and 24.5 are not within 2 % of a bound
    ends = np.array(info["ends"]["x"])
    assert ends[0, 0] < 6.5 and ends[1, 0] > 23.5
    assert np.allclose(ends[:, 1:], ex.samples[0, 1:])
    grid = reference_grid()
    V = SpecimenSolver(setup.problem, grid).solve(SpecimenModel(
        setup.problem, setup.space).solver_rows(torch.tensor(ends)), TIMES).V.numpy()
    on_grid = np.array([n in set(grid[0]) for n in SpecimenSolver(setup.problem, grid).names])
    dV = np.abs(V[0] - V[1])[:, on_grid]  # (T, 558): nothing of the grid is measured
    opt = {o["measurement"]: o for o in info["options"]}
    full = opt["full-field V (31 x 18 grid) at the measured times"]
    assert full["n_new"] == 2 * 558
    assert full["max_diff_um"] == pytest.approx(dV.max(), rel=1e-9)
    assert full["chi2_apart"] == pytest.approx((dV**2).sum() / 0.05**2, rel=1e-9)
    assert full["chi2_apart"] >= APART_CHI2  # creep at 75 degC: s0 = 6 vs 24 MPa is visible
    assert info["options"][0]["chi2_apart"] == max(o["chi2_apart"] for o in info["options"])
    assert info["advice"].startswith("s0 is weakly identified") and "To narrow it, measure" \
        in info["advice"]


def test_effect_parameters_reach_the_fe_in_their_columns():
    """Moire rigid motion (observation side, exact): only the first image's offset moire_c_1
    spreads (over [-0.95, 0.95] um of its [-1, 1] box), so the two ends' full fields differ by
    exactly their offset difference, uniformly at t = 600 s and not at all at 900 s. A column
    mix-up (a rotation w instead of an offset c, or the other image) breaks this."""
    fx = ("moire_rigid_motion",)
    setup, space, meas, ex, rows = _case(4, -0.95, 0.95, fx)
    assert space.names[4] == "moire_c_1"
    info = identifiability(setup, fx, space, rows, ex, meas, 0.05)
    assert [w["parameter"] for w in info["weak"]] == ["moire_c_1"]
    ends = np.array(info["ends"]["x"])
    full = {o["measurement"]: o for o in info["options"]}[
        "full-field V (31 x 18 grid) at the measured times"]
    dc = ends[1, 4] - ends[0, 4]
    assert dc > 1.6
    assert full["max_diff_um"] == pytest.approx(dc, rel=1e-9)
    assert full["rms_diff_um"] == pytest.approx(dc / np.sqrt(2.0), rel=1e-9)  # 600 s only
    assert full["time_s"] == 600.0
    assert info["advice"].startswith("moire_c_1 is weakly identified")
    assert "[-0.9" in info["advice"] and " um spans" in info["advice"]
