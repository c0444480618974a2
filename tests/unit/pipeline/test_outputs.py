"""posterior.nc as ArviZ reads it: the sampler's per-draw statistics (az.bfmi, az.plot_energy),
observations named by time and point, and the non-factorized leave-one-out log likelihood
of the correlated KOH likelihood (az.loo), checked against the conditional of the normal by
explicit partitioning."""

from __future__ import annotations

import math
from types import SimpleNamespace

import arviz as az
import numpy as np
import pytest
import torch

from solderpyro.calibration import calibrate_emulator
from solderpyro.calibration.emulators import GPEmulator
from solderpyro.calibration.koh import SITE_SIGMA, SITE_T
from solderpyro.calibration.nuts import SAMPLE_STATS
from solderpyro.io.measurements import from_arrays
from solderpyro.params import Box
from solderpyro.pipeline.calibrate import save_posterior
from solderpyro.pipeline.outputs import (
    lowrank_log_likelihoods,
    lowrank_loo_log_likelihood,
    mvn_log_likelihoods,
    mvn_loo_log_likelihood,
    observation_coords,
)
from solderpyro.surrogate import GPOptions, GPSurrogate


def _spd(n: int, g: torch.Generator) -> torch.Tensor:
    a = torch.randn(n, n, generator=g, dtype=torch.float64)
    return a @ a.T / n + 0.3 * torch.eye(n, dtype=torch.float64)


def _by_partitioning(y: torch.Tensor, mu: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """log p(y_i | y_-i) from the conditional normal, one explicit partition per i."""
    n = y.shape[0]
    out = torch.empty(n, dtype=torch.float64)
    for i in range(n):
        o = [j for j in range(n) if j != i]
        w = torch.linalg.solve(c[o][:, o], c[o, i])  # C_-i,-i^-1 C_-i,i
        m = mu[i] + w @ (y[o] - mu[o])
        v = c[i, i] - c[i, o] @ w
        out[i] = -0.5 * math.log(2 * math.pi * v) - 0.5 * (y[i] - m) ** 2 / v
    return out


def test_loo_terms_are_the_conditionals_of_the_normal():
    """The closed form ``-log(2 pi)/2 + log(gbar_ii)/2 - g_i^2/(2 gbar_ii)`` equals the log
    density of the conditional ``y_i | y_-i`` found by partitioning the covariance, for a
    batch of correlated normals (float64, condition numbers ~1e2: agreement to 1e-10), and
    the Woodbury form of a low-rank-plus-diagonal covariance equals the dense one."""
    g = torch.Generator().manual_seed(0)
    n = 9
    covs = torch.stack([_spd(n, g) for _ in range(4)])
    mus = torch.randn(4, n, generator=g, dtype=torch.float64)
    y = torch.randn(n, generator=g, dtype=torch.float64)
    got = mvn_loo_log_likelihood(y, mus, covs)
    want = torch.stack([_by_partitioning(y, mus[k], covs[k]) for k in range(4)])
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-10)
    # low rank plus diagonal (a PCA surrogate's code covariance plus the noise)
    f = torch.randn(4, n, 3, generator=g, dtype=torch.float64)
    d = 0.05 + torch.rand(4, n, generator=g, dtype=torch.float64)
    dense = f @ f.transpose(-1, -2) + torch.diag_embed(d)
    torch.testing.assert_close(lowrank_loo_log_likelihood(y, mus, f, d),
                               mvn_loo_log_likelihood(y, mus, dense), rtol=1e-10, atol=1e-10)
    # with no correlation the terms are the marginal normal densities
    diag = torch.diag_embed(d)
    marg = -0.5 * torch.log(2 * math.pi * d) - 0.5 * (y - mus) ** 2 / d
    torch.testing.assert_close(mvn_loo_log_likelihood(y, mus, diag), marg, rtol=1e-12,
                               atol=1e-12)



def test_the_joint_log_likelihood_is_torchs_multivariate_normal_dense_and_low_rank():
    """The joint log density from the same factorization as the LOO terms equals torch's
    MultivariateNormal.log_prob, for dense covariances and for low rank plus diagonal (the
    determinant lemma), to 1e-10 on condition numbers ~1e2 (float64)."""
    g = torch.Generator().manual_seed(1)
    n = 9
    covs = torch.stack([_spd(n, g) for _ in range(4)])
    mus = torch.randn(4, n, generator=g, dtype=torch.float64)
    y = torch.randn(n, generator=g, dtype=torch.float64)
    want = torch.distributions.MultivariateNormal(mus, covs).log_prob(y)
    torch.testing.assert_close(mvn_log_likelihoods(y, mus, covs)[1], want, rtol=1e-10,
                               atol=1e-10)
    f = torch.randn(4, n, 3, generator=g, dtype=torch.float64)
    d = 0.05 + torch.rand(4, n, generator=g, dtype=torch.float64)
    dense = f @ f.transpose(-1, -2) + torch.diag_embed(d)
    want = torch.distributions.MultivariateNormal(mus, dense).log_prob(y)
    torch.testing.assert_close(lowrank_log_likelihoods(y, mus, f, d)[1], want, rtol=1e-10,
                               atol=1e-10)

TIMES = [600.0, 900.0, 1500.0]
POINTS = {"A": (15.0, 4.5), "B": (15.0, -4.0)}
BOX = Box(("s0", "QR"), (5.0, 7000.0), (25.0, 13000.0), (False, False))
DRAWS, MORE = 300, 100


def _code(th: torch.Tensor) -> torch.Tensor:
    """A smooth toy code ``(m, 2) -> (m, 6)``: the 2 points at the 3 times, um."""
    u = BOX.to_unit(th)
    ts = torch.tensor(TIMES, dtype=torch.float64) / 1500.0
    a = (1.0 + 0.8 * u[:, :1]) * ts  # (m, 3)
    b = -(0.5 + 0.6 * u[:, 1:] * u[:, :1]) * ts.sqrt()
    return torch.stack([a, b], -1).reshape(-1, 6)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A run directory's posterior.nc, written by the pipeline's own ``save_posterior`` from a
    modular KOH posterior through a fitted PCA surrogate (2 points x 3 times, 3 components; 2
    parameters and sigma), whose chains ran on once (as ``reach_min_ess`` does)."""
    torch.set_default_dtype(torch.float64)
    from solderpyro.design import lhs

    th = lhs(BOX, 24, 0)
    gp = GPSurrogate(BOX, output="pca", kernel="matern52", ard=True,
                     options=GPOptions(n_pc=3, restarts=1)).fit(th, _code(th))
    truth = BOX.from_unit(torch.tensor([[0.4, 0.6]]))
    rng = np.random.default_rng(2)
    vals = _code(truth)[0].numpy().reshape(3, 2) + 0.02 * rng.standard_normal((3, 2))
    meas = from_arrays(TIMES, list(POINTS), list(POINTS.values()), vals, sigma_um=0.02)
    y = torch.tensor(np.asarray(meas.value_um, float))
    nk = dict(chains=2, warmup=200, draws=DRAWS, seed=1, progress=False, workers=1)
    post, inp = calibrate_emulator(GPEmulator(gp), y, BOX, **nk)
    more, _ = calibrate_emulator(GPEmulator(gp), y, BOX,
                                 **{**nk, "draws": MORE, "warmup": 0, "warm": post.warm,
                                    "seed": 8})
    post = post.extend(more)
    out = tmp_path_factory.mktemp("run")
    save_posterior(SimpleNamespace(y=y, meas=meas), post, inp, 0, out)
    return out, post, inp, meas


def test_sample_stats_hold_every_per_draw_statistic(run_dir):
    out, post, _, _ = run_dir
    idata = az.from_netcdf(str(out / "posterior.nc"))
    ss = idata.sample_stats
    assert set(SAMPLE_STATS) <= set(ss.data_vars)
    assert idata.posterior.sizes["draw"] == post.n_draws == DRAWS + MORE
    for k in SAMPLE_STATS:
        assert ss[k].shape == (2, DRAWS + MORE)
    e, lp = ss["energy"].values, ss["lp"].values
    assert np.all(np.isfinite(e)) and np.all(np.isfinite(lp))
    # energy = -lp + kinetic energy >= -lp; at the selected point the momentum is (up to the
    # integrator's error) a draw of N(0, M), so the kinetic energy averages d/2 (d = 3
    # coordinates: sd sqrt(d/2) per draw, 800 draws with fresh momenta: 5 standard errors
    # ~0.22)
    kin = e + lp
    assert kin.min() >= -1e-9
    assert abs(kin.mean() - 1.5) < 0.25
    assert np.all(ss["n_steps"].values >= 1)
    assert np.all(ss["n_steps"].values <= 2 ** ss["tree_depth"].values)
    assert np.all((ss["acceptance_rate"].values >= 0) & (ss["acceptance_rate"].values <= 1))
    assert np.all(ss["step_size"].values > 0)


def test_arviz_diagnostics_run_on_the_file(run_dir):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out, _, _, _ = run_dir
    idata = az.from_netcdf(str(out / "posterior.nc"))
    bfmi = az.bfmi(idata)
    # BFMI below 0.3 signals a heavy-tailed energy distribution (Betancourt 2016); a
    # three-coordinate posterior of smooth code outputs is far from that
    assert bfmi.shape == (2,) and np.all(bfmi > 0.3)
    ax = az.plot_energy(idata)
    assert ax is not None
    plt.close("all")
    summ = az.summary(idata)
    assert {"s0", "QR", "sigma"} <= set(summ.index)
    loo = az.loo(idata, pointwise=True)
    # (six values and three parameters: each observation is influential, so some Pareto
    # k-hat may exceed 0.7 here; that is the data's size, not the file)
    assert np.isfinite(float(loo.elpd_loo)) and loo.pareto_k.shape == (6,)
    assert np.all(np.isfinite(loo.loo_i.values))


def test_observations_are_named_by_time_and_point(run_dir):
    out, _, _, meas = run_dir
    idata = az.from_netcdf(str(out / "posterior.nc"))
    for grp in ("observed_data", "posterior_predictive", "log_likelihood"):
        obs = idata[grp]["obs"]
        want = [f"{p}@{t:g}s" for p, t in zip(meas.point, meas.time_s, strict=True)]
        assert list(obs.values) == want
        np.testing.assert_array_equal(idata[grp]["time_s"].values, meas.time_s)
        np.testing.assert_array_equal(idata[grp]["point"].values, meas.point.astype(str))
        np.testing.assert_array_equal(idata[grp]["x_mm"].values, meas.x_mm)
        np.testing.assert_array_equal(idata[grp]["y_mm"].values, meas.y_mm)
    with pytest.raises(ValueError, match="5 values"):
        observation_coords(meas, 5)


def test_the_files_log_likelihood_is_the_leave_one_out_density_of_the_sampled_likelihood(
        run_dir):
    """At a kept draw the file holds log p(y_i | y_-i, theta) of N(mu(theta), C(theta) +
    sigma^2 I), the emulator's mean and dense code covariance, by partitioning (the file's
    come from the low-rank form through Woodbury; float32 storage: 1e-5 relative)."""
    out, post, inp, _ = run_dir
    idata = az.from_netcdf(str(out / "posterior.nc"))
    ll = idata.log_likelihood["y"].values  # (chain, k, n_obs)
    pos = int(idata.log_likelihood["draw"].values[7])
    i = 1 * post.n_draws + pos  # chain 1
    t = BOX.from_unit(post.raw[SITE_T].reshape(-1, 2)[i])
    sigma = post.raw[SITE_SIGMA].reshape(-1)[i]
    m, c = inp.emulator(t)
    want = _by_partitioning(inp.y_obs, m, c + sigma**2 * torch.eye(6))
    np.testing.assert_allclose(ll[1, 7], want.numpy(), rtol=1e-5, atol=1e-5)
