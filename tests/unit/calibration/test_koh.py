"""KOH likelihoods: the beta marginalization is exact; bad input names the argument."""

import math

import pytest
import torch

from solderpyro.calibration import CalibrationData, Priors, calibrate_direct
from solderpyro.calibration.data import InputAxes
from solderpyro.calibration.koh import joint_cholesky, joint_loglik, prepare_joint
from solderpyro.examples.seed_math import LHS_T, X_BOX, code, lhs_runs, make_data

DT = torch.float64


def _data():
    x, y = make_data(0)
    xs, ts, ys = lhs_runs(8, 0)
    return CalibrationData.create(xs, ts, ys, x, y,
                                  InputAxes(["x"], ["t"], theta_box=LHS_T, x_box=X_BOX))


def test_beta_marginal_equals_quadrature():
    """log int N(z; F beta, S) d beta (flat prior), by Gauss-Hermite-free brute force."""
    inp = prepare_joint(_data())
    args = [(torch.tensor([0.4], dtype=DT), torch.tensor(0.5, dtype=DT),
             torch.tensor(3.0, dtype=DT), torch.tensor([2.0], dtype=DT)),
            (torch.tensor([0.7], dtype=DT), torch.tensor(0.8, dtype=DT),
             torch.tensor(5.0, dtype=DT), torch.tensor([0.5], dtype=DT))]
    ours, brute = [], []
    for a in args:
        ll, bh, bc = joint_loglik(inp, *a)
        ours.append(ll.item())
        chol, h = joint_cholesky(inp, *a, None)
        b = torch.linspace(bh.item() - 12 * bc.sqrt().item(), bh.item() + 12 * bc.sqrt().item(),
                           20001, dtype=DT)
        r = inp.z[None, :] - b[:, None] * h[:, 0][None, :]  # (n_b, N)
        w = torch.linalg.solve_triangular(chol, r.T, upper=False)
        logp = -0.5 * w.square().sum(0) - chol.diagonal().log().sum()
        db = (b[1] - b[0]).item()
        brute.append((torch.logsumexp(logp, 0) + math.log(db)).item())
    # the marginal drops the constant (2 pi)^(p/2); differences between settings must agree
    assert abs((ours[0] - ours[1]) - (brute[0] - brute[1])) < 1e-8


def test_bad_input_names_the_argument():
    x, y = make_data(0)
    xs, ts, ys = lhs_runs(5, 0)
    with pytest.raises(ValueError, match="y_obs contains NaN"):
        CalibrationData.create(xs, ts, ys, x, torch.full_like(y, float("nan")))
    with pytest.raises(ValueError, match="theta_sim has 4 rows, expected 5"):
        CalibrationData.create(xs, ts[:4], ys, x, y)
    with pytest.raises(ValueError, match="x_obs is empty"):
        CalibrationData.create(xs, ts, ys, x[:0], y[:0])
    with pytest.raises(ValueError, match="y_sim must have 1 dimension"):
        CalibrationData.create(xs, ts, ys[:, None], x, y)
    with pytest.raises(ValueError, match="Priors.sigma_max must be positive"):
        Priors(sigma_max=0.0)
    with pytest.raises(ValueError, match="corr_range"):
        Priors(corr_range=(1.0, 0.5))
    with pytest.raises(ValueError, match="x_obs has 11 rows but y_obs has 5"):
        calibrate_direct(code, x, y[:5], LHS_T)
    with pytest.raises(ValueError, match="run_nuts draws must be a positive integer"):
        calibrate_direct(code, x, y, LHS_T, draws=0)


def test_posterior_netcdf_round_trip_and_summary(tmp_path):
    import warnings

    import numpy as np

    from solderpyro.calibration import Posterior

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        import arviz as az
    g = torch.Generator().manual_seed(0)
    t = torch.randn(4, 500, 2, generator=g, dtype=DT) * torch.tensor([1.0, 0.1], dtype=DT)
    post = Posterior({"t": t, "sigma": t[..., 0].abs()}, {"t": ["s0", "m"]}, [0, 1, 0, 0])
    rows = {r["parameter"]: r for r in post.summary()}
    assert set(rows) == {"s0", "m", "sigma"}
    # iid N(0, 1) draws: median within 4 standard errors of 0, quantiles near +-1.96
    assert abs(float(rows["s0"]["median"])) < 4 * 1.2533 / np.sqrt(2000)
    assert abs(float(rows["s0"]["q97.5"]) - 1.96) < 0.15
    assert abs(float(rows["s0"]["r_hat"]) - 1.0) < 0.01
    assert float(rows["s0"]["ess_bulk"]) > 1200
    path = post.save(tmp_path / "post.nc")
    back = az.from_netcdf(str(path))
    assert np.array_equal(back.posterior["m"].values, t[..., 1].numpy())
    assert int(back.sample_stats["diverging"].values.sum()) == 1



def test_known_sigma_prior_is_centred_on_the_stated_noise():
    import pyro

    x, y = make_data(0)
    pr = Priors(sigma_known=0.6)
    from solderpyro.calibration.emulators import FunctionEmulator
    from solderpyro.calibration.koh import observation_model, prepare_observation

    inp = prepare_observation(y, FunctionEmulator(code, x), LHS_T)
    draws = torch.stack([pyro.poutine.trace(observation_model).get_trace(inp, pr)
                         .nodes["sigma"]["value"] for _ in range(2000)])
    # LogNormal(log 0.6, 0.1): median 0.6, 95 % within a factor exp(0.196)
    assert abs(draws.median().item() - 0.6) < 0.01
    assert ((draws / 0.6).log().abs() < 0.196).double().mean().item() > 0.93
    with pytest.raises(ValueError, match="Priors.sigma_known must be positive"):
        Priors(sigma_known=-1.0)
