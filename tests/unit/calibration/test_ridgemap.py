"""The ridge map (solderpyro.calibration.ridgemap): an exact change of variables, and NUTS in
its coordinates samples the same curved posterior with fewer gradients."""

from __future__ import annotations

import math

import arviz as az
import numpy as np
import pytest

from solderpyro.calibration.mcmc import WarmStart, chains_agree, ridge_map
from solderpyro.calibration.nuts import NutsSettings, sample_nuts
from solderpyro.calibration.ridgemap import MIN_DRAWS, RidgeMap

TOL = 4.5  # Monte Carlo standard errors


def _banana(q: np.ndarray) -> tuple[float, np.ndarray]:
    """x ~ N(0, 1), y | x ~ N(x^2 / 2, 0.05^2), z ~ N(x, 1): a thin curved ridge in (x, y).
    E[y] = 0.5, Var(y) = 0.5 + 0.0025, E[z] = 0, Var(z) = 2."""
    x, y, z = q
    r = (y - 0.5 * x * x) / 0.05**2
    lp = -0.5 * x * x - 0.5 * r * (y - 0.5 * x * x) - 0.5 * (z - x) ** 2
    return lp, np.array([-x + r * x + (z - x), -r, -(z - x)])


def _exact_draws(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = rng.standard_normal(n)
    return np.stack([x, 0.5 * x * x + 0.05 * rng.standard_normal(n),
                     x + rng.standard_normal(n)], 1)


def test_the_map_is_an_exact_volume_preserving_bijection_with_the_right_gradient():
    """forward(inverse(q)) = q; the Jacobian dq/dw is triangular with det = prod(sd) at any
    point (in the draws or far outside them), so the density is unchanged up to a constant;
    vjp is J^T g by central differences."""
    Q = _exact_draws(800, 1) * np.array([1.0, 30.0, 0.2]) + np.array([0.0, 5.0, -1.0])
    m = RidgeMap(Q)
    rng = np.random.default_rng(2)
    for q in (Q[7], Q[500], m.mean + m.sd * np.array([6.0, -9.0, 4.0])):
        w = m.inverse(q)
        np.testing.assert_allclose(m.forward(w)[0], q, rtol=0, atol=1e-10)
        h = 1e-6
        J = np.stack([(m.forward(w + h * e)[0] - m.forward(w - h * e)[0]) / (2 * h)
                      for e in np.eye(3)], 1)  # (3, 3): dq_i / dw_j
        assert np.allclose(np.triu(J, 1), 0.0, atol=1e-8)
        assert math.isclose(np.linalg.det(J), float(np.prod(m.sd)), rel_tol=1e-6)
        g = rng.standard_normal(3)
        np.testing.assert_allclose(m.vjp(m.forward(w)[1], g), J.T @ g, rtol=1e-6, atol=1e-8)
    # the fitted curve is the ridge: what is left of y is its thin noise
    W = m.inverse(Q)
    assert W[:, 1].std() < 0.1  # the ridge's 0.05 of y's sd ~0.71, in sd units of y


def test_native_map_equals_numpy():
    """The C forward and vjp (the sampler's path through :meth:`RidgeMap.wrap`) give the
    NumPy ones to rounding, inside the draws and far outside (where h bends), on a map with
    curved and straight coordinates."""
    from solderpyro import _native

    if _native.library() is None:
        pytest.skip("no C compiler: the native kernels are unavailable")
    rng = np.random.default_rng(4)
    X = _exact_draws(800, 3)
    Q = np.concatenate([X, (X[:, :1] + 0.3 * rng.standard_normal((800, 1))),
                        rng.standard_normal((800, 1))], 1) * np.array([1.0, 30.0, 0.2, 2.0, 1.0])
    m = RidgeMap(Q)
    assert any(m.curved) and not all(m.curved[1:])
    k = m.native()
    for w in [*m.inverse(Q[::97]), *(8.0 * rng.standard_normal((5, 5)))]:
        q, z = m.forward(w)
        q2, z2 = k.forward(w)
        np.testing.assert_allclose(q2, q, rtol=1e-14, atol=1e-13 * np.abs(q).max())
        np.testing.assert_allclose(z2, z, rtol=1e-14, atol=1e-13 * np.abs(z).max())
        g = rng.standard_normal(5)
        want = m.vjp(z, g)
        np.testing.assert_allclose(k.vjp(z, g), want, rtol=1e-13, atol=1e-13 * np.abs(want).max())
    lp, g = m.wrap(_banana_5)(m.inverse(Q[3]))
    assert np.isfinite(lp) and g.shape == (5,)


def _banana_5(q: np.ndarray) -> tuple[float, np.ndarray]:
    lp, g = _banana(q[:3])
    return lp - 0.5 * float(q[3:] @ q[3:]), np.concatenate([g, -q[3:]])


def test_nuts_in_ridge_coordinates_samples_the_banana_where_plain_nuts_diverges():
    """On a thin curved ridge, NUTS in the map's coordinates (fitted to 1,000 independent
    draws) gets E and Var of y and z within 4.5 MCSEs of the exact values, with fewer divergent
    transitions and at most half the gradients per iteration of NUTS in the original
    coordinates. (That one under-explores the ridge's arms where it diverges: measured on this
    project's machine, mean y 0.30-0.35 against 0.5 over seeds 5-7, 8-14 MCSEs
    off, with 29-38 divergent transitions in 4 x 1500 iterations; on an earlier machine it
    happened to pass. Its bias is the reason for the map, so it is not asserted either way.)"""
    m = RidgeMap(_exact_draws(1000, 3))
    W = m.inverse(_exact_draws(1000, 4))
    ns = NutsSettings(chains=4, warmup=500, draws=1000, seed=5, dense_mass=True)
    plain = sample_nuts(_banana, 3, ns)
    mapped = sample_nuts(m.wrap(_banana), 3, ns, init=W[:4], inv_metric=np.cov(W.T))
    Q = m.forward(mapped.draws)[0]
    y, z = Q[..., 1], Q[..., 2]
    for a, ref in ((y, 0.5), ((y - 0.5) ** 2, 0.5025), (z, 0.0), (z * z, 2.0)):
        se = float(a.std() / math.sqrt(float(az.ess(a, method="bulk"))))
        assert abs(a.mean() - ref) < TOL * se, (a.mean(), ref, se)
    assert sum(mapped.divergences) < sum(plain.divergences), (mapped.divergences,
                                                               plain.divergences)
    per_it = [sum(r.n_leapfrog) / (4 * 1500) for r in (plain, mapped)]
    assert per_it[1] < 0.5 * per_it[0], per_it


def test_a_warm_state_keeps_its_draws_and_maps_only_the_same_coordinates(tmp_path):
    D = _exact_draws(MIN_DRAWS, 5)
    ws = WarmStart(["x", "y", "z"], D[:4], np.eye(3), 0.4, draws=D)
    back = WarmStart.load(ws.save(tmp_path / "s.npz"))
    np.testing.assert_array_equal(back.draws, D)
    assert isinstance(ridge_map(back, ["x", "y", "z"]), RidgeMap)
    assert ridge_map(back, ["x", "y", "k_E"]) is None  # another model: no map
    # a straight (Gaussian, correlated) posterior: no bend, the dense metric's job, no map
    rng = np.random.default_rng(6)
    G = rng.standard_normal((1000, 3)) @ np.array([[1.0, 0.9, 0.0], [0.0, 0.3, 0.5],
                                                   [0.0, 0.0, 1.0]])
    assert not any(RidgeMap(G).curved)
    assert ridge_map(WarmStart(["x", "y", "z"], G[:4], np.eye(3), 0.4, draws=G),
                     ["x", "y", "z"]) is None
    assert RidgeMap(_exact_draws(1000, 7)).curved[1]  # the banana's y is bent
    assert ridge_map(WarmStart(["x", "y", "z"], D[:4], np.eye(3), 0.4, draws=D[:50]),
                     ["x", "y", "z"]) is None  # too few draws
    with pytest.raises(ValueError, match="RidgeMap needs draws"):
        RidgeMap(D[:10])


def test_draws_of_chains_in_separate_modes_are_not_kept_for_a_map():
    """A map is fitted only to chains that describe one posterior: four chains of the same
    normal agree; one of them three sd away (an island) does not (R-hat > 1.1)."""
    rng = np.random.default_rng(0)
    d = rng.standard_normal((4, 200, 3))
    assert chains_agree(d)
    d[1] += 3.0
    assert not chains_agree(d)
    assert not chains_agree(d[:1])  # one chain: R-hat undefined, no map
