"""The power family's logarithm (solderpyro.effects.power.log_power): the closed form against
numpy, the exponential exact at n = 0, the series' derivative through 0, and finite gradients
where the branch not taken would be undefined."""

import numpy as np
import torch

from solderpyro.effects.power import N_SERIES, log_power

F64 = torch.float64


def test_log_power_is_log1p_over_n_and_z_at_zero():
    """Away from n = 0 it is numpy's log1p(n z) / n to 1e-15 relative (the same operations);
    at n = 0 it is z bit for bit; just below the switch it is within the series' truncation
    n^2 |z|^3 / 3 of the closed form (up to 1.7e-11 here; rounding of the closed form adds
    ~1e-16 |z|)."""
    z = torch.linspace(-0.45, 3.7, 50, dtype=F64)
    for n in (-1.0, -0.3, 0.5, 1.0, 2.0):
        nt = torch.full_like(z, n)
        ok = 1 + nt * z > 0
        ref = np.log1p(n * z.numpy()[ok.numpy()]) / n
        np.testing.assert_allclose(log_power(z, nt)[ok].numpy(), ref, rtol=1e-15, atol=0)
    assert torch.equal(log_power(z, torch.zeros_like(z)), z)
    n = torch.full_like(z, N_SERIES * (1 - 1e-3))
    closed = torch.log1p(n * z) / n
    bound = 1.01 * n * n * z.abs() ** 3 / 3 + 1e-15
    assert bool(((log_power(z, n) - closed).abs() <= bound).all())


def test_gradients_are_finite_where_the_closed_form_is_not_taken():
    """At n = 0 with z <= -1 (the modulus law's exponential far above 25 degC: log1p(z) is
    undefined there) the value is z and the gradients are d/dz = 1 - n z = 1 and
    d/dn = -z^2 / 2 exactly, not NaN."""
    z = torch.tensor([-1.0, -2.5, 0.3], dtype=F64, requires_grad=True)
    n = torch.zeros(3, dtype=F64, requires_grad=True)
    gz, gn = torch.autograd.grad(log_power(z, n).sum(), (z, n))
    assert torch.equal(gz, torch.ones(3, dtype=F64))
    assert torch.equal(gn, -z.detach() ** 2 / 2)
