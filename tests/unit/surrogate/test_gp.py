"""GPSurrogate: transforms, agreement with GPyTorch's own predictive, layouts, validation."""

import gpytorch
import pytest
import torch
from scipy.stats import qmc

from solderpyro.params import Box
from solderpyro.surrogate import GPOptions, GPSurrogate, SurrogateWarning

BOX = Box(("x", "t"), (0.0, 0.2), (3.0, 1.5), (False, True))


def _f(X):
    return 5.0 * torch.exp(-X[:, 1] * X[:, 0])


def _design(n, seed=1):
    u = torch.as_tensor(qmc.LatinHypercube(d=2, seed=seed).random(n), dtype=torch.float64)
    return BOX.from_unit(u)


def test_box_round_trip_and_log_scale():
    x = _design(10)
    assert torch.allclose(BOX.from_unit(BOX.to_unit(x)), x, rtol=1e-13, atol=0)
    u = BOX.to_unit(torch.tensor([[1.5, (0.2 * 1.5) ** 0.5]], dtype=torch.float64))
    assert torch.allclose(u, torch.tensor([[0.5, 0.5]], dtype=torch.float64), atol=1e-14)
    with pytest.raises(ValueError, match="log scale needs lower > 0"):
        Box(("a",), (0.0,), (1.0,), (True,))
    with pytest.raises(ValueError, match="lower 2.0 must be < upper 1.0"):
        Box(("a",), (2.0,), (1.0,))


@pytest.mark.parametrize("kernel", ["gaussian", "matern52"])
def test_frozen_predictor_matches_gpytorch(kernel):
    """Our plain-torch prediction equals GPyTorch's exact predictive (standardized space)."""
    x = _design(15)
    gp = GPSurrogate(BOX, kernel=kernel, ard=True).fit(x, _f(x))
    xt = _design(7, seed=5)
    with torch.no_grad(), gpytorch.settings.fast_pred_var(False), \
            gpytorch.settings.fast_computations(False, False, False):
        ref = gp.model(BOX.to_unit(xt).expand(1, 7, 2))
    m, c = gp.coefficients(xt, full_cov=True)
    assert torch.allclose(m, ref.mean, atol=1e-8)
    assert torch.allclose(c, ref.covariance_matrix, atol=1e-8)


def test_accuracy_and_loo_on_smooth_function():
    x = _design(30)
    gp = GPSurrogate(BOX, ard=True).fit(x, _f(x))
    xt = _design(200, seed=7)
    held = gp.validate(xt, _f(xt))
    assert held.rmse_rel < 0.05, held.rmse_rel
    assert held.coverage95 >= 0.85, held.coverage95
    loo = gp.loo()
    assert loo.coverage95 >= 0.8 and loo.rmse_rel < 0.1


def test_mean_cov_consistent_and_differentiable():
    x = _design(15)
    gp = GPSurrogate(BOX).fit(x, _f(x))
    xt = _design(4, seed=3)
    m, c = gp.mean_cov(xt)
    pm, pv = gp.predict(xt)
    assert torch.allclose(m, pm, atol=1e-12) and torch.allclose(c.diagonal(), pv, atol=1e-10)
    xt = xt.clone().requires_grad_(True)
    gp.mean_cov(xt)[0].sum().backward()
    h = 1e-6
    e = torch.zeros_like(xt)
    e[1, 1] = h
    fd = (gp.mean_cov(xt.detach() + e)[0].sum() - gp.mean_cov(xt.detach() - e)[0].sum()) / (2 * h)
    assert torch.isclose(xt.grad[1, 1], fd, rtol=1e-5)


def test_pca_recovers_low_rank_outputs_and_batched_agrees():
    x = _design(25)
    a, b = _f(x), torch.sin(2 * x[:, 0]) + x[:, 1]
    v1 = torch.linspace(0, 1, 12, dtype=torch.float64)
    v2 = torch.cos(torch.arange(12, dtype=torch.float64))
    y = a[:, None] * v1 + b[:, None] * v2 + 3.0  # rank 2 plus a constant
    pca = GPSurrogate(BOX, output="pca").fit(x, y)
    assert pca.basis.shape[1] == 2
    assert float(pca.resid_var.max()) < 1e-20
    bat = GPSurrogate(BOX, output="batched").fit(x, y)
    xt = _design(50, seed=9)
    yt = _f(xt)[:, None] * v1 + (torch.sin(2 * xt[:, 0]) + xt[:, 1])[:, None] * v2 + 3.0
    for g in (pca, bat):
        r = g.validate(xt, yt)
        assert r.rmse_rel < 0.05, (g.output, r.rmse_rel)
    m, c = pca.mean_cov(xt[:2])
    assert m.shape == (24,) and c.shape == (24, 24)
    assert torch.linalg.eigvalsh(c).min() > -1e-8 * c.diagonal().max()


def test_untrustworthy_surrogate_warns():
    x = _design(4)
    rough = torch.tensor([0.0, 10.0, -10.0, 5.0], dtype=torch.float64)
    gp = GPSurrogate(BOX).fit(x, rough)
    xt = _design(40, seed=2)
    res = gp.validate(xt, torch.sin(40 * xt[:, 0]) * 10)
    with pytest.warns(SurrogateWarning, match="not trustworthy"):
        gp.check(res)


def test_bad_input_names_argument():
    gp = GPSurrogate(BOX)
    with pytest.raises(ValueError, match=r"x must have shape \(n, 2\)"):
        gp.fit(torch.zeros(5, 3, dtype=torch.float64), torch.zeros(5, dtype=torch.float64))
    with pytest.raises(ValueError, match="y contains NaN"):
        gp.fit(_design(5), torch.tensor([1.0, float("nan"), 0, 0, 0], dtype=torch.float64))
    with pytest.raises(ValueError, match="x has 5 rows but y has 4"):
        gp.fit(_design(5), torch.zeros(4, dtype=torch.float64))
    with pytest.raises(ValueError, match="kernel='rbf'"):
        GPSurrogate(BOX, kernel="rbf")
    with pytest.raises(RuntimeError, match="must be called before"):
        gp.predict(_design(2))


def test_box_maps_have_finite_gradients_for_large_linear_values():
    """exp() of a large linear-scale value must not poison gradients (QR ~ 1e4 K)."""
    box = Box(("s0", "QR", "m"), (5.0, 7000.0, 0.05), (25.0, 13000.0, 0.5), (False, False, True))
    u = torch.full((3,), 0.5, dtype=torch.float64, requires_grad=True)
    box.from_unit(u).sum().backward()
    assert torch.isfinite(u.grad).all()
    x = torch.tensor([10.0, 9000.0, 0.1], dtype=torch.float64, requires_grad=True)
    box.to_unit(x).sum().backward()
    assert torch.isfinite(x.grad).all()


def test_pca_keeps_components_until_the_truncation_chi_square_is_below_its_bound():
    """resid_chi2 with noise_sd: the PCs kept leave at most resid_chi2 noise variances of
    truncation variance over the outputs, and one component fewer would leave more."""
    from solderpyro.design import lhs
    from solderpyro.params import ParameterSpace

    box = ParameterSpace.seed()
    x = lhs(box, 44, 0)
    u = box.to_unit(x)
    y = torch.stack([torch.sin(3 * u[:, 0] + k / 10) * (1 + u[:, 1])
                     + 0.01 * k * u[:, 2] ** 2 * u[:, 3] + 1e-3 * torch.cos(7 * u[:, 3] * k)
                     for k in range(30)], 1)
    plain = GPSurrogate(box, output="pca", options=GPOptions(restarts=1)).fit(x, y)
    sd, tol = 1e-3, 5.0
    gp = GPSurrogate(box, output="pca",
                     options=GPOptions(resid_chi2=tol, noise_sd=sd, restarts=1)).fit(x, y)

    def left(g):
        return float((g.resid_var * g.std.scale**2).sum() / sd**2)

    k = gp.basis.shape[1]
    assert left(plain) > tol >= left(gp) and k > plain.basis.shape[1]
    fewer = GPSurrogate(box, output="pca", options=GPOptions(n_pc=k - 1, restarts=1)).fit(x, y)
    assert left(fewer) > tol
    # never more components than half the runs
    few = GPSurrogate(box, output="pca",
                      options=GPOptions(resid_chi2=0.01, noise_sd=sd, restarts=1)).fit(
        x[:12], y[:12])
    assert few.basis.shape[1] == 6 and left(few) > 0.01
    with pytest.raises(ValueError, match="go together"):
        GPOptions(noise_sd=0.1)


_FIT = """
import sys, torch
if sys.argv[1] == "botorch":
    import botorch  # noqa: F401  (sets linear_operator's global defaults at import)
from scipy.stats import qmc
from linear_operator import settings as ls
from solderpyro.params import Box
from solderpyro.surrogate import GPSurrogate
box = Box(("x", "t"), (0.0, 0.2), (3.0, 1.5), (False, True))
x = box.from_unit(torch.as_tensor(qmc.LatinHypercube(d=2, seed=1).random(40)))
y = torch.stack([5.0 * torch.exp(-x[:, 1] * x[:, 0]) + 0.1 * k * x[:, 0] for k in range(3)], 1)
gp = GPSurrogate(box, output="batched", kernel="matern52", ard=True).fit(x, y)
m, v = gp.predict(box.from_unit(torch.rand(9, 2, generator=torch.Generator().manual_seed(0),
                                           dtype=torch.float64)))
print(repr([ls.max_cholesky_size.value(), ls._fast_solves.on(), ls.cholesky_max_tries.value()]))
print(repr(m.flatten().tolist() + v.flatten().tolist()))
"""


def test_gp_fit_does_not_depend_on_whether_botorch_was_imported():
    """Importing BoTorch sets linear_operator's global defaults (Cholesky to 4,096 rows, no
    fast solves); the fit runs in a context with the same values
    (:func:`~solderpyro.surrogate.exact_linear_algebra`), so a fit in an interpreter that
    imported BoTorch first is identical to one that did not, and without BoTorch the
    interpreter keeps GPyTorch's own defaults."""
    import subprocess
    import sys

    out = [subprocess.run([sys.executable, "-c", _FIT, arg], capture_output=True, text=True,
                          check=True).stdout.splitlines() for arg in ("plain", "botorch")]
    assert out[0][0] == "[800, True, 3]" and out[1][0] == "[4096, False, 6]"
    assert out[0][1] == out[1][1]


@pytest.mark.parametrize("kernel", ["matern52", "gaussian"])
@pytest.mark.parametrize("mean", ["constant", "linear"])
@pytest.mark.parametrize("ard", [True, False])
def test_analytic_mll_closure_equals_gpytorch_autograd(kernel, mean, ard):
    """The fit's closure (solderpyro.surrogate.mll: NumPy/LAPACK loss and analytic gradient)
    gives GPyTorch's ExactMarginalLogLikelihood loss and its autograd gradient in every raw
    parameter, to 1e-11 relative, at hyperparameters away from their initial values."""
    from solderpyro.surrogate.gp import BatchGP
    from solderpyro.surrogate.mll import mll_closure

    g = torch.Generator().manual_seed(3)
    x = torch.rand(1, 40, 3, generator=g, dtype=torch.float64).expand(4, 40, 3)
    z = torch.sin(4 * x[..., 0]) + torch.randn(4, 40, generator=g, dtype=torch.float64)
    m = BatchGP(x, z, kernel, mean, ard, 1e-6).double()
    with torch.no_grad():
        for p in m.parameters():
            p.add_(0.5 * torch.randn(p.shape, generator=g, dtype=torch.float64))
    m.train()
    mll = gpytorch.mlls.ExactMarginalLogLikelihood(m.likelihood, m)
    opt = torch.optim.LBFGS(m.parameters())

    def autograd_closure():
        opt.zero_grad()
        loss = -mll(m(x), z).sum()
        loss.backward()
        return loss

    want = float(autograd_closure().detach())
    g_want = [p.grad.clone() for p in m.parameters()]
    got = float(mll_closure(m, opt, autograd_closure)())
    assert abs(got - want) <= 1e-11 * abs(want)
    for a, b in zip([p.grad for p in m.parameters()], g_want, strict=True):
        assert float((a - b).abs().max()) <= 1e-10 * float(b.abs().max()) + 1e-14


def test_analytic_mll_closure_falls_back_where_cholesky_fails():
    """Duplicate training inputs and an outputscale 1e12 times the noise: K is singular in
    float64, LAPACK's factorization fails, and the closure returns GPyTorch's own (jittered)
    evaluation instead of raising."""
    from solderpyro.surrogate.gp import BatchGP
    from solderpyro.surrogate.mll import mll_closure

    x = torch.rand(1, 10, 2, dtype=torch.float64)
    x = torch.cat([x, x], 1).expand(2, 20, 2)
    z = torch.randn(2, 20, dtype=torch.float64)
    m = BatchGP(x, z, "gaussian", "constant", True, 1e-6).double()
    m.covar_module.outputscale = 1e12
    m.likelihood.noise = 1e-6
    m.train()
    opt = torch.optim.LBFGS(m.parameters())
    called = []

    def fallback():
        called.append(1)
        return torch.tensor(7.0, dtype=torch.float64)

    assert float(mll_closure(m, opt, fallback)()) == 7.0 and called


@pytest.mark.parametrize("kernel", ["gaussian", "matern52"])
def test_the_factors_reproduce_the_coefficients_predictive(kernel):
    """GPFactors is what prediction outside the class needs: the prior mean plus
    ``K(u*, u) alpha`` and ``outputscale - |L^-1 K(u, u*)|^2`` rebuilt from the factors equal
    :meth:`GPSurrogate.coefficients` (same float64 arithmetic, so to rounding: 1e-12), and the
    factors' training inputs are the GP inputs of the training runs."""
    x = _design(15)
    gp = GPSurrogate(BOX, kernel=kernel, mean="linear", ard=True,
                     options=GPOptions(restarts=1)).fit(x, _f(x))
    f = gp.factors()
    k, n = f.z.shape
    assert (k, n) == (1, 15) and f.u.shape == (1, 15, 2) and f.chol.shape == (1, 15, 15)
    assert f.lengthscale.shape == (1, 2) and f.mean_weights is not None
    assert gp.input_scaling is None
    torch.testing.assert_close(gp.x_train, x, rtol=0, atol=0)
    torch.testing.assert_close(gp.y_train[:, 0], _f(x), rtol=0, atol=0)
    torch.testing.assert_close(f.u[0], gp.gp_inputs(x), rtol=0, atol=0)
    xt = _design(6, seed=4)
    ut = gp.gp_inputs(xt).expand(k, 6, 2)
    ks = f.outputscale[:, None, None] * gp.correlation(ut, f.u)  # (k, 6, n)
    prior = f.mean_const[:, None] + (ut * f.mean_weights[:, None, :]).sum(-1)
    v = torch.linalg.solve_triangular(f.chol, ks.transpose(-1, -2), upper=False)
    mc, vc = gp.coefficients(xt)
    torch.testing.assert_close(mc, prior + (ks * f.alpha[:, None, :]).sum(-1), rtol=0,
                               atol=1e-12)
    torch.testing.assert_close(vc, (f.outputscale[:, None] - v.square().sum(-2)).clamp_min(0),
                               rtol=0, atol=1e-12)
    # L L^T is the training covariance with its noise
    kxx = f.outputscale[:, None, None] * gp.correlation(f.u, f.u) \
        + f.noise[:, None, None] * torch.eye(n, dtype=torch.float64)
    torch.testing.assert_close(f.chol @ f.chol.transpose(-1, -2), kxx, rtol=0, atol=1e-12)


def test_an_input_maps_scaling_is_the_gp_inputs():
    """With an input map the GP inputs are ``(inputs(x) - lo) / span`` for the published
    ``input_scaling``, and before a fit the factors are refused."""
    gp = GPSurrogate(BOX, options=GPOptions(restarts=1),
                     inputs=lambda x: torch.stack([x[..., 0] * x[..., 1], x[..., 1]], -1))
    with pytest.raises(RuntimeError, match="fit"):
        gp.factors()
    x = _design(12)
    gp.fit(x, _f(x))
    scaling = gp.input_scaling
    assert scaling is not None
    lo, span = scaling
    xt = _design(5, seed=2)
    raw = torch.stack([xt[:, 0] * xt[:, 1], xt[:, 1]], -1)
    torch.testing.assert_close(gp.gp_inputs(xt), (raw - lo) / span, rtol=0, atol=0)
    u = gp.gp_inputs(x)
    assert float(u.min()) >= 0.0 and float(u.max()) <= 1.0  # the range covers the runs
