"""The diagnosis's finite-difference Jacobians (diagnose.screen): steps stay in the box."""

import numpy as np
import pytest

from solderpyro.diagnose.screen import fd_design, fd_jacobians, fd_rows


def test_a_draw_on_a_bound_is_differenced_inside_the_box_and_exactly_for_a_linear_model():
    """A lag's split at its upper bound 0.5 (a recalibrated run's draw): no FE row may step
    past it (the effect refuses a split above 0.5), and the difference there, one-sided over
    the step, is still exact for outputs linear in the parameters; an interior draw keeps the
    central step (2 steps wide)."""
    cols = fd_design(["s0", "split"], [5.0, 0.0], [25.0, 0.5], {}, 1e-3)
    theta = np.array([[12.0, 0.5], [5.0, 0.25]])  # a split on its bound; s0 on its lower one
    rows, span = fd_rows(theta, np.zeros(0), cols)
    P = np.array(rows)
    assert np.all(P >= cols.lower) and np.all(P <= cols.upper)
    assert span[0, 1] == pytest.approx(1e-3 * 0.5) and span[1, 1] == pytest.approx(2e-3 * 0.5)
    assert span[1, 0] == pytest.approx(1e-3 * 20.0) and span[0, 0] == pytest.approx(2e-3 * 20)
    A = np.array([[1.5, -4.0], [0.2, 7.0], [3.0, 0.0]])  # (3 outputs, 2 parameters)
    V = P @ A.T
    Vb, J = fd_jacobians(V, span, cols)
    assert np.allclose(Vb, theta @ A.T)
    # differences of a linear model: exact up to rounding of values ~10 over steps ~5e-4
    assert np.allclose(J, np.broadcast_to(A, J.shape), rtol=0, atol=1e-9)
