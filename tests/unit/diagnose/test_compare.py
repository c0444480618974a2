"""Before/after metrics of two calibration runs (solderpyro.diagnose.compare) on small run
directories: the RMS residual of the predictive median, the Gaussian ELPD of a run without a
log_likelihood group and its standard error, and the refusal to compare runs on different
data. The full compare (figure, markdown) is in tests/unit/config/test_rundir.py."""

import numpy as np
import pytest
from scipy.stats import norm

from solderpyro.config.rundir import Checks, DesignSummary, Draws, RunDir, RunInfo, SurrogateRecord
from solderpyro.diagnose.compare import compare, measured, run_metrics
from solderpyro.io.measurements import from_arrays

TIMES = [600.0, 900.0, 1500.0]
POINTS = {"A": (15.0, 4.5), "B": (15.0, -4.0)}


def _run(path, y, seed):
    info = RunInfo(
        parameters=["s0"], lower=[5.0], upper=[25.0], effects=[], sigma_known=None,
        times_s=TIMES, points=list(POINTS), overrides=[], data="d.csv", store="store", seed=0,
        settings={}, surrogate=SurrogateRecord("matern52", True, "linear", "pca", "unit", False,
                                               False),
        n_runs=10, design=DesignSummary({}), checks=Checks({}, {}, 0.0, 0.95), timing_s={},
        trust="", posterior="surrogate", exact={}, extra={})
    meas = from_arrays(TIMES, list(POINTS), list(POINTS.values()), y.reshape(3, 2),
                       sigma_um=0.05)
    rng = np.random.default_rng(seed)
    n = 60
    proc = y.reshape(-1) + 0.1 + 0.02 * rng.standard_normal((n, 6))
    dr = Draws(theta=rng.uniform(10, 14, (n, 1)), sigma=np.full(n, 0.05), names=["s0"],
               process=proc, observed=proc + 0.05 * rng.standard_normal(proc.shape),
               y_obs=np.asarray(meas.value_um, float), y_liu=y.reshape(-1),
               sigma_pred=np.full(n, 0.05))
    RunDir(path, info).write(meas, dr)
    q = np.quantile(dr.theta[:, 0], [0.025, 0.5, 0.975])
    (path / "summary.csv").write_text(
        "parameter,q2.5,median,mean,q97.5,lo95,hi95,interval,r_hat,ess_bulk\n"
        f"s0,{q[0]},{q[1]},{q[1]},{q[2]},{q[0]},{q[2]},central,1.0,400\n")
    return dr


def test_metrics_are_the_stated_arithmetic(tmp_path):
    """rms_um = sqrt(mean((median_draws(process) - y)^2)); without posterior.nc the ELPD is
    sum_i log N(y_i; mean, sd (ddof 1) of the observed draws) with se sqrt(n var(elpd_i));
    measured() gives the data back (1e-12: float arithmetic of the same sums)."""
    y = np.array([1.0, -0.5, 1.4, -0.7, 2.0, -1.1])
    dr = _run(tmp_path / "a", y, 0)
    m = run_metrics(tmp_path / "a")
    yo = dr.y_obs
    np.testing.assert_allclose(measured(tmp_path / "a"), yo, rtol=0, atol=1e-12)
    rms = np.sqrt(np.mean((np.median(dr.process, 0) - yo) ** 2))
    assert m["rms_um"] == pytest.approx(rms, rel=1e-12)
    assert 0.08 < m["rms_um"] < 0.12  # the process draws sit 0.1 um above the data
    e_i = norm.logpdf(yo, dr.observed.mean(0), dr.observed.std(0, ddof=1))
    assert m["elpd_method"] == "gaussian" and m["n"] == 6
    assert m["elpd"] == pytest.approx(e_i.sum(), rel=1e-12)
    assert m["elpd_se"] == pytest.approx(np.sqrt(6 * e_i.var()), rel=1e-12)
    assert np.isnan(m["p_loo"]) and m["pareto_k_bad"] == 0


def test_runs_on_different_data_are_refused(tmp_path):
    y = np.array([1.0, -0.5, 1.4, -0.7, 2.0, -1.1])
    _run(tmp_path / "a", y, 0)
    _run(tmp_path / "b", y + 0.2, 1)
    with pytest.raises(ValueError, match="calibrated on different data"):
        compare(tmp_path / "a", tmp_path / "b", tmp_path / "cmp")
    assert not (tmp_path / "cmp" / "comparison.json").exists()
