"""The full joint's Kronecker likelihood (calibration.kronjoint) is the dense one.

On a product design (every parameter set run at the same input points) the Gaussian kernel's
simulation block is R_t (x) R_x; the likelihood computed through the two factors'
eigendecompositions and the n x n Schur complement must equal the dense (m + n) Cholesky of
koh.joint_loglik, value and gradient (torch autograd as the reference), to 1e-8 relative:
the covariance's condition number reaches ~1e8 (the 1e-6 nugget), so the two factorizations
agree to ~1e-8 at worst and to ~1e-11 typically.
"""

import numpy as np
import pytest
import torch
from scipy.stats import qmc

from solderpyro.calibration import CalibrationData, Priors
from solderpyro.calibration.data import InputAxes
from solderpyro.calibration.fastkoh import joint_flat
from solderpyro.calibration.koh import joint_loglik, prepare_joint
from solderpyro.calibration.kronjoint import MIN_RUNS, KronJoint, kron_joint, product_design
from solderpyro.params import Box

DT = torch.float64
REL = 1e-8


def _product_data(mt: int, mx: int, p: int, nx: int, n: int = 5, seed: int = 0,
                  drop: int = 0) -> CalibrationData:
    """``mt`` parameter sets (LHS) each run at the same ``mx`` input points, rows shuffled
    (the structure is found, not assumed from the order); ``drop`` runs removed at the end."""
    rng = np.random.default_rng(seed)
    t = qmc.LatinHypercube(d=p, seed=seed).random(mt)
    x = qmc.LatinHypercube(d=nx, seed=seed + 1).random(mx)
    ts, xs = np.repeat(t, mx, 0), np.tile(x, (mt, 1))
    perm = rng.permutation(mt * mx)[: mt * mx - drop]
    ts, xs = ts[perm], xs[perm]

    def f(xx: np.ndarray, tt: np.ndarray) -> np.ndarray:
        return np.sin(3.0 * xx.sum(1)) * np.exp(-tt.sum(1)) + xx[:, 0] * tt[:, 0]

    xo = rng.random((n, nx))
    yo = f(xo, np.full((n, p), 0.4)) + 0.01 * rng.standard_normal(n)
    xb = Box(tuple(f"x{i}" for i in range(nx)), (0.0,) * nx, (1.0,) * nx)
    tb = Box(tuple(f"t{i}" for i in range(p)), (0.0,) * p, (1.0,) * p)

    def tt(a: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(a, dtype=DT)

    return CalibrationData.create(tt(xs), tt(ts), tt(f(xs, ts)), tt(xo), tt(yo),
                                  InputAxes(list(xb.names), list(tb.names), theta_box=tb,
                                            x_box=xb))


def _points(inp, p: int, k: int = 4, seed: int = 1) -> list[np.ndarray]:
    """Constrained flat vectors (t_unit, sigma, sigma_c, corr): small and large noise, short
    and long correlation lengths."""
    rng = np.random.default_rng(seed)
    return [np.concatenate([rng.random(p), [0.005 + 0.1 * rng.random(), 0.3 + 2 * rng.random()],
                            0.2 + 4.0 * rng.random(inp.n_corr)]) for _ in range(k)]


def _torch_reference(inp, x: np.ndarray, p: int) -> tuple[float, np.ndarray]:
    """koh.joint_loglik (dense Cholesky) and its autograd gradient at ``x``."""
    xt = torch.tensor(x, dtype=DT, requires_grad=True)
    ll = joint_loglik(inp, xt[:p], xt[p], xt[p + 1], xt[p + 2:])[0]
    ll.backward()
    return float(ll.detach()), xt.grad.numpy()


@pytest.mark.parametrize("mt,mx,p,nx,ard", [(8, 9, 1, 1, False), (8, 9, 1, 1, True),
                                             (6, 7, 2, 2, True), (6, 7, 2, 2, False)])
def test_kronecker_likelihood_equals_the_dense_one(mt, mx, p, nx, ard):
    inp = prepare_joint(_product_data(mt, mx, p, nx), ard=ard)
    kron = kron_joint(inp, force=True)
    assert isinstance(kron, KronJoint)
    dense = joint_flat(inp, Priors(), structure="dense")
    for x in _points(inp, p):
        ll, g = kron(x)
        ll_ref, g_ref = _torch_reference(inp, x, p)
        assert abs(ll - ll_ref) <= REL * max(1.0, abs(ll_ref))
        assert np.abs(g - g_ref).max() <= REL * max(1.0, np.abs(g_ref).max())
        ll_d, g_d = dense.loglik(x)
        assert abs(ll - ll_d) <= REL * max(1.0, abs(ll_d))
        assert np.abs(g - g_d).max() <= REL * max(1.0, np.abs(g_d).max())


def test_beta_moments_equal_the_dense_ones():
    """beta | rest (mean and variance, standardized units) as koh.joint_loglik gives them."""
    inp = prepare_joint(_product_data(8, 9, 1, 1))
    kron = kron_joint(inp, force=True)
    for x in _points(inp, 1, 3):
        bm, bv = kron.beta(x)
        xt = torch.tensor(x, dtype=DT)
        _, b_ref, v_ref = joint_loglik(inp, xt[:1], xt[1], xt[2], xt[3:])
        assert abs(bm - float(b_ref[0])) <= REL * max(1.0, abs(float(b_ref[0])))
        assert abs(bv - float(v_ref[0, 0])) <= REL * abs(float(v_ref[0, 0]))


def test_the_structure_is_found_only_on_a_product_design():
    full = _product_data(6, 7, 2, 2)
    u = prepare_joint(full).u_sim.numpy()
    des = product_design(u, 2)
    assert des is not None and des.t.shape == (6, 2) and des.x.shape == (7, 2)
    # the order puts the runs on the grid: parameter set major
    grid = u[des.order]
    assert np.array_equal(grid[:, 2:], np.repeat(des.t, 7, 0))
    assert np.array_equal(grid[:, :2], np.tile(des.x, (6, 1)))
    # a missing run, a repeated run, a Latin hypercube: not a product design
    assert product_design(prepare_joint(_product_data(6, 7, 2, 2, drop=1)).u_sim.numpy(),
                          2) is None
    assert product_design(np.concatenate([u, u[:1]]), 2) is None
    lhs = qmc.LatinHypercube(d=3, seed=0).random(40)
    assert product_design(lhs, 1) is None
    # no input columns: nothing to factor
    assert product_design(u[:, 2:], 0) is None


def test_joint_flat_chooses_the_kronecker_form_by_size_and_says_when_it_cannot():
    small = prepare_joint(_product_data(8, 9, 1, 1))  # 72 runs < MIN_RUNS
    assert not isinstance(joint_flat(small, Priors()).loglik, KronJoint)
    assert isinstance(joint_flat(small, Priors(), structure="kronecker").loglik, KronJoint)
    big = prepare_joint(_product_data(12, 12, 1, 1))  # 144 runs
    assert big.u_sim.shape[0] >= MIN_RUNS
    assert isinstance(joint_flat(big, Priors()).loglik, KronJoint)
    assert not isinstance(joint_flat(big, Priors(), structure="dense").loglik, KronJoint)
    broken = prepare_joint(_product_data(12, 12, 1, 1, drop=3))
    assert not isinstance(joint_flat(broken, Priors()).loglik, KronJoint)
    with pytest.raises(ValueError, match="product design"):
        joint_flat(broken, Priors(), structure="kronecker")
    with pytest.raises(ValueError, match="structure"):
        joint_flat(big, Priors(), structure="sparse")
    # options the Kronecker form does not cover (a discrepancy) are not given it
    assert kron_joint(prepare_joint(_product_data(12, 12, 1, 1), discrepancy=True)) is None


def test_a_non_positive_covariance_is_zero_density():
    inp = prepare_joint(_product_data(8, 9, 1, 1))
    kron = kron_joint(inp, force=True)
    x = _points(inp, 1, 1)[0]
    x[2] = 0.0  # sigma_c = 0: A is singular
    ll, g = kron(x)
    assert ll == -np.inf and not g.any()
    x = _points(inp, 1, 1)[0]
    x[3] = np.nan  # a non-finite correlation parameter (as a diverging trajectory may give)
    ll, g = kron(x)
    assert ll == -np.inf and not g.any()


def test_calibrate_joint_on_a_product_design_recovers_the_parameter():
    """End to end through the default path (the structure found, nothing passed): 12 x 12 runs
    of a smooth code, 5 observations at t = 0.4 with noise sd 0.01; the 95 % interval of t
    holds 0.4, the chains agree, and beta's draws (from the Kronecker factors) are finite."""
    from solderpyro.calibration import calibrate_joint

    data = _product_data(12, 12, 1, 1)
    assert kron_joint(prepare_joint(data)) is not None
    post, _ = calibrate_joint(data, Priors(sigma_max=1.0), chains=2, warmup=200, draws=200,
                              seed=0, progress=False, workers=1)
    t = post.samples["t"].reshape(-1)
    lo, hi = torch.quantile(t, torch.tensor([0.025, 0.975], dtype=t.dtype)).tolist()
    assert lo <= 0.4 <= hi and hi - lo < 0.15  # measured 0.378-0.424; the prior is 0-1
    assert max(r["r_hat"] for r in post.summary()) < 1.05
    assert torch.isfinite(post.samples["beta"]).all()
