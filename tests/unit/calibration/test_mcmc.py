"""Chain starting points (solderpyro.calibration.mcmc.sir_inits / run_nuts(init=...))."""

import pyro
import pyro.distributions as dist
import pytest
import torch

from solderpyro.calibration.mcmc import NutsOptions, run_nuts, sir_inits

MODES = (-3.0, 3.0)
WEIGHTS = (0.99, 0.01)


def _bimodal():
    """t ~ U(-5, 5) and an observed site whose likelihood is a two-mode mixture in t (masses
    0.99 at -3 and 0.01 at +3, sd 0.1): NUTS cannot cross the gap between the modes."""
    t = pyro.sample("t", dist.Uniform(-5.0, 5.0))
    lik = torch.logsumexp(torch.stack([
        torch.log(torch.tensor(w)) + dist.Normal(mu, 0.1).log_prob(t)
        for mu, w in zip(MODES, WEIGHTS, strict=True)]), 0)
    pyro.sample("obs", dist.Unit(lik), obs=torch.tensor([]))


def test_sir_starts_chains_in_proportion_to_the_mass_of_each_mode():
    """Systematic resampling of 512 prior draws: 8 chains expect 0.08 starts in the 1 % mode,
    and systematic resampling puts at most one there (its count is within 1 of 8 x weight)."""
    inits = sir_inits(_bimodal, (), chains=8, n=512, seed=1)
    ts = torch.stack([i["t"] for i in inits])
    assert ((ts - MODES[0]).abs() < 0.5).sum() >= 7, ts
    assert ((ts > -5) & (ts < 5)).all()


def test_nuts_chains_from_sir_sit_in_the_main_mode():
    s = run_nuts(_bimodal, (), NutsOptions(chains=4, warmup=100, draws=100, seed=3,
                                           progress=False, init="sir")).samples
    med = s["t"].median(1).values  # (chains,)
    assert ((med - MODES[0]).abs() < 0.3).all(), med


def test_bad_init_is_named():
    with pytest.raises(ValueError, match="init"):
        run_nuts(_bimodal, (), NutsOptions(init="best"))
    with pytest.raises(ValueError, match="init_draws"):
        run_nuts(_bimodal, (), NutsOptions(init_draws=0))
