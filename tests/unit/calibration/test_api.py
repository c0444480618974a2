"""The direct calibration mode (solderpyro.calibration.api) on a linear Gaussian model, whose
posterior is known: y = a x + c + N(0, sigma^2) with flat priors on a box that does not bind
(sigma flat on (0, 1)). Integrating sigma out, p(a, c | y) ~ RSS(a, c)^(-(n-1)/2): a
Student t with n - 3 degrees of freedom centred on the least-squares fit, covariance
RSS_min / (n - 5) (F^T F)^-1. The seed's cases against grid posteriors are in
tests/unit/calibration/test_nuts.py and tests/verification/test_calibration_stats.py."""

import numpy as np
import torch

from solderpyro.calibration import Priors, calibrate_direct
from solderpyro.params import Box

F64 = torch.float64
SIGMA = 0.05
X = torch.linspace(-1.0, 1.0, 12, dtype=F64)[:, None]  # centred: a, c uncorrelated
NUTS = dict(chains=2, warmup=250, draws=400, seed=3, progress=False, workers=1)


def _data():
    g = torch.Generator().manual_seed(0)
    return 0.8 * X[:, 0] + 0.25 + SIGMA * torch.randn(12, generator=g, dtype=F64)


def _check(post, names, y):
    """Posterior means within 4.5 Monte Carlo standard errors (sd / sqrt(ESS_bulk)) of the
    least-squares values, posterior sds within 20 % of the t posterior's (an sd from ESS
    >= 150 draws of a t with 9 degrees of freedom has a relative MC error of ~8 %; 3000
    draws per chain give the t sds to 2-4 %)."""
    F = np.c_[X[:, 0].numpy(), np.ones(12)]
    ls, rss = np.linalg.lstsq(F, y.numpy(), rcond=None)[:2]
    sd = np.sqrt(rss[0] / (len(y) - 5) * np.diag(np.linalg.inv(F.T @ F)))
    rows = {r["parameter"]: r for r in post.summary()}
    for nm, m, s in zip(names, ls, sd, strict=True):
        r = rows[nm]
        assert r["r_hat"] < 1.05 and r["ess_bulk"] >= 150
        draws = post.columns()[nm].reshape(-1)
        mcse = draws.std() / np.sqrt(r["ess_bulk"])
        assert abs(r["mean"] - m) < 4.5 * mcse, (nm, r["mean"], m, mcse)
        assert abs(draws.std() / s - 1) < 0.2, (nm, draws.std(), s)


def test_direct_calibration_centres_on_least_squares():
    y = _data()
    box = Box(("a", "c"), (-2.0, -2.0), (3.0, 3.0))
    post, _ = calibrate_direct(lambda x, t: t[0] * x[:, 0] + t[1], X, y, box,
                               Priors(sigma_max=1.0), **NUTS)
    assert post.samples["t"].shape == (2, 400, 2)
    _check(post, ["a", "c"], y)
