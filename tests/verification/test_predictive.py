"""Posterior predictive bands (seed Eq. 9, 12) and the discrepancy GP, on the seed's example.

The seed's computer model 5 exp(-t x) cannot represent the true process 1.5 + 3.5 exp(-1.7 x)
(it decays to 0, the truth to 1.5). Facts checked:
- without a discrepancy, the direct calibration's 95 % process band misses the truth over
  a good part of [0, 3] (a wrong model fitted confidently);
- with a GP discrepancy delta(x) the band covers the truth nearly everywhere;
- the full-joint predictive from 20 runs, on data without model error, covers the truth.
"""

import torch

from solderpyro.calibration import (
    CalibrationData,
    Priors,
    calibrate_direct,
    calibrate_joint,
    predict_joint,
    predict_observation_model,
)
from solderpyro.calibration.data import InputAxes
from solderpyro.examples.seed_math import X_BOX, code, lhs_runs, make_data, true_process
from solderpyro.params import Box

DT = torch.float64
XG = torch.linspace(0, 3, 31, dtype=DT)[:, None]
T_BOX = Box(("t",), (-0.5,), (2.5,))
NUTS = dict(chains=2, warmup=250, draws=300, seed=0, progress=False)


def _coverage(bands, truth):
    return ((bands.lo <= truth) & (truth <= bands.hi)).double().mean().item()


def test_discrepancy_repairs_the_wrong_model():
    x, y = make_data(0)
    truth = true_process(XG[:, 0])
    pr = Priors(sigma_max=5.0)
    post, inp = calibrate_direct(code, x, y, T_BOX, pr, **NUTS)
    plain = _coverage(predict_observation_model(post, inp, XG, n_draws=300), truth)
    post_d, inp_d = calibrate_direct(code, x, y, T_BOX, pr, discrepancy=True, x_box=X_BOX,
                                     **NUTS)
    u_new = X_BOX.to_unit(XG)
    with_d = _coverage(predict_observation_model(post_d, inp_d, XG, u_new, n_draws=300), truth)
    assert plain < 0.8, plain
    assert with_d >= 0.9, with_d


def test_joint_predictive_covers_truth_without_model_error():
    x, y = make_data(7, true_fn=lambda xx: 5 * torch.exp(-0.7 * xx))
    xs, ts, ys = lhs_runs(20, 0)
    data = CalibrationData.create(
        xs, ts, ys, x, y,
        InputAxes(["x"], ["t"], theta_box=Box(("t",), (-0.5,), (2.5,)), x_box=X_BOX))
    post, inp = calibrate_joint(data, Priors(sigma_max=5.0), **NUTS)
    bands = predict_joint(post, inp, XG, n_draws=300)
    truth = 5 * torch.exp(-0.7 * XG[:, 0])
    assert _coverage(bands, truth) >= 0.9
    # the observation band is wider than the process band by about the noise
    width = (bands.obs_hi - bands.obs_lo) - (bands.hi - bands.lo)
    assert bool((width > 0).all())
