"""Simulation-based calibration of the sampler (Talts et al. 2018).

The harness is benchmarks/sbc.py (its full study writes benchmarks/results/sbc.json). Slow:
200 replications of the seed math model (direct mode: t, sigma) and of a 60-output field model
through a PCA GP surrogate (modular mode: a, k, sigma); per replication (t, sigma) is drawn from
the model's prior, y from the model's own likelihood, NUTS runs one chain (300 warm-up, 300
draws, doubled up to twice while the bulk ESS is below 99) and the rank of the prior draw among
99 thinned draws is taken. Ranks of a correct sampler are uniform on {0, ..., 99}: a chi-square
test on 10 equal bins (20 expected per bin) per parameter. A third model, the four Anand
constants through a flow-stress PCA GP, is the one NUTS samples in the soft-walled flow-stress
coordinates (calibration/flowcoords.py); a fourth runs the same Anand model in the ridge
coordinates of calibration/ridgemap.py, warm-started from a pilot as a design round is.
Fifteen tests in all (two parameters direct, three field, five Anand, five Anand in ridge
coordinates); Bonferroni at a family-wise 1 %: each fails below p = 0.00067, so a correct
sampler fails the slow suite with probability <= 1 % (Bonferroni is conservative for the
dependent ranks of one replication).

Measured (benchmarks/results/sbc.json, same seeds as here): p = 0.50 / 0.44 (direct t, sigma),
0.34 / 0.80 / 0.047 (field a, k, sigma); (benchmarks/results/sbc_anand.json) 0.86 / 0.95 /
0.45 / 0.33 / 0.30 (Anand s0, QR, xi, m, sigma). The check can fail: calibrating on every
observation twice (likelihood squared, `--mutate double-lik`) gave p = 2e-7 (t, below the
0.001 line) and 0.0018 (sigma, below the 0.002 line of the five-test family it was run
with). A sampler with a 10-iteration warm-up and 99 consecutive draws of one chain
(`--mutate short`) was NOT detected (p = 0.17, 0.13): on this 2-parameter posterior NUTS
reaches the typical set within a few iterations.

Default suite: the rank statistics themselves (uniform ranks pass, the shapes a wrong posterior
gives fail) and the simulation step (draws from the model's prior and likelihood). No quick SBC
run: R = 40 replications take ~30 s and have ~10 % power against a posterior sqrt(2) too wide
(likelihood halved), so it would only repeat what test_calibration_stats' grid check catches.
"""

import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy import stats

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from sbc import (  # noqa: E402
    DIRECT_BOX,
    L_DRAWS,
    anand_problem,
    anand_ridge_problem,
    bonferroni_alpha,
    direct_problem,
    field_problem,
    rank_stats,
    run_sbc,
    simulate,
)

from solderpyro.examples.seed_math import code  # noqa: E402

REPS = 200  # the minimum
BINS = 10
N_TESTS = 15  # direct: t, sigma; field: a, k, sigma; anand, anand_ridge: s0, QR, xi, m, sigma
ALPHA = bonferroni_alpha(0.01, N_TESTS)  # 0.00067 per chi-square test


def test_rank_stats_pass_uniform_and_fail_wrong_shapes():
    rng = np.random.default_rng(0)
    n_ranks = L_DRAWS + 1
    uniform = rng.integers(0, n_ranks, REPS)
    assert rank_stats(uniform, BINS)["p_value"] > ALPHA
    # a posterior sqrt(2) too wide (likelihood halved): ranks pile up in the middle
    u = stats.norm.cdf(rng.standard_normal(REPS) / np.sqrt(2))
    too_wide = np.minimum((u * n_ranks).astype(int), L_DRAWS)
    # too narrow (overconfident): ranks pile up at both ends
    u = stats.norm.cdf(rng.standard_normal(REPS) * np.sqrt(2))
    too_narrow = np.minimum((u * n_ranks).astype(int), L_DRAWS)
    biased = np.minimum((rng.random(REPS) ** 1.5 * n_ranks).astype(int), L_DRAWS)
    for bad in (too_wide, too_narrow, biased):
        assert rank_stats(bad, BINS)["p_value"] < ALPHA
    s = rank_stats(np.arange(n_ranks).repeat(2), BINS)  # exactly uniform
    assert s["chi2"] == 0.0 and s["max_bin_dev"] == 0.0 and s["ecdf_max_dev"] < 1e-12
    with pytest.raises(ValueError):
        rank_stats(uniform, 7)


def test_simulation_draws_from_the_model_prior_and_likelihood():
    p = direct_problem()
    draws = [simulate(p, 1000 + i) for i in range(300)]
    t = np.array([d[0]["t"] for d in draws])
    sigma = np.array([d[0]["sigma"] for d in draws])
    lo, hi = DIRECT_BOX.lower[0], DIRECT_BOX.upper[0]
    assert stats.kstest(t, stats.uniform(lo, hi - lo).cdf).pvalue > 1e-3
    assert stats.kstest(sigma, stats.uniform(0, 2).cdf).pvalue > 1e-3
    x = p.inp.emulator.x_obs
    z = np.concatenate([((y - code(x, torch.tensor([tr["t"]]))) / tr["sigma"]).numpy()
                        for tr, y in draws])
    assert stats.kstest(z, "norm").pvalue > 1e-3


def _check(res):
    for nm, s in res["stats"].items():
        assert s["p_value"] > ALPHA, (res["model"], nm, s["chi2"], s["p_value"], s["counts"],
                                      s["max_bin_dev"], s["ecdf_max_dev"])


@pytest.mark.slow
def test_sbc_seed_math_direct():
    _check(run_sbc(direct_problem(), REPS, chains=1, warmup=300, draws=300, bins=BINS))


@pytest.mark.slow
def test_sbc_field_pca_modular():
    _check(run_sbc(field_problem(), REPS, chains=1, warmup=300, draws=300, bins=BINS))


@pytest.mark.slow
def test_sbc_anand_flow_coordinates():
    _check(run_sbc(anand_problem(), REPS, chains=1, warmup=300, draws=300, bins=BINS))


@pytest.mark.slow
def test_sbc_anand_ridge_coordinates():
    """The mapped sampler (calibration/ridgemap.py) as a design round runs it: a pilot, then
    the run warm-started in the ridge coordinates fitted to the pilot's draws."""
    p = anand_ridge_problem()
    res = run_sbc(p, REPS, chains=1, warmup=300, draws=300, bins=BINS)
    assert p.info["mapped_reps"] >= 0.8 * REPS  # the map ran (runs, reruns included)
    _check(res)
