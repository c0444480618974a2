"""The reduced (projected) likelihood of PCA surrogates (calibration.reduced): equal to the full
low-rank Gaussian density to 1e-8, the input map's Jacobian equal to autograd's. (pca_flat
against Pyro's potential of observation_model, value and gradient: test_fast_densities.py.)"""

import math

import numpy as np
import pyro.distributions as dist
import pytest
import torch

from solderpyro.calibration.emulators import GPEmulator, ObservedEmulator
from solderpyro.calibration.koh import Priors, prepare_observation
from solderpyro.calibration.reduced import PCAReduction, pca_flat, reduced_loglik_torch
from solderpyro.design import lhs
from solderpyro.params import Box
from solderpyro.surrogate import GPOptions, GPSurrogate
from solderpyro.surrogate.features import FlowStressInputs

DT = torch.float64
ANAND = Box(("s0", "QR", "xi", "m"), (5.0, 7000.0, 1.0, 0.05), (25.0, 13000.0, 5.0, 0.5),
            log_scale=(False, False, True, False))
FIXED = {"A": 4e6, "s_hat": 13.79, "n": 0.07}


def _field(theta: torch.Tensor, n_y: int = 60) -> torch.Tensor:
    """A smooth stand-in field ``(b, n_y)`` of the four Anand constants (um)."""
    x = torch.linspace(0, 1, n_y, dtype=DT)
    f = FlowStressInputs(ANAND, FIXED)(theta)  # (b, 4): log flow stresses, xi, m on [0, 1]
    return (torch.sin(3 * x + f[:, :1]) * f[:, 1:2] + 0.3 * f[:, 2:3] * x ** 2
            + 0.2 * torch.cos(5 * x * f[:, 3:4]))


def _gp(kernel: str, mean: str, inputs: bool, n: int = 25) -> GPSurrogate:
    th = lhs(ANAND, n, 0).to(DT)
    feats = FlowStressInputs(ANAND, FIXED) if inputs else None
    return GPSurrogate(ANAND, output="pca", kernel=kernel, mean=mean, ard=True,
                       options=GPOptions(n_pc=4, restarts=1), inputs=feats).fit(th, _field(th))


@pytest.fixture(scope="module")
def gps():
    return {"matern-flow": _gp("matern52", "constant", True),
            "gauss-raw-linear": _gp("gaussian", "linear", False)}


def _y(gp: GPSurrogate) -> torch.Tensor:
    th = torch.tensor([[12.9, 10586.0, 2.04, 0.1]], dtype=DT)
    g = torch.Generator().manual_seed(0)
    return _field(th)[0] + 0.05 * torch.randn(60, generator=g, dtype=DT)


@pytest.mark.parametrize("name", ["matern-flow", "gauss-raw-linear"])
def test_reduced_equals_full_low_rank_density(gps, name):
    """log N(y; m, F F^T + diag(d + s^2)) of the surrogate, the full n-dimensional density,
    equals the K-dimensional reduction to 1e-8 (relative) at points across the box."""
    gp = gps[name]
    y = _y(gp)
    for u in ([0.1, 0.2, 0.3, 0.4], [0.9, 0.5, 0.7, 0.05], [0.5, 0.95, 0.2, 0.8]):
        t = ANAND.from_unit(torch.tensor(u, dtype=DT))
        for s in (0.01, 0.05, 0.3):
            sig = torch.tensor(s, dtype=DT)
            m, F, d = gp.mean_lowrank(t)
            full = float(dist.LowRankMultivariateNormal(m, F, d + sig**2).log_prob(y))
            red = float(reduced_loglik_torch(gp, y, t, sig))
            assert abs(red - full) <= 1e-8 * max(1.0, abs(full)), (u, s, red, full)


def test_projected_path_equals_the_direct_one(gps):
    """The projections computed once (no offsets) give what the per-evaluation residual does."""
    gp = gps["matern-flow"]
    red = PCAReduction(gp, _y(gp))
    rng = np.random.default_rng(0)
    c, v = rng.normal(0, 2, red.K), rng.uniform(0, 1, red.K)
    a = red.loglik(c, v, 0.07, None)
    b = red.loglik(c, v, 0.07, np.zeros(red.n))
    assert abs(a[0] - b[0]) < 1e-9 * abs(a[0])
    for i in (1, 2, 3):
        np.testing.assert_allclose(a[i], b[i], rtol=1e-8, atol=1e-8)


def test_weight_moment_series_equals_the_sums_over_outputs():
    """The sigma-dependent sums from the moments of d (_WeightMoments) equal the sums over the
    n outputs to 1e-13 of their terms' sizes wherever the series is used, and give way to the
    direct sums (None) where sigma^2 is small against the spread of d."""
    from solderpyro.calibration.reduced import _WeightMoments

    rng = np.random.default_rng(3)
    n = 500
    d = rng.uniform(0.0, 2e-3, n) * rng.uniform(0, 1, n) ** 3  # skewed, min ~0
    Qt = rng.normal(0, 1, (7, n))
    wm = _WeightMoments(d, Qt)
    used = 0
    for s in (1e-5, 1e-4, 1e-3, 3e-3, 1e-2, 0.1, 10.0):
        w = 1.0 / (d + s)
        got = wm(s)
        r = wm.half / (wm.mid + s)
        if got is None:
            assert r > 0.3, (s, r)  # given way only where the series is long
            continue
        used += 1
        S1, S2, sw, slw = got
        # the direct n-term sums round by ~sqrt(n) u sum|terms| (~3e-15 of it at n = 500),
        # the series adds its cut-off TOL = 1e-15: 1e-13 of the terms' sizes leaves 30x
        scale1, scale2 = np.abs(Qt) @ w, np.abs(Qt) @ (w * w)
        assert np.all(np.abs(S1 - Qt @ w) <= 1e-13 * scale1), s
        assert np.all(np.abs(S2 - Qt @ (w * w)) <= 1e-13 * scale2), s
        assert abs(sw - w.sum()) <= 1e-13 * w.sum(), s
        assert abs(slw - np.log(w).sum()) <= 1e-13 * np.abs(np.log(w)).sum(), s
    assert used >= 4
    # constant d: the series is exact at its first term
    wc = _WeightMoments(np.full(n, 1e-3), Qt)
    S1, _, sw, _ = wc(0.01)
    # both sides sum the same n terms Qt_ij / 0.011 (a GEMM against ones, numpy's pairwise
    # sum) in different orders, then scale by 1/a: each is within (n - 1) u sum|terms| of the
    # exact sum in any order, plus a few u |S1| from the scaling (u = eps / 2), so their
    # difference is below 2 n eps sum|terms|; a row's sum can cancel to far less than its
    # terms, so a bound relative to S1 alone does not hold
    eps = np.finfo(np.float64).eps
    np.testing.assert_array_less(np.abs(S1 - Qt.sum(1) / 0.011),
                                 2 * n * eps * np.abs(Qt).sum(1) / 0.011)


def _offset_emulator(gp: GPSurrogate):
    """A rigid offset and tilt of the field: q = (c um, w um per unit x) -> (n,)."""
    x = torch.linspace(-1, 1, 60, dtype=DT)

    def off(q: torch.Tensor) -> torch.Tensor:
        return q[..., 0] + q[..., 1] * x

    box = Box((*ANAND.names, "c", "w"), (*ANAND.lower, -1.0, -0.5), (*ANAND.upper, 1.0, 0.5),
              log_scale=(*ANAND.log_scale, False, False))
    return ObservedEmulator(GPEmulator(gp), 4, off), box


@pytest.mark.parametrize("offsets", [False, True])
def test_flow_coordinates_are_the_same_posterior(gps, offsets):
    """With a flow-stress surrogate the default flat model samples (s0, QR, xi, m) in the
    soft-walled flow coordinates: its density, less that map's log-Jacobian, equals the
    logit model's, less the logit's, at the same parameters (one constant), and its gradient
    equals central differences."""
    gp = gps["matern-flow"]
    em, box = _offset_emulator(gp) if offsets else (GPEmulator(gp), ANAND)
    inp = prepare_observation(_y(gp), em, box)
    pr = Priors(sigma_max=2.0)
    fa, fl = pca_flat(inp, pr), pca_flat(inp, pr, coords="logit")
    assert fa.reparam is not None and fl.reparam is None
    ri, rc = fa.reparam
    rng = np.random.default_rng(2)
    diffs = []
    for _ in range(5):
        t = rng.uniform(0.05, 0.95, box.dim)
        q = np.append(np.log(t) - np.log1p(-t), rng.normal(-1.0, 0.3))
        lq, _ = fl.logp_and_grad(q)
        qa = q.copy()
        qa[ri] = rc.inverse(t[ri])
        la, ga = fa.logp_and_grad(qa)
        ld = rc.forward(qa[ri])[1]
        diffs.append((la - ld) - (lq - float(np.log(t[ri] * (1 - t[ri])).sum())))
        # h 1e-5: at 1e-6 the differences' round-off reached 1.6e-4 on the project's machine
        # (AMD EPYC, OpenBLAS's Haswell kernels; 3e-5-7e-5 typical) against 2e-6-8e-6 at 1e-5
        # and 3e-7-4e-6 at 1e-4 (truncation): the analytic gradient is the exact one
        h = 1e-5
        fd = [(fa.logp_and_grad(qa + h * e)[0] - fa.logp_and_grad(qa - h * e)[0]) / (2 * h)
              for e in np.eye(fa.dim)]
        np.testing.assert_allclose(ga, fd, rtol=1e-5, atol=1e-4)
    assert np.ptp(diffs) < 1e-8 * max(1.0, abs(lq)), diffs
    draws = np.stack([qa, qa])[None]  # (1 chain, 2 draws, d)
    np.testing.assert_allclose(fa.to_samples(draws)["t_unit"][0, 0].numpy(), t, atol=1e-10)
    np.testing.assert_allclose(fa.to_unconstrained(fa.to_samples(draws) | {
        "t_unit": torch.as_tensor(t), "sigma": fa.to_samples(draws)["sigma"][0, 0]}), qa,
        atol=1e-8)


def test_flow_stress_jacobian_equals_autograd():
    box = Box(("s0", "QR", "A", "xi", "m", "n"), (5, 7000, 1e5, 1, 0.05, 0.01),
              (25, 13000, 1e8, 5, 0.5, 0.2), log_scale=(False, False, True, True, False, False))
    fm = FlowStressInputs(box, {"s_hat": 13.79})
    for u in ([0.1, 0.2, 0.3, 0.4, 0.5, 0.6], [0.9, 0.8, 0.05, 0.6, 0.99, 0.3]):
        x = box.from_unit(torch.tensor(u, dtype=DT))
        f, j = fm.value_and_jacobian(x.numpy())
        np.testing.assert_allclose(f, fm(x).numpy(), rtol=1e-12, atol=1e-12)
        jt = torch.autograd.functional.jacobian(fm, x)
        np.testing.assert_allclose(j, jt.numpy(), rtol=1e-10, atol=1e-12)


def test_bad_input_is_named(gps):
    gp = gps["matern-flow"]
    with pytest.raises(ValueError, match="y_obs has shape"):
        PCAReduction(gp, torch.zeros(5, dtype=DT))
    inp = prepare_observation(_y(gp), GPEmulator(gp), ANAND)
    with pytest.raises(NotImplementedError, match="custom"):
        pca_flat(inp, Priors(custom={"sigma": dist.HalfNormal(1.0)}))
    swapped = Box(("QR", "s0", "xi", "m"), (7000.0, 5.0, 1.0, 0.05), (13000.0, 25.0, 5.0, 0.5))
    with pytest.raises(ValueError, match="surrogate's inputs"):
        pca_flat(prepare_observation(_y(gp), GPEmulator(gp), swapped), Priors())


@pytest.mark.parametrize("name", ["matern-flow", "gauss-raw-linear"])
def test_native_reduced_likelihood_equals_numpy(gps, name):
    """The fused native kernel (solderpyro/_native/reduced.c) gives the NumPy path's component
    means and variances, log density and gradients (in the GP inputs and sigma), with sigma
    from where the moment series serves to where the direct sums over the outputs do. The
    gradient's tolerance follows from its terms (:func:`_gradient_term_sizes`): at small sigma
    d ll/dc = e - A P e cancels terms up to ~5e8 times larger than the gradient in u, so the
    two summation orders differ there by ~eps x those terms (0.5 of it measured)."""
    from solderpyro import _native
    from solderpyro.calibration.reduced import ComponentGPs, native_loglik

    if _native.library() is None:
        pytest.skip("no C compiler: the native kernels are unavailable")
    gp = gps[name]
    red, cg = PCAReduction(gp, _y(gp)), ComponentGPs(gp)
    fused = native_loglik(cg, red)
    rng = np.random.default_rng(5)
    paths = set()
    for _ in range(40):
        u = rng.uniform(-0.1, 1.1, cg.U.shape[1])
        s = float(np.exp(rng.uniform(math.log(1e-3), math.log(1.0))))
        paths.add(red._moments(s * s) is None)
        c, v, vjp = cg(u)
        ll, gc, gv, gs, _ = red.loglik(c, v, s, None)
        gu = vjp(gc, gv)
        ll2, gu2, gs2, c2, v2 = fused(u, s)
        # c = c0 + sum_i os rho_i alpha_i (+ w u) over the n runs, each term rounded (and its
        # exp taken) differently by the two paths: |c2 - c| <= (n + 4) eps times the terms'
        # sizes, |c0| + os sum|alpha| + |w||u| (rho <= 1), which exceed |c| by up to ~1e4 here
        n_sim, eps = cg.alpha.shape[1], np.finfo(float).eps
        c_terms = np.abs(cg.c0) + cg.os * np.abs(cg.alpha).sum(1)
        if cg.w is not None:
            c_terms = c_terms + np.abs(cg.w) @ np.abs(u)
        assert np.all(np.abs(c2 - c) <= (n_sim + 4) * eps * c_terms), (s, c, c2)
        np.testing.assert_allclose(v2, v, rtol=1e-9, atol=1e-12 * cg.os.max())
        assert abs(ll2 - ll) <= 1e-10 * abs(ll), (s, ll, ll2)
        assert abs(gs2 - gs) <= 1e-8 * abs(gs) + 1e-10 * abs(ll), (s, gs, gs2)
        # rounding of the cancelling terms (<= 8 eps of their sizes), and of everything else
        # (the GP's c and v, the moment series: <= 5e-13 max|gu| measured) under 1e-8 max|gu|
        tol = 8 * np.finfo(float).eps * _gradient_term_sizes(red, vjp, c, v, s)
        err = np.abs(gu2 - gu) - (1e-6 * np.abs(gu) + 1e-8 * np.abs(gu).max() + tol)
        assert np.all(err <= 0), (s, gu, gu2, tol)
    assert paths == {True, False}, "both the series and the direct sums must be exercised"


def _gradient_term_sizes(red, vjp, c: np.ndarray, v: np.ndarray, s: float) -> np.ndarray:
    """Sizes ``(d',)`` of the terms that d ll/du sums: with ``e = B^T D^-1 r`` and ``P``, ``A``
    of :func:`~solderpyro.calibration.reduced._k_terms`, ``g = e - A P e`` and ``gv`` sum terms
    up to ``G = |e| + |A||P||e|`` and ``|g| G + (|diag A| + diag |A||P||A|) / 2``
    (``|e|`` itself counting ``|B^T D^-1 y0| + |A||c|``), which ``|J_c|^T``, ``|J_v|^T`` (the
    chain to u, one vjp per component) carry to u; sums over the n outputs that build A and e
    add a few eps of their own terms, within the same sizes."""
    K, m = red.K, len(red._iu[0])
    S1 = red._Qt @ (1.0 / (red.d + s * s))
    A, bw = red._sym(S1[:m]), S1[m:m + K]
    sv = np.sqrt(v)
    P = sv[:, None] * np.linalg.inv(np.eye(K) + sv[:, None] * A * sv[None, :]) * sv[None, :]
    e = bw - A @ c
    aA, aP = np.abs(A), np.abs(P)
    E = np.abs(bw) + aA @ np.abs(c)
    G = E + aA @ aP @ E
    GV = np.abs(e - A @ (P @ e)) * G + 0.5 * (np.abs(np.diag(A)) + np.diag(aA @ aP @ aA))
    eye, zero = np.eye(K), np.zeros(K)
    Jc = np.stack([vjp(eye[k], zero) for k in range(K)])  # (K, d')
    Jv = np.stack([vjp(zero, eye[k]) for k in range(K)])
    return np.abs(Jc).T @ G + np.abs(Jv).T @ GV


def test_without_native_kernels_the_numpy_path_gives_the_same_flat_density(gps, monkeypatch):
    """Where no compiler is found (``library()`` None) the flat model and the ridge map run
    in NumPy and give the same log density and gradient as the native path."""
    from solderpyro import _native
    from solderpyro.calibration.ridgemap import RidgeMap

    gp = gps["matern-flow"]
    inp = prepare_observation(_y(gp), GPEmulator(gp), ANAND)
    pr = Priors(sigma_max=2.0)
    rng = np.random.default_rng(8)
    Q = rng.normal(0, 1, (300, 5)) @ np.triu(rng.normal(0, 0.3, (5, 5)) + np.eye(5))
    Q[:, 1] += 0.4 * Q[:, 0] ** 2
    fa = RidgeMap(Q).wrap(pca_flat(inp, pr).logp_and_grad)
    monkeypatch.setattr(_native, "library", lambda: None)
    fb = RidgeMap(Q).wrap(pca_flat(inp, pr).logp_and_grad)
    for w in rng.normal(0, 1.5, (10, 5)):
        (la, ga), (lb, gb) = fa(w), fb(w)
        assert abs(la - lb) <= 1e-9 * max(1.0, abs(lb)), (la, lb)
        np.testing.assert_allclose(ga, gb, rtol=1e-6, atol=1e-8 * np.abs(gb).max())


def test_native_reduced_likelihood_non_finite_input_as_numpy(gps):
    """A non-finite GP input (a leapfrog step gone far) gives a NaN log density on both paths
    (the sampler counts a divergence), not an exception."""
    from solderpyro import _native
    from solderpyro.calibration.reduced import ComponentGPs, native_loglik

    if _native.library() is None:
        pytest.skip("no C compiler: the native kernels are unavailable")
    gp = gps["matern-flow"]
    red, cg = PCAReduction(gp, _y(gp)), ComponentGPs(gp)
    u = np.array([0.5, np.nan, 0.5, 0.5])
    c, v, _ = cg(u)
    assert math.isnan(red.loglik(c, v, 0.05, None)[0])
    assert math.isnan(native_loglik(cg, red)(u, 0.05)[0])


@pytest.mark.parametrize("extra", [False, True], ids=["anand", "anand+effect"])
@pytest.mark.parametrize("pr", [Priors(sigma_known=0.05), Priors(sigma_max=2.0)],
                         ids=["known", "flat"])
def test_native_flow_flat_equals_the_python_flat_model(extra, pr):
    """The whole flat log density in flow coordinates in one native call (flowflat.c, the
    default where a compiler is found) equals FlatModel.logp_and_grad's Python path, at points
    inside the box and far out on the soft walls (|q| up to 12), with and without a further
    (logit) parameter beside the Anand constants, for both sigma priors."""
    from solderpyro import _native

    if _native.library() is None:
        pytest.skip("no C compiler: the native kernels are unavailable")
    if extra:
        box = Box((*ANAND.names, "k"), (*ANAND.lower, -1.0), (*ANAND.upper, 1.0),
                  log_scale=(*ANAND.log_scale, False))
        th = lhs(box, 30, 1).to(DT)
        y = _field(th[:, :4]) + 0.3 * th[:, 4:5]
        gp = GPSurrogate(box, output="pca", kernel="matern52", mean="constant", ard=True,
                         options=GPOptions(n_pc=4, restarts=1),
                         inputs=FlowStressInputs(box, FIXED)).fit(th, y)
    else:
        box = ANAND
        gp = _gp("matern52", "constant", True)
    fm = pca_flat(prepare_observation(_y(gp), GPEmulator(gp), box), pr)
    assert fm.native is not None and fm.reparam is not None
    nat = fm.native
    rng = np.random.default_rng(11)
    for scale in (0.8, 3.0, 12.0):
        for _ in range(6):
            q = rng.normal(0.0, scale, fm.dim)
            q[-1] = math.log(0.05) + rng.normal(0.0, 0.3)
            fm.native = nat
            la, ga = fm.logp_and_grad(q)
            fm.native = None
            lb, gb = fm.logp_and_grad(q)
            assert abs(la - lb) <= 1e-11 * max(1.0, abs(lb)), (q, la, lb)
            np.testing.assert_allclose(ga, gb, rtol=1e-8, atol=1e-9 * np.abs(gb).max())
