"""The batched Levenberg-Marquardt of solderpyro.exact.fit: exact answers on small problems."""

import numpy as np
import pytest

from solderpyro.exact.fit import LMOptions, lm_fit

X = np.linspace(0.0, 3.0, 11)


def _exp(rows):
    return rows[:, :1] * np.exp(-rows[:, 1:2] * X[None])  # (N, 11)


def test_lm_recovers_a_nonlinear_fit_from_several_starts_at_once():
    """Noise-free y = 5 exp(-0.7 x): every start reaches (5, 0.7) to 1e-5 and chi2 ~ 0; a
    start whose 'free' set omits b keeps b and fits a alone (the profile of a)."""
    y = 5.0 * np.exp(-0.7 * X)
    x0 = np.array([[2.0, 0.2], [8.0, 1.5], [3.0, 1.0]])
    fits = lm_fit(_exp, x0, [0.1, 0.01], [10.0, 3.0], y, 0.1,
                  free=[np.array([0, 1]), np.array([0, 1]), np.array([0])],
                  options=LMOptions(iters=40))
    for f in fits[:2]:
        assert f.x == pytest.approx([5.0, 0.7], abs=1e-5) and f.chi2 < 1e-8
    assert fits[2].x[1] == 1.0  # b held
    a_hat = (y * np.exp(-X)).sum() / np.exp(-2 * X).sum()  # least squares in a at b = 1
    assert fits[2].x[0] == pytest.approx(a_hat, rel=1e-6)


def test_lm_stays_in_the_box_and_laplace_sd_matches_linear_regression():
    """A linear model y = c0 + c1 x: the Laplace sd equals the least-squares standard errors;
    with the optimum of c1 outside the box the fit stops on the bound."""
    rng = np.random.default_rng(0)
    y = 1.0 + 2.0 * X + 0.1 * rng.standard_normal(X.size)

    def lin(rows):
        return rows[:, :1] + rows[:, 1:2] * X[None]

    lo, hi = np.array([-5.0, -5.0]), np.array([5.0, 5.0])
    f = lm_fit(lin, np.array([[0.0, 0.0]]), lo, hi, y, 0.1, options=LMOptions(iters=30))[0]
    A = np.column_stack([np.ones_like(X), X])
    beta = np.linalg.lstsq(A, y, rcond=None)[0]
    se = 0.1 * np.sqrt(np.diag(np.linalg.inv(A.T @ A)))
    assert f.x == pytest.approx(beta, abs=1e-6)
    assert f.laplace_sd(lo, hi, 0.1) == pytest.approx(se, rel=1e-4)
    g = lm_fit(lin, np.array([[0.0, 0.0]]), lo, [5.0, 1.5], y, 0.1, options=LMOptions(iters=30))[0]
    assert g.x[1] == 1.5 and g.chi2 > f.chi2
    # on the bound the rest is the constrained optimum (c0 refitted with c1 held at 1.5)
    assert g.x[0] == pytest.approx(float(np.mean(y - 1.5 * X)), abs=1e-6)


def test_lm_rejects_bad_input():
    with pytest.raises(ValueError, match="sigma"):
        lm_fit(_exp, np.array([[1.0, 1.0]]), [0, 0], [2, 2], np.zeros(11), 0.0)
    with pytest.raises(ValueError, match="columns"):
        lm_fit(_exp, np.array([[1.0, 1.0, 1.0]]), [0, 0], [2, 2], np.zeros(11), 1.0)


def test_lm_tol_stops_each_start_when_converged_and_spends_no_more_rows_on_it():
    """With ``tol``, a start that has converged is not evaluated again: the noise-free fit
    still reaches (5, 0.7), a start already at the optimum stops after its first iteration, and
    the rows evaluated are fewer than with the fixed 40 iterations."""
    y = 5.0 * np.exp(-0.7 * X)
    n_rows = {"tol": 0, "fixed": 0}

    def counted(key):
        def f(rows):
            n_rows[key] += len(rows)
            return _exp(rows)
        return f

    x0 = np.array([[2.0, 0.2], [5.0, 0.7]])
    fits = lm_fit(counted("tol"), x0, [0.1, 0.01], [10.0, 3.0], y, 0.1,
                  options=LMOptions(iters=40, tol=1e-6))
    lm_fit(counted("fixed"), x0, [0.1, 0.01], [10.0, 3.0], y, 0.1, options=LMOptions(iters=40))
    assert fits[0].x == pytest.approx([5.0, 0.7], abs=1e-5) and fits[0].converged
    assert fits[1].converged and fits[1].iters == 0 and fits[1].chi2 < 1e-20
    assert n_rows["tol"] < n_rows["fixed"] / 2


def test_difference_jacobian_is_lm_fits_and_costs_one_call():
    """The Jacobian of one point equals the one an lm_fit iteration takes there (same steps,
    same unit-box scale; a backward step on the upper bound), in one call of 1 + p rows."""
    from solderpyro.exact.fit import difference_jacobian

    calls = []

    def f(rows):
        calls.append(len(rows))
        return _exp(rows)

    x = np.array([4.0, 3.0])  # b on its upper bound: a backward step
    jac = difference_jacobian(f, x, [0.1, 0.01], [10.0, 3.0])
    assert calls == [3]
    ref = lm_fit(_exp, x[None], [0.1, 0.01], [10.0, 3.0], np.zeros(11), 1.0,
                 options=LMOptions(iters=1))[0]
    np.testing.assert_array_equal(jac.J, ref.J)
    # the derivative itself: d(a e^{-bx})/db times the box width, to the step's O(h) error
    exact_b = -4.0 * X * np.exp(-3.0 * X) * (3.0 - 0.01)
    np.testing.assert_allclose(jac.J[:, 1], exact_b, rtol=5e-3, atol=1e-12)
