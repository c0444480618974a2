"""The discretization check (pipeline.fe_check): one refinement of the FE, and what it
tells a user about the FE's own error against the data's resolution."""

import dataclasses

import numpy as np

from solderpyro.cli import simulate_table
from solderpyro.config.compose import build, compose
from solderpyro.io.measurements import from_arrays
from solderpyro.params import LIU2008
from solderpyro.pipeline.fe_check import DISCRETIZATION_CHI2, discretization_check, refined
from solderpyro.pipeline.problem import CalibrationProblem


def test_refined_multiplies_every_count_and_divides_every_step():
    p = build(compose([])).problem
    r = refined(p, 1.5)
    assert r.mesh.nx == 45 and [lay.ny for lay in r.layers] == [12, 6, 12]
    assert np.isclose(r.stepping.dT_max, p.stepping.dT_max / 1.5)
    assert np.isclose(r.stepping.dt_max, p.stepping.dt_max / 1.5)
    assert np.isclose(r.stepping.dwell_dt0, p.stepping.dwell_dt0 / 1.5)
    assert r.mesh.x_grading == p.mesh.x_grading and r.cycle == p.cycle


def test_the_fe_converges_under_the_refinement_the_check_uses():
    """Successive refinements by 1.5 change the full field by less and less (a convergent
    discretization; order p > 0 means the second change is the first times 1.5^-p < 1): the
    check's one-refinement shift is an upper bound of the remaining error's scale."""
    setup = build(compose(["mesh=coarse"]))  # coarse: three levels in a few seconds
    times = (600.0, 4800.0)
    V = []
    for k in range(3):
        prob = setup.problem
        for _ in range(k):
            prob = refined(prob)
        V.append(simulate_table(dataclasses.replace(setup, problem=prob), {}, times, True,
                                progress=False)[3])
    d1 = np.sqrt(np.mean((V[1] - V[0]) ** 2))
    d2 = np.sqrt(np.mean((V[2] - V[1]) ** 2))
    assert d2 < 0.8 * d1, (d1, d2)
    assert d1 < 0.05 * np.sqrt(np.mean(V[0] ** 2))  # a refinement, not a different model


def test_the_check_measures_the_shift_in_noise_units(tmp_path):
    """shift_chi2 = |V_fine - V|^2 / sigma^2 exactly: it scales as 1/sigma^2, and warns from
    DISCRETIZATION_CHI2 on."""
    setup = build(compose(["mesh=coarse"]))
    times = (600.0, 4800.0)
    t, names, pts, V = simulate_table(setup, {}, times, True, progress=False)
    temps = np.array([setup.problem.cycle(x) for x in t])
    meas = from_arrays(t, names, pts, V, temperature_C=temps, sigma_um=np.full(V.shape, 0.05))
    sm = CalibrationProblem.build(setup, meas, str(tmp_path / "store"), 64, False)
    x = np.array([LIU2008[nm] for nm in sm.space.names])
    a = discretization_check(sm, x, 0.05)
    fine = CalibrationProblem.build(dataclasses.replace(setup, problem=refined(setup.problem)),
                                    meas, str(tmp_path / "store"), 64, False)
    d = fine.observed(x[None])[0] - sm.observed(x[None])[0]
    assert np.isclose(a["shift_chi2"], np.sum(d**2) / 0.05**2, rtol=1e-10)
    sig_edge = np.sqrt(np.sum(d**2) / DISCRETIZATION_CHI2)  # the sigma where it starts to warn
    assert discretization_check(sm, x, 0.9 * sig_edge)["warn"]
    assert not discretization_check(sm, x, 1.1 * sig_edge)["warn"]
    # the data are the calibration FE's own output: refining can only fit them worse
    assert a["fit_change"] > 0


def test_a_correction_taken_at_one_point_of_the_ridge_holds_all_along_it(tmp_path):
    """The FE's discretization error at the observed values (one refinement, x1.5) is nearly
    the same all along the full-field posterior's ridge: taken at one point, it takes the
    calibration FE to within a small fraction of its error from the refined FE at the others
    (measured: the error's chi2 at 0.05 um is 4.27-4.33; what is left, 0.001-0.004; the test
    asks for 1 % of it). Not so across the whole box: at the Liu 2008 constants the error
    has another size (chi2 3.1), so the calibration takes it at a checked posterior draw. The
    points: the clean hidden-effect data's truth and two points of its posterior's ridge
    (BENCHMARKS.md, "Hidden effects: diagnose, recalibrate, cover the truths"); the data's layout:
    the 31 x 18 grid at the seed times."""
    from solderpyro.fem.loading import SEED_TIMES
    from solderpyro.pipeline.fe_check import discretization_error

    setup = build(compose([]))
    t, names, pts, V = simulate_table(setup, {}, SEED_TIMES, True, progress=False)
    temps = np.array([setup.problem.cycle(x) for x in t])
    meas = from_arrays(t, names, pts, V, temperature_C=temps, sigma_um=np.full(V.shape, 0.05))
    sm = CalibrationProblem.build(setup, meas, str(tmp_path / "store"), 64, False)
    ridge = np.array([[12.92, 10586.0, 2.04, 0.1], [13.6, 12025.0, 3.02, 0.1127],
                      [16.4, 11820.0, 3.4, 0.108]])
    full = ridge  # the FE parameters are the four Anand constants calibrated
    d = np.stack([discretization_error(sm, x) for x in full])  # (3, n_obs)
    sig = 0.05
    raw = (d**2).sum(1) / sig**2
    assert np.all(raw > 1.0), raw  # the data resolve the error: what the correction is for
    for i in range(3):
        for j in range(3):
            left = ((d[j] - d[i]) ** 2).sum() / sig**2
            assert left < 0.01 * raw[j], (i, j, left, raw[j])
    # the check after a correction measures what is left, exactly; the correction is a new
    # data value, the problem's own data stay as measured
    y0 = sm.y.numpy().copy()
    data = sm.data.corrected(d[0], at=0)
    assert not sm.data.is_corrected and data.is_corrected and dict(data.info) == {"at": 0}
    np.testing.assert_allclose(data.y.numpy(), y0 - d[0], rtol=0, atol=1e-15)
    cp = sm.with_data(data)
    assert cp.model is sm.model and cp.tally is sm.tally  # the same model and run count
    chk = discretization_check(cp, full[1], sig, delta=d[0])
    assert np.isclose(chk["shift_chi2"], ((d[1] - d[0]) ** 2).sum() / sig**2, rtol=1e-8)
    assert np.isclose(chk["uncorrected_chi2"], raw[1], rtol=1e-8) and not chk["warn"]
    again = data.corrected(d[1])  # a second correction replaces the first, from the measured
    np.testing.assert_allclose(again.y.numpy(), y0 - d[1], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(sm.y.numpy(), y0)
    import pytest

    with pytest.raises(ValueError, match="delta must be"):
        data.corrected(np.full(len(y0), np.nan))
