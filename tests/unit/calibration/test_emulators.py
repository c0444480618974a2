"""What the likelihood sees of the computer model (solderpyro.calibration.emulators): the
direct function at the observation inputs, a scalar GP's (x, t) input layout, and additive
observation-side offsets that leave the code covariance alone. GP-backed emulators against
the surrogate are in tests/unit/calibration/test_koh_lowrank.py and
tests/unit/calibration/test_reduced.py."""

from types import SimpleNamespace

import pytest
import torch

from solderpyro.calibration.emulators import FunctionEmulator, GPEmulator, ObservedEmulator
from solderpyro.params import Box
from solderpyro.surrogate import GPSurrogate

F64 = torch.float64


def test_function_emulator_evaluates_the_model_exactly():
    x_obs = torch.tensor([[0.0], [1.0], [2.0]], dtype=F64)
    em = FunctionEmulator(lambda x, t: t[0] * x[:, 0] + t[1], x_obs)
    t = torch.tensor([2.0, -1.0], dtype=F64)
    m, c = em(t)
    assert c is None and torch.equal(m, torch.tensor([-1.0, 1.0, 3.0], dtype=F64))
    m2, _ = em(t, torch.tensor([[10.0]], dtype=F64))
    assert torch.equal(m2, torch.tensor([19.0], dtype=F64))


def test_scalar_gp_sees_x_columns_then_t():
    """The GP's input rows are (x_i, t) with t repeated per observation; the stand-in GP
    returns its inputs' row sums and a diagonal covariance of their first column."""
    gp = SimpleNamespace(model=object(), output="scalar",
                         mean_cov=lambda inp: (inp @ torch.tensor([1.0, 10.0, 100.0],
                                                                  dtype=F64),
                                               torch.diag(inp[:, 0])))
    x_obs = torch.tensor([[1.0], [2.0]], dtype=F64)
    em = GPEmulator(gp, x_obs)
    m, c = em(torch.tensor([3.0, 4.0], dtype=F64))
    assert torch.equal(m, torch.tensor([431.0, 432.0], dtype=F64))  # 1*x + 10*3 + 100*4
    assert torch.equal(c, torch.diag(x_obs[:, 0]))
    assert em.n_x == 1 and em.lowrank(torch.zeros(2, dtype=F64)) is None


def test_gp_emulator_rejects_unfitted_and_mismatched_layouts():
    box = Box(("t",), (0.0,), (1.0,))
    with pytest.raises(ValueError, match="gp must be fitted"):
        GPEmulator(GPSurrogate(box))
    pca = SimpleNamespace(model=object(), output="pca")
    with pytest.raises(ValueError, match="x_obs is only meaningful for a 'scalar'"):
        GPEmulator(pca, torch.zeros(2, 1, dtype=F64))
    em = GPEmulator(pca)
    with pytest.raises(ValueError, match="predicts the observed outputs only"):
        em(torch.zeros(1, dtype=F64), torch.zeros(1, 1, dtype=F64))


def test_observed_emulator_adds_the_offset_and_keeps_the_code_covariance():
    """t = (t_fe, q): mean(t_fe) + offset(q), the base's covariance unchanged; the low-rank
    form is shifted the same way (factor and diagonal unchanged), or None without one."""
    cov = torch.eye(3, dtype=F64) * 0.01
    F, d = torch.ones(3, 1, dtype=F64), torch.full((3,), 0.02, dtype=F64)

    class Base:
        def __call__(self, t, x=None):
            return t[0] * torch.arange(3.0, dtype=F64), cov

        def lowrank(self, t):
            return t[0] * torch.arange(3.0, dtype=F64), F, d

    x_pts = torch.tensor([0.0, 15.0, 15.0], dtype=F64)
    em = ObservedEmulator(Base(), 1, lambda q: q[0] + 1e-3 * q[1] * x_pts)
    t = torch.tensor([2.0, 0.3, 20.0], dtype=F64)
    m, c = em(t)
    torch.testing.assert_close(m, torch.tensor([0.3, 2.6, 4.6], dtype=F64), rtol=1e-15,
                               atol=1e-15)
    assert c is cov and em.x_obs is None
    mean, F1, d1 = em.lowrank(t)
    torch.testing.assert_close(mean, m, rtol=0, atol=0)
    assert F1 is F and d1 is d
    base_nolr = SimpleNamespace(__call__=None)
    assert ObservedEmulator(base_nolr, 1, lambda q: q).lowrank(t) is None
