"""The soft-walled flow-stress coordinates NUTS samples in (solderpyro.calibration.flowcoords):
a bijection onto the box whose log-Jacobian and analytic gradient are right."""

import math

import numpy as np
import pytest
from scipy import stats

from solderpyro.calibration.flowcoords import SoftFlowCoords, soft, soft_inverse
from solderpyro.calibration.nuts import NutsSettings, sample_nuts
from solderpyro.params import Box

BOX = Box(("s0", "QR", "xi", "m"), (5.0, 7000.0, 1.0, 0.05), (25.0, 13000.0, 5.0, 0.5))
FIXED = {"A": 4.0e6, "s_hat": 13.79, "n": 0.07}


def _fd(f, q, h=1e-6):
    return np.array([(f(q + h * e) - f(q - h * e)) / (2 * h) for e in np.eye(len(q))]).T


def test_soft_is_identity_inside_and_inverts():
    # 50 wall widths inside the interval the map is the identity to 1e-20 (e^-50)
    for q in (0.3, 0.5, 0.7):
        assert soft(q, 0.0, 1.0, 0.01)[0] == pytest.approx(q, abs=1e-15)
    for q in (-0.1, -0.02, 0.004, 0.5, 0.998, 1.03, 1.1):
        y = soft(q, 0.0, 1.0, 0.01)[0]
        assert 0.0 < y < 1.0
        assert soft_inverse(y, 0.0, 1.0, 0.01) == pytest.approx(q, abs=1e-9)


def test_soft_partials_match_finite_differences():
    for q in (-0.05, 0.002, 0.4, 0.995, 1.06):
        a, b, e = 0.1, 1.3, 0.02
        out = soft(q, a, b, e)
        base = (q, a, b, e)
        for k, arg in enumerate(base):
            def f(v, k=k, base=base):
                args = list(base)
                args[k] = v
                return np.array(soft(*args)[:2])
            d = (f(arg + 1e-7) - f(arg - 1e-7)) / 2e-7
            assert out[2 + k] == pytest.approx(d[0], rel=1e-5, abs=1e-8)
            assert out[6 + k] == pytest.approx(d[1], rel=1e-5, abs=1e-6)


@pytest.mark.parametrize("log_s0", [False, True])
def test_roundtrip_logdet_and_gradient(log_s0):
    box = Box(BOX.names, BOX.lower, BOX.upper, (log_s0, False, False, False))
    c = SoftFlowCoords(box, FIXED)
    rng = np.random.default_rng(0)
    gt = np.array([3.0, -2.0, 0.5, 7.0])
    for t in np.vstack([rng.uniform(0.001, 0.999, (6, 4)), [[0.5, 0.999, 0.2, 0.11]]]):
        q = c.inverse(t)
        t2, ld, vjp = c.forward(q)
        gq = vjp(gt)
        np.testing.assert_allclose(t2, t, atol=1e-10)
        J = _fd(lambda v: c.forward(v)[0], q)
        assert ld == pytest.approx(math.log(abs(np.linalg.det(J))), abs=1e-5)
        fd = _fd(lambda v: np.array([gt @ c.forward(v)[0] + c.forward(v)[1]]), q)[0]
        np.testing.assert_allclose(gq, fd, rtol=1e-5, atol=1e-5)
    # far outside the box's image: finite, maps onto the faces
    t, ld, vjp = c.forward(np.array([-40.0, 60.0, 3.0, -2.0]))
    gq = vjp(gt)
    assert np.isfinite(ld) and np.all(np.isfinite(gq))
    assert np.all((t >= 0) & (t <= 1))


def test_prior_density_is_uniform_on_the_box():
    """NUTS on the log-Jacobian alone (a flat likelihood) must give uniform t: a wrong
    log-Jacobian or gradient tilts the marginals (KS test per coordinate on 4 x 1600 draws
    thinned by 16: bulk ESS was 450-2700 of 8000 draws with these settings, so the thinned
    draws are near-independent; fails below p = 0.001)."""
    c = SoftFlowCoords(BOX, FIXED)

    def f(q):
        _, ld, vjp = c.forward(q)
        return ld, vjp(np.zeros(4))
    init = np.array([c.inverse(t) for t in ((0.3, 0.4, 0.5, 0.6), (0.6, 0.5, 0.4, 0.3),
                                            (0.5, 0.5, 0.5, 0.5), (0.2, 0.7, 0.3, 0.8))])
    res = sample_nuts(f, 4, NutsSettings(chains=4, warmup=300, draws=1600, seed=3), init=init)
    t = np.array([c.forward(q)[0] for q in res.draws[:, ::16].reshape(-1, 4)])
    for k in range(4):
        assert stats.kstest(t[:, k], "uniform").pvalue > 1e-3, k


def test_applies_names_what_is_missing():
    assert "QR" in SoftFlowCoords.applies(Box(("s0", "xi", "m"), (5, 1, .05), (25, 5, .5)),
                                          FIXED)
    assert "n" in SoftFlowCoords.applies(BOX, {"A": 4e6, "s_hat": 13.79})
    with pytest.raises(ValueError, match="not fixed"):
        SoftFlowCoords(BOX, {"A": 4e6, "s_hat": 13.79})
