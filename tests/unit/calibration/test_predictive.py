"""posterior.nc's ArviZ groups (observed_data, posterior_predictive, log_likelihood) and the
pointwise likelihood of the predictive bands: a user's az.loo works on the file and equals the
PSIS-LOO of the same log-likelihood computed by hand."""

import arviz as az
import numpy as np
import pytest
import torch
from scipy import stats

from solderpyro.calibration.mcmc import Posterior, thin_index
from solderpyro.calibration.predictive import Bands


def test_thin_index_takes_the_same_draws_of_every_chain():
    idx = thin_index(4, 1000, 1000)
    assert idx.shape == (1000,)
    per = idx.reshape(4, 250)
    assert np.array_equal(per // 1000, np.repeat(np.arange(4)[:, None], 250, 1))
    assert np.array_equal(per[0] % 1000, per[3] % 1000) and per[0, 0] == 0 and per[0, -1] == 999
    assert thin_index(2, 30, 1000).shape == (60,)  # fewer draws than asked: all of them


def test_bands_log_likelihood_is_the_gaussian_density():
    g = torch.Generator().manual_seed(0)
    loc, var = torch.randn(5, 3, generator=g), torch.rand(5, 3, generator=g)
    sig, y = torch.rand(5, generator=g) + 0.1, torch.randn(3, generator=g)
    b = Bands(loc, loc, sig, loc, var)
    want = stats.norm.logpdf(y.numpy(), loc.numpy(), np.sqrt(var.numpy()
                                                             + sig.numpy()[:, None] ** 2))
    np.testing.assert_allclose(b.log_likelihood(y).numpy(), want, rtol=1e-12)
    with pytest.raises(ValueError, match="per-draw"):
        Bands(loc, loc).log_likelihood(y)


def test_posterior_nc_groups_and_loo(tmp_path):
    rng = np.random.default_rng(1)
    C, D, n = 2, 200, 6
    mu = rng.normal(size=(C, D))
    post = Posterior({"t": torch.tensor(mu[..., None])}, {"t": ["mu"]}, [0, 0])
    y = rng.normal(size=n)
    idx = thin_index(C, D, 100)
    m = mu.reshape(-1)[idx]
    ll = stats.norm.logpdf(y[None], m[:, None], 1.0)
    pp = m[:, None] + rng.normal(size=(len(idx), n))
    p = post.save(tmp_path / "posterior.nc", predictive={"y": y, "index": idx,
                                                          "observed": pp, "log_likelihood": ll})
    idata = az.from_netcdf(str(p))
    assert {"posterior", "sample_stats", "observed_data", "posterior_predictive",
            "log_likelihood"} <= set(idata.groups())
    assert idata.posterior["mu"].shape == (C, D)
    assert idata.log_likelihood["y"].shape == (C, 50, n)
    np.testing.assert_array_equal(idata.log_likelihood["draw"].values, idx[:50] % D)
    loo = az.loo(idata)
    # float32 storage: the ELPD to ~1e-5 of the float64 one
    ref = az.loo(az.from_dict(posterior={"mu": mu}, log_likelihood={
        "y": ll.reshape(C, 50, n)}))
    assert float(loo.elpd_loo) == pytest.approx(float(ref.elpd_loo), rel=1e-5)
    with pytest.raises(ValueError, match="same draws of every chain"):
        post.to_inference_data({"y": y, "index": np.arange(7), "observed": pp[:7],
                                "log_likelihood": ll[:7]})
