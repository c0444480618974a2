"""Sampling coordinates: the flow-stress map's inverse and Jacobian, and densities carried
through it (a flat prior sampled in flow-stress coordinates comes back flat)."""

import numpy as np
import pytest
import torch

from solderpyro.exact.amis import AmisOptions, TMixture, amis
from solderpyro.exact.coords import FlowStressCoords, UnitCoords, sampling_coords
from solderpyro.params import LIU2008, Box

BOX = Box(("s0", "QR", "xi", "m", "T_sf"), (5.0, 7000.0, 1.0, 0.05, 25.0),
          (25.0, 13000.0, 5.0, 0.5, 183.0))
FIXED = {k: LIU2008[k] for k in ("A", "s_hat", "n")}


def _points(n=200, seed=0):
    u = np.random.default_rng(seed).uniform(0.0, 1.0, (n, BOX.dim))
    return BOX.from_unit(torch.as_tensor(u)).numpy()


def test_flow_stress_inverse_round_trips():
    fc = FlowStressCoords(BOX, FIXED)
    x = _points()
    back = fc.from_w(fc.to_w(x))
    np.testing.assert_allclose(back, x, rtol=1e-10)
    assert fc.inside(fc.to_w(x)).all()
    assert fc.pass_through == (2, 3, 4)


def test_flow_stress_log_det_is_the_jacobian_determinant():
    fc = FlowStressCoords(BOX, FIXED)
    x = _points(12, 1)
    ld = fc.log_det(x)
    for xi, li in zip(x, ld, strict=True):
        assert li == pytest.approx(np.log(abs(np.linalg.det(fc.jac(xi)))), abs=1e-9)
    # and against central differences of to_w on the unit scale
    u = BOX.to_unit(torch.as_tensor(x[0])).numpy()
    D = np.empty((5, 5))
    for k in range(5):
        e = np.zeros(5)
        e[k] = 1e-6
        f = [fc.to_w(BOX.from_unit(torch.as_tensor(u + s * e)).numpy()[None])[0]
             for s in (1, -1)]
        D[:, k] = (f[0] - f[1]) / 2e-6
    np.testing.assert_allclose(fc.jac(x[0]), D, rtol=1e-6, atol=1e-8)


def test_points_outside_the_box_are_not_inside():
    fc = FlowStressCoords(BOX, FIXED)
    w = fc.to_w(_points(5, 2))
    w_out = w.copy()
    w_out[:, 2] = 1.3  # xi above its box
    assert not fc.inside(w_out).any()
    w_out = w.copy()
    w_out[:, 0] += 5.0  # a flow stress no s0 in the box gives
    assert not fc.inside(w_out).any()
    uc = UnitCoords(BOX)
    assert uc.inside(np.full((1, 5), 0.5)).all() and not uc.inside(np.full((1, 5), 1.1)).any()


def test_a_flat_prior_sampled_in_flow_stress_coordinates_comes_back_flat():
    """AMIS of the target 'prior only' in w: its weights carry 1/|det dw/du|, so the weighted
    samples are uniform on the unit cube (quantiles 0.1, 0.5, 0.9 of every coordinate, within
    Monte Carlo error). On a box around the reference constants (over the whole seed box the
    Jacobian spans decades and a flat target needs far more samples)."""
    box = Box(("s0", "QR", "xi", "m"), (10.0, 9500.0, 1.5, 0.08), (16.0, 11500.0, 2.5, 0.12))
    fc = FlowStressCoords(box, FIXED)
    u0 = np.random.default_rng(3).uniform(0.0, 1.0, (4000, 4))
    w0 = fc.to_w(box.from_unit(torch.as_tensor(u0)).numpy())
    q0 = TMixture.single(w0.mean(0), 1.5 * np.cov(w0.T), df=5.0)
    res = amis(lambda w: (-fc.log_det(fc.from_w(w)), {}), q0, 2000, 3, AmisOptions(seed=4),
               in_support=fc.inside)
    assert res.reliable, res.history
    u = box.to_unit(torch.as_tensor(fc.from_w(res.u))).numpy()
    wts = res.weights()
    se = np.sqrt(0.25 / res.ess)
    for k in range(4):
        o = np.argsort(u[:, k])
        cw = np.cumsum(wts[o])
        for q in (0.1, 0.5, 0.9):
            assert abs(u[o, k][np.searchsorted(cw, q)] - q) < 4 * se + 0.01, (k, q)


def test_sampling_coords_picks_flow_stress_when_it_can():
    assert isinstance(sampling_coords(BOX, FIXED), FlowStressCoords)
    other = Box(("a", "b"), (0.0, 0.0), (1.0, 1.0))
    assert type(sampling_coords(other, FIXED)) is UnitCoords
    assert type(sampling_coords(BOX, FIXED, "unit")) is UnitCoords
    with pytest.raises(ValueError, match="kind"):
        sampling_coords(BOX, FIXED, "polar")
