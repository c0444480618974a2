"""The PCA surrogate's low-rank covariance equals its dense one, and the low-rank likelihood
equals the dense Gaussian likelihood (full-field calibration relies on both)."""

import pyro
import pyro.poutine as poutine
import torch

from solderpyro.calibration import Priors
from solderpyro.calibration.emulators import GPEmulator
from solderpyro.calibration.koh import SITE_Y, observation_model, prepare_observation
from solderpyro.params import Box
from solderpyro.surrogate import GPOptions, GPSurrogate


def _field_gp(n_y=60, n=16):
    g = torch.Generator().manual_seed(0)
    box = Box(("a", "b"), (0.0, 0.0), (1.0, 1.0))
    x = torch.rand(n, 2, generator=g, dtype=torch.float64)
    s = torch.linspace(0, 1, n_y, dtype=torch.float64)
    y = torch.sin(3 * x[:, :1] + 2 * s) * (1 + x[:, 1:]) + 0.3 * x[:, 1:] * s ** 2
    return GPSurrogate(box, output="pca", options=GPOptions(n_pc=3)).fit(x, y), box


def test_lowrank_equals_dense_covariance():
    gp, _ = _field_gp()
    t = torch.tensor([0.3, 0.7], dtype=torch.float64)
    m, F, d = gp.mean_lowrank(t)
    md, cd = gp.mean_cov(t[None])
    assert torch.allclose(m, md, atol=1e-12)
    # each component's variance is os_k - |v_k|^2 (v_k: n terms, |v_k|^2 <= os_k), summed in
    # different orders by the two paths, so they differ by rounding of up to (n + 3) eps os_k,
    # mapped to the outputs by the scaled basis sv; the posterior covariance itself is far
    # smaller than its prior terms (the variance cancels), so its own size bounds nothing
    sv = gp.basis * gp.std.scale[:, None]  # (n_y, k)
    prior = (sv.abs() * gp._os) @ sv.abs().T  # (n_y, n_y)
    n, eps = gp._u.shape[1], torch.finfo(torch.float64).eps
    assert ((F @ F.T + torch.diag(d) - cd).abs() <= 2 * (n + 8) * eps * prior).all()
    assert F.shape[1] == 3


def test_lowrank_likelihood_equals_dense():
    gp, box = _field_gp()
    em = GPEmulator(gp)
    t = torch.tensor([0.4, 0.2], dtype=torch.float64)
    y = gp.mean_lowrank(t)[0] + 0.05
    inp = prepare_observation(y, em, box)
    cond = {"t_unit": box.to_unit(t), "sigma": torch.tensor(0.07, dtype=torch.float64)}
    tr = poutine.trace(poutine.condition(observation_model, cond)).get_trace(
        inp, Priors(sigma_max=1.0))
    lp = tr.nodes[SITE_Y]["fn"].log_prob(y)
    m, c = gp.mean_cov(t[None])
    dense = torch.distributions.MultivariateNormal(m, c + 0.07 ** 2 * torch.eye(len(y),
                                                   dtype=torch.float64)).log_prob(y)
    assert torch.allclose(lp, dense, rtol=1e-10)
    pyro.clear_param_store()
