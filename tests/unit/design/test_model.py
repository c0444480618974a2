"""The surrogate seen by BoTorch (solderpyro.design.model): the input transform maps the unit
cube through the box to the GP's inputs, and observed_weights turns the GP coefficients'
variances into the noise-weighted code variance of the observed outputs. The BoTorch model
against the surrogate's predictive distribution is in tests/unit/design/test_loop.py."""

import pytest
import torch

from solderpyro.design.model import SurrogateInputs, observed_weights
from solderpyro.design.space_filling import lhs
from solderpyro.params import Box
from solderpyro.surrogate import GPOptions, GPSurrogate

F64 = torch.float64
BOX = Box(("s0", "A"), (5.0, 1e4), (25.0, 1e8), log_scale=(False, True))


@pytest.fixture(scope="module")
def gp():
    x = lhs(BOX, 14, seed=2)
    u = BOX.to_unit(x)
    y = torch.stack([torch.sin(2 * u[:, 0] + 0.3 * k) * (1 + k) + u[:, 1] * k
                     for k in range(6)], 1)  # (14, 6), output scales 1..6
    return GPSurrogate(BOX, output="pca", kernel="matern52", ard=False,
                       options=GPOptions(n_pc=2, restarts=1)).fit(x, y)


def test_observed_weights_sum_the_code_variance_of_the_outputs(gp):
    """sum_i var(eta_i) / sigma^2 from the surrogate's own predictive variances equals
    sum_k a_k var(z_k) + sum_i resid_i scale_i^2 / sigma^2 at any input (1e-10 relative:
    the same quantities summed in another order); a scales as 1/sigma^2."""
    sigma = 0.05
    a = observed_weights(gp, sigma)
    assert a.shape == (gp.basis.shape[1],) and bool((a > 0).all())
    x = lhs(BOX, 5, seed=9)
    _, var = gp.predict(x)  # (5, n_y), output units^2
    _, vc = gp.coefficients(x, False)  # (k, 5)
    resid = (gp.resid_var * gp.std.scale**2).sum() / sigma**2
    lhs_ = var.sum(1) / sigma**2
    rhs_ = (a[:, None] * vc).sum(0) + resid
    torch.testing.assert_close(lhs_, rhs_, rtol=1e-10, atol=0)
    torch.testing.assert_close(observed_weights(gp, 2 * sigma), a / 4, rtol=1e-15, atol=0)
    with pytest.raises(ValueError, match="sigma must be > 0"):
        observed_weights(gp, 0.0)


def test_input_transform_is_box_from_unit_then_the_gp_inputs(gp):
    """The unit-cube corners map to the box's corners (A through its logarithm: u = 0.5 is
    sqrt(1e4 1e8) = 1e6), and the transform equals gp.gp_inputs of the physical point."""
    tf = SurrogateInputs(gp)
    X = torch.tensor([[0.0, 0.0], [1.0, 1.0], [0.5, 0.5]], dtype=F64)
    phys = BOX.from_unit(X)
    torch.testing.assert_close(phys[:, 1], torch.tensor([1e4, 1e8, 1e6], dtype=F64),
                               rtol=1e-12, atol=0)
    torch.testing.assert_close(tf.transform(X), gp.gp_inputs(phys), rtol=0, atol=0)
    assert tf.equals(SurrogateInputs(gp)) and tf.equals(tf)
