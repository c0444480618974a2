"""Per-call costs inside a design round, paired in one process.

    python benchmarks/round_costs.py RUN_DIR [--store STORE] [--json OUT.json]

Rebuilds a finished run's final surrogate from its design runs (design.csv, through the run
store) and times, one thread, median of 5 repeats each, side by side:

- the posterior's log density and gradient (``FlatModel.logp_and_grad``, the reduced PCA
  likelihood) at 600 of the run's posterior draws: the sigma-dependent sums from the moments
  of the truncation variance (``reduced._WeightMoments``, the default) against the sums over
  every output (the series switched off);
- the same gradient in the ridge coordinates the sampler uses (``RidgeMap.wrap``, the map
  fitted to the 600 draws), with the native kernels (``reduced.c``, ``ridgemap.c``: the
  default where a C compiler is found) against the NumPy path they replaced, and the largest
  differences of log density and gradient between the two;
- the surrogate's hyperparameter fit (``fit_surrogate`` on the run's converged design runs,
  one thread): the marginal likelihood's loss and gradient in NumPy/LAPACK
  (``surrogate/mll.py``, the default) against GPyTorch's autograd closure, with each fit's
  summed negative log marginal likelihood;
- the design's acquisition (``greedy_draws``, 256 draws, 512 candidates, q = 8, 4 pending,
  the loglik criterion): the kept low-rank form against the full covariance matrix with
  rank-1 updates it replaced (:func:`_greedy_full`, kept here as the reference), with the
  chosen runs compared.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np
import torch


def _greedy_full(gp, mc_theta, cand_theta, q, sigma, y, pending):
    """The previous ``greedy_draws`` (loglik criterion): the full (k, M, M) posterior
    covariance of the coefficients over draws, candidates and pending runs, rank-1 updated."""
    from solderpyro.design.acquisition import loglik_terms

    N, C = len(mc_theta), len(cand_theta)
    S = torch.cat([mc_theta, cand_theta, pending]).to(torch.float64)
    with torch.no_grad():
        _, cov = gp.coefficients(S, full_cov=True)
        tau = gp.factors().noise

        def condition(cov, i):
            den = (cov[:, i, i] + tau)[:, None, None]
            return cov - cov[:, :, i:i + 1] * cov[:, i:i + 1, :] / den

        for i in range(N + C, len(S)):
            cov = condition(cov, i)
        g, M = loglik_terms(gp, mc_theta, y, sigma, None)
        g2, M2 = g.square().T, M.square()
        chosen: list[int] = []
        for _ in range(q):
            d = cov.diagonal(dim1=-2, dim2=-1)
            cm = cov[:, :N, N:N + C]
            vn = (d[:, :N, None] - cm.square() / (d[:, None, N:N + C] + tau[:, None, None])
                  ).clamp_min(0.0)
            val = -((g2[:, :, None] * vn).sum(0)
                    + 0.5 * torch.einsum("knc,kl,lnc->nc", vn, M2, vn)).mean(0)
            if chosen:
                val[chosen] = -float("inf")
            b = int(val.argmax())
            chosen.append(b)
            cov = condition(cov, N + b)
    return torch.tensor(chosen), float(val[chosen[-1]])


def _median_time(f, repeats: int = 5) -> float:
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        f()
        out.append(time.perf_counter() - t0)
    return statistics.median(out)


def main() -> None:
    from _runs import rebuild  # benchmarks/ is on sys.path when this script runs

    from solderpyro.calibration.fastkoh import flat_model
    from solderpyro.calibration.koh import SITE_SIGMA, SITE_T, observation_model
    from solderpyro.calibration.reduced import PCAReduction
    from solderpyro.design.acquisition import AcquisitionPoints, greedy_draws

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", help="a finished 'solderpyro calibrate' run directory")
    ap.add_argument("--store", default=None, help="its run store (default: run.json's)")
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    torch.set_num_threads(1)
    from threadpoolctl import threadpool_limits
    threadpool_limits(1)
    rb = rebuild(Path(a.run), a.store)
    sm, gp, inp, fm, T, sig = rb.sm, rb.gp, rb.inp, rb.fm, rb.T, rb.sig
    u = sm.space.to_unit(torch.as_tensor(T)).numpy()
    sel = np.linspace(0, len(T) - 1, 600).round().astype(int)
    Q = np.stack([fm.to_unconstrained({SITE_T: torch.as_tensor(u[i]),
                                       SITE_SIGMA: torch.as_tensor(sig[i])}) for i in sel])
    out: dict = {"run": str(a.run), "n_obs": int(sm.y.numel()),
                 "components": int(gp.basis.shape[1]), "fe_runs": int(gp.x_train.shape[0])}

    def timed_gradients(model) -> tuple[float, np.ndarray]:
        """Seconds per gradient over Q (median of 5 passes after one untimed) and the log
        densities at Q's first 50 points."""
        def grads() -> None:
            for q in Q:
                model.logp_and_grad(q)

        grads()
        return (_median_time(grads) / len(Q),
                np.array([model.logp_and_grad(q)[0] for q in Q[:50]]))

    from solderpyro import _native
    from solderpyro.calibration.ridgemap import RidgeMap

    lib = _native.library
    _native.library = lambda: None  # the series against the sums: both in NumPy
    fm = flat_model(observation_model, (inp, sm.priors))
    t_series, lp_series = timed_gradients(fm)
    saved = PCAReduction.__init__

    def no_series(self, *args, **kw):
        saved(self, *args, **kw)
        self._moments = lambda s: None

    PCAReduction.__init__ = no_series  # type: ignore[method-assign]
    try:
        fm_direct = flat_model(observation_model, (inp, sm.priors))
    finally:
        PCAReduction.__init__ = saved  # type: ignore[method-assign]
    t_direct, lp_direct = timed_gradients(fm_direct)
    _native.library = lib
    out["gradient_us"] = {"series": round(t_series * 1e6, 1), "direct": round(t_direct * 1e6, 1),
                          "ratio": round(t_direct / t_series, 2),
                          "max_abs_logp_difference": float(np.abs(lp_series - lp_direct).max())}
    print("gradient:", out["gradient_us"], flush=True)

    rmap = RidgeMap(Q)
    W = rmap.inverse(Q)
    f_native = rmap.wrap(flat_model(observation_model, (inp, sm.priors)).logp_and_grad)
    _native.library = lambda: None  # the NumPy path, as where no compiler is found
    try:
        f_numpy = rmap.wrap(flat_model(observation_model, (inp, sm.priors)).logp_and_grad)
    finally:
        _native.library = lib

    def per_gradient(f) -> float:
        for w in W:
            f(w)
        return _median_time(lambda: [f(w) for w in W]) / len(W)

    t_nat, t_np = per_gradient(f_native), per_gradient(f_numpy)
    pairs = [(f_native(w), f_numpy(w)) for w in W[:100]]
    out["ridge_gradient_us"] = {
        "native": round(t_nat * 1e6, 1), "numpy": round(t_np * 1e6, 1),
        "ratio": round(t_np / t_nat, 2),
        "max_rel_logp_difference": max(abs(a[0] - b[0]) / abs(b[0]) for a, b in pairs),
        "max_rel_gradient_difference": max(float(np.abs(a[1] - b[1]).max()
                                                 / np.abs(b[1]).max()) for a, b in pairs)}
    print("gradient in ridge coordinates:", out["ridge_gradient_us"], flush=True)

    import gpytorch

    import solderpyro.surrogate.gp as gpmod
    from solderpyro.config.settings import CalibrationSettings
    from solderpyro.pipeline.surrogate import fit_surrogate

    X = torch.as_tensor(gp.x_train)
    Y = torch.as_tensor(gp.y_train)
    s_med0 = float(np.median(sig))

    def fit_once() -> tuple[float, float]:
        t0 = time.perf_counter()
        g = fit_surrogate(sm, CalibrationSettings().surrogate, X, Y, s_med0)
        sec = time.perf_counter() - t0
        mdl = g.model
        mdl.train()
        mll = gpytorch.mlls.ExactMarginalLogLikelihood(mdl.likelihood, mdl)
        with torch.no_grad():
            nll = -float(mll(mdl(mdl.train_inputs[0]), mdl.train_targets).sum()) * X.shape[0]
        return sec, nll

    new_fit = [fit_once() for _ in range(2)]
    saved_closure = gpmod.mll_closure
    gpmod.mll_closure = lambda model, opt, fallback: fallback  # GPyTorch's autograd closure
    try:
        old_fit = [fit_once() for _ in range(2)]
    finally:
        gpmod.mll_closure = saved_closure
    t_new, t_old = min(f[0] for f in new_fit), min(f[0] for f in old_fit)
    out["gp_fit_s"] = {"runs": int(X.shape[0]), "numpy_closure": round(t_new, 2),
                       "gpytorch_autograd": round(t_old, 2), "ratio": round(t_old / t_new, 2),
                       "neg_log_mll_numpy": round(new_fit[0][1], 3),
                       "neg_log_mll_gpytorch": round(old_fit[0][1], 3)}
    print("GP fit:", out["gp_fit_s"], flush=True)

    th = torch.as_tensor(T, dtype=torch.float64)
    mc = th[np.linspace(0, len(th) - 1, 256).round().astype(int)]
    cand = th[np.linspace(0, len(th) - 1, 512).round().astype(int)]
    pend = th[np.linspace(3, len(th) - 4, 4).round().astype(int)]
    s_med = float(np.median(sig))
    res = {}

    def new() -> None:
        res["new"] = greedy_draws(gp, "loglik", AcquisitionPoints(mc, cand, pend), 8, s_med,
                                  sm.y)

    def full() -> None:
        res["full"] = _greedy_full(gp, mc, cand, 8, s_med, sm.y, pend)

    t_new, t_full = _median_time(new, 3), _median_time(full, 3)
    out["greedy_s"] = {"low_rank": round(t_new, 3), "full_matrix": round(t_full, 3),
                       "ratio": round(t_full / t_new, 2),
                       "same_choices": res["new"][0].tolist() == res["full"][0].tolist(),
                       "value_rel_difference": abs(res["new"][1] - res["full"][1])
                       / abs(res["full"][1])}
    print("greedy:", out["greedy_s"], flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
