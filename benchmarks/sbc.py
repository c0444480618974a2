"""Simulation-based calibration of the NUTS sampler (Talts et al. 2018, arXiv:1804.06788).

Usage: python benchmarks/sbc.py [--reps 200] [--models direct field anand] [--chains 1]
       [--warmup 300] [--draws 300] [--bins 10] [--mutate none|half-lik|double-lik|short]
       [--out benchmarks/results/sbc.json]

For r = 1..R: (t, sigma) is drawn from the model's prior and y from the model's own likelihood
at that draw (the Pyro model run with its observed site un-conditioned, so the simulation is
the model's generative process exactly), the posterior is sampled with
:func:`~solderpyro.calibration.mcmc.run_nuts` through the public API, thinned to L = 99
roughly independent draws (L equally spaced draws of all chains, the run repeated with twice the
draws, up to twice, while the smallest bulk ESS is below L: Talts et al.'s Algorithm 2), and the
rank of the prior draw among them is recorded per parameter. For a correct sampler the ranks are
uniform on {0, ..., L}; a chi-square test on B bins (each bin (L + 1) / B rank values) checks
it, and the largest bin deviation and the ECDF's largest distance from the uniform CDF are
reported beside it.

Three models:

- ``direct``: the seed math example (Section 3), y_i ~ N(5 exp(-t x_i), sigma^2) on the seed's
  11 x, t ~ U(0, 2), sigma ~ U(0, 2) (``Priors(sigma_max=2)``).
- ``field``: a 60-point 1-D field f(s; a, k) = a exp(-k s) + (1 - a) s on s in [0, 1], a in
  [0.5, 2], k in [0.5, 3], replaced by a PCA GP surrogate fitted on 25 LHS runs; the modular
  likelihood y ~ N(mean(t), F F^T + diag(d) + sigma^2 I) of ``GPEmulator(gp).lowrank(t)``,
  sigma ~ LogNormal(log 0.05, 0.1) (``Priors(sigma_known=0.05)``). Data come from that
  Gaussian, not from f, so the ranks test the sampler, not the surrogate.

- ``anand``: the Anand constants (s0, QR, xi, m on the seed box) through a PCA GP on
  flow-stress inputs (Matern 5/2, ARD, 4 components, 30 LHS runs) of a 60-value stand-in
  field linear in the four flow-stress features f (f0 (1 - s) + f1 s + f2 sin(pi s) +
  f3 cos(2 pi s), s in [0, 1]: identifiable, one mode); sigma ~ LogNormal(log 0.3, 0.1), so
  posteriors are wide and often reach the box's faces. This is
  the model whose NUTS runs in the soft-walled flow-stress coordinates
  (:mod:`solderpyro.calibration.flowcoords`): its ranks test that transform (log-Jacobian,
  gradient, walls) over the whole box.

Mutations (run once to show the check can fail, not a result): ``half-lik`` samples a posterior
with the likelihood's log density halved (too wide; through Pyro's potential with autograd,
slow); ``double-lik`` (direct model only) calibrates on every observation twice, i.e. the
likelihood squared (too narrow; on the analytic path); ``short`` runs one chain per replication
with a 10-iteration warm-up and keeps L consecutive draws unthinned (an under-adapted,
autocorrelated sampler); ``half-jacobian`` / ``no-jacobian`` (anand model only) sample the
flow coordinates with half / none of their log-Jacobian (density and gradient kept
consistent: a smooth, wrong posterior whose prior is no longer uniform on the box;
``no-jacobian`` is improper beyond the walls, where the likelihood is flat, and its chains
drift away: it did not finish 10 replications in 35 minutes).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyro
import torch
from pyro import poutine
from pyro.poutine.messenger import Messenger
from scipy import stats

from solderpyro.calibration import Priors, calibrate_direct, calibrate_emulator, run_nuts
from solderpyro.calibration.emulators import FunctionEmulator, GPEmulator
from solderpyro.calibration.koh import (
    SITE_SIGMA,
    SITE_T,
    SITE_Y,
    ObsInputs,
    observation_model,
    prepare_observation,
)
from solderpyro.calibration.mcmc import NutsOptions
from solderpyro.examples.seed_math import X_OBS, code
from solderpyro.params import Box

DT = torch.float64
L_DRAWS = 99  #: thinned posterior draws per replication: ranks in {0, ..., 99}
PARAMS = ("t", "sigma")

DIRECT_BOX = Box(("t",), (0.0,), (2.0,))
DIRECT_PRIORS = Priors(sigma_max=2.0)
FIELD_BOX = Box(("a", "k"), (0.5, 0.5), (2.0, 3.0))
FIELD_PRIORS = Priors(sigma_known=0.05)
FIELD_S = torch.linspace(0.0, 1.0, 60, dtype=DT)


def field_code(t: torch.Tensor) -> torch.Tensor:
    """The field model ``t (..., 2) -> (..., 60)``: a exp(-k s) + (1 - a) s."""
    a, k = t[..., :1], t[..., 1:2]
    return a * torch.exp(-k * FIELD_S) + (1.0 - a) * FIELD_S


@dataclass
class Problem:
    """One SBC model: its inputs (with a placeholder y), priors and parameter names.

    ``calibrate(y, **nuts)`` returns the posterior through the public API.
    """

    name: str
    inp: ObsInputs
    priors: Priors
    names: list[str]  # column names of t (Posterior.columns)
    calibrate: Callable[..., Any]
    info: dict


def direct_problem() -> Problem:
    """The seed math model in direct mode on the seed's 11 x."""
    x = X_OBS.clone()
    y0 = code(x, torch.tensor([1.0], dtype=DT))
    inp = prepare_observation(y0, FunctionEmulator(code, x), DIRECT_BOX, x)

    def calibrate(y: torch.Tensor, **nuts: Any) -> Any:
        return calibrate_direct(code, x, y, DIRECT_BOX, DIRECT_PRIORS, progress=False,
                                **nuts)[0]

    return Problem("direct", inp, DIRECT_PRIORS, ["t"], calibrate,
                   {"box": [DIRECT_BOX.lower, DIRECT_BOX.upper], "n_obs": 11,
                    "sigma_prior": "Uniform(0, 2)"})


def field_problem(n_runs: int = 25, seed: int = 0) -> Problem:
    """The PCA-surrogate field model (GP fitted once, on an LHS of ``n_runs`` runs)."""
    from scipy.stats import qmc

    from solderpyro.surrogate import GPSurrogate

    u = torch.as_tensor(qmc.LatinHypercube(d=2, seed=seed).random(n_runs), dtype=DT)
    ts = FIELD_BOX.from_unit(u)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gp = GPSurrogate(FIELD_BOX, output="pca").fit(ts, field_code(ts))
    return _gp_problem("field", gp, FIELD_BOX, FIELD_PRIORS, {
        "n_obs": int(FIELD_S.shape[0]), "n_runs": n_runs,
        "sigma_prior": "LogNormal(log 0.05, 0.1)"})


def _gp_problem(name: str, gp: Any, box: Box, priors: Priors, info: dict) -> Problem:
    """A modular SBC problem on a fitted PCA GP (placeholder data at the box's middle)."""
    emu = GPEmulator(gp)
    with torch.no_grad():
        y0 = emu(box.from_unit(torch.full((box.dim,), 0.5, dtype=DT)))[0]
    inp = prepare_observation(y0, emu, box)

    def calibrate(y: torch.Tensor, **nuts: Any) -> Any:
        return calibrate_emulator(emu, y, box, priors, progress=False, **nuts)[0]

    return Problem(name, inp, priors, list(box.names), calibrate,
                   {"box": [box.lower, box.upper], "n_pc": int(gp.basis.shape[1]), **info})


ANAND_BOX = Box(("s0", "QR", "xi", "m"), (5.0, 7000.0, 1.0, 0.05), (25.0, 13000.0, 5.0, 0.5))
ANAND_FIXED = {"A": 4.0e6, "s_hat": 13.79, "n": 0.07}
ANAND_PRIORS = Priors(sigma_known=0.3)


def anand_problem(n_runs: int = 30, seed: int = 0) -> Problem:
    """The flow-stress PCA-surrogate model of the four Anand constants (see the docstring)."""
    from solderpyro.design import lhs
    from solderpyro.surrogate import GPOptions, GPSurrogate
    from solderpyro.surrogate.features import FlowStressInputs

    feats = FlowStressInputs(ANAND_BOX, ANAND_FIXED)
    x = torch.linspace(0, 1, 60, dtype=DT)

    def field(th: torch.Tensor) -> torch.Tensor:
        f = feats(th)
        return (f[:, :1] * (1 - x) + f[:, 1:2] * x + f[:, 2:3] * torch.sin(math.pi * x)
                + f[:, 3:4] * torch.cos(2 * math.pi * x))

    th = lhs(ANAND_BOX, n_runs, seed).to(DT)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gp = GPSurrogate(ANAND_BOX, output="pca", kernel="matern52", ard=True,
                         options=GPOptions(n_pc=4, restarts=1), inputs=feats).fit(th, field(th))
    return _gp_problem("anand", gp, ANAND_BOX, ANAND_PRIORS, {
        "n_obs": 60, "n_runs": n_runs, "inputs": "flow_stress",
        "sigma_prior": "LogNormal(log 0.3, 0.1)"})


def anand_ridge_problem(n_runs: int = 30, seed: int = 0) -> Problem:
    """The Anand model sampled as a design round samples it: a pilot posterior (2 chains x
    (150 + 150)), then the replication's run warm-started from it in the ridge coordinates
    fitted to the pilot's draws (calibration/ridgemap.py), always (``ridge="always"``: these
    posteriors rarely bend enough for the default gate, and the check is of the mapped
    sampler's correctness). ``info["mapped_reps"]`` counts the runs that ran mapped (the
    chains of the pilot agreed; reruns with more draws count too)."""
    from solderpyro.calibration.mcmc import ridge_map

    p = anand_problem(n_runs, seed)
    base = p.calibrate
    info = {**p.info, "pilot": "2 chains x (150 + 150); the run warm-started from it",
            "mapped_reps": 0}

    def calibrate(y: torch.Tensor, **nuts: Any) -> Any:
        pilot = base(y, chains=2, warmup=150, draws=150, seed=int(nuts.get("seed", 0)) + 10**6,
                     workers=1)
        if ridge_map(pilot.warm, pilot.warm.coords, bent=False) is not None:
            info["mapped_reps"] += 1
        return base(y, warm=pilot.warm, ridge="always", **nuts)

    return Problem("anand_ridge", p.inp, p.priors, p.names, calibrate, info)


def simulate(p: Problem, seed: int) -> tuple[dict[str, np.ndarray], torch.Tensor]:
    """One draw of (t, sigma) from the prior and y from the likelihood: the model itself, run
    with its observed site un-conditioned. Returns the truth by column name and y."""
    pyro.set_rng_seed(seed)
    with torch.no_grad():
        tr = poutine.trace(poutine.uncondition(observation_model)).get_trace(p.inp, p.priors)
    t = p.inp.theta_box.from_unit(tr.nodes[SITE_T]["value"])
    truth = {nm: float(t[i]) for i, nm in enumerate(p.names)}
    truth["sigma"] = float(tr.nodes[SITE_SIGMA]["value"])
    return truth, tr.nodes[SITE_Y]["value"].detach()


class _HalfLik(Messenger):
    """Mutation: the observed site's log density times 0.5."""

    def _process_message(self, msg: dict) -> None:
        if msg["name"] == SITE_Y:
            msg["scale"] = 0.5 * msg["scale"]


def _half_lik_model(inp: ObsInputs, priors: Priors) -> None:
    with _HalfLik():
        observation_model(inp, priors)


def _columns(p: Problem, y: torch.Tensor, mutate: str, nuts: dict) -> dict[str, np.ndarray]:
    """Posterior draws ``(chain, draw)`` by column name."""
    if mutate == "double-lik":  # every observation twice: the likelihood squared
        if p.name != "direct":
            raise NotImplementedError("the double-lik mutation is for the direct model")
        x = p.inp.emulator.x_obs
        post = calibrate_direct(code, torch.cat([x, x]), torch.cat([y, y]), DIRECT_BOX,
                                DIRECT_PRIORS, progress=False, **nuts)[0]
        return post.columns()
    if mutate in ("half-jacobian", "no-jacobian"):
        if p.name != "anand":
            raise NotImplementedError(f"the {mutate} mutation is for the anand model")
        with _scaled_jacobian(0.5 if mutate == "half-jacobian" else 0.0):
            return p.calibrate(y, **nuts).columns()
    if mutate != "half-lik":
        return p.calibrate(y, **nuts).columns()
    inp = ObsInputs(y, p.inp.emulator, p.inp.theta_box, p.inp.u_x)
    samples = run_nuts(_half_lik_model, (inp, p.priors),
                       NutsOptions(progress=False, **nuts)).samples
    t = p.inp.theta_box.from_unit(samples[SITE_T]).numpy()
    out = {nm: t[..., i] for i, nm in enumerate(p.names)}
    out["sigma"] = samples[SITE_SIGMA].numpy()
    return out


@contextmanager
def _scaled_jacobian(k: float) -> Iterator[None]:
    """Mutation: SoftFlowCoords with ``k`` times its log-Jacobian (``vjp`` is linear in its
    argument plus the log-Jacobian's gradient ``vjp(0)``, so the gradient stays the
    density's)."""
    from solderpyro.calibration.flowcoords import SoftFlowCoords

    orig = SoftFlowCoords.forward

    def forward(self: Any, q: np.ndarray) -> Any:
        t, ld, vjp = orig(self, q)
        g0 = vjp(np.zeros(4))
        return t, k * ld, lambda g: vjp(g) - (1.0 - k) * g0

    SoftFlowCoords.forward = forward  # type: ignore[method-assign]
    try:
        yield
    finally:
        SoftFlowCoords.forward = orig  # type: ignore[method-assign]


def _min_ess(cols: dict[str, np.ndarray]) -> float:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import arviz as az

        logging.getLogger("arviz").setLevel(logging.ERROR)
        return min(float(az.ess(np.asarray(a, dtype=float), method="bulk"))
                   for a in cols.values())


def replicate(p: Problem, r: int, chains: int, warmup: int, draws: int, seed0: int = 0,
              mutate: str = "none", max_doublings: int = 2, max_retries: int = 3) -> dict:
    """One SBC replication: ranks of the prior draw among L thinned posterior draws.

    A sampler run that raises is rerun on the same data with another sampler seed (at most
    ``max_retries`` times) and the error recorded: the retry does not depend on the data, so the
    ranks stay those of the posterior; the errors are reported, not hidden.
    """
    truth, y = simulate(p, seed0 + 100_003 * (r + 1))
    t0 = time.perf_counter()
    errors: list[str] = []

    def sample(nuts: dict) -> dict[str, np.ndarray]:
        for k in range(max_retries + 1):
            try:
                return _columns(p, y, mutate, {**nuts, "seed": nuts["seed"] + 7919 * k})
            except (ArithmeticError, RuntimeError, ValueError, np.linalg.LinAlgError) as exc:
                errors.append(f"{type(exc).__name__}: {exc}")
                if k == max_retries:
                    raise
        raise AssertionError("unreachable")

    if mutate == "short":
        cols = sample(dict(chains=1, warmup=10, draws=L_DRAWS, seed=seed0 + r, workers=1))
        ess, n_draws = _min_ess(cols), L_DRAWS
    else:
        n_draws = draws
        for k in range(max_doublings + 1):
            n_draws = draws * 2**k
            cols = sample(dict(chains=chains, warmup=warmup, draws=n_draws, seed=seed0 + r,
                               workers=1))
            ess = _min_ess(cols)
            if ess >= L_DRAWS:
                break
    sec = time.perf_counter() - t0
    ranks = {}
    for nm, v in truth.items():
        flat = np.asarray(cols[nm], dtype=float).reshape(-1)  # chain-major
        keep = flat[np.round(np.linspace(0, flat.size - 1, L_DRAWS)).astype(int)]
        ranks[nm] = int((keep < v).sum())
    return {"rep": r, "truth": truth, "ranks": ranks, "min_ess": ess, "draws": n_draws,
            "seconds": sec, "errors": errors}


def rank_stats(ranks: np.ndarray, bins: int, n_ranks: int = L_DRAWS + 1) -> dict:
    """Chi-square test of uniform ranks on {0, ..., n_ranks - 1} over ``bins`` equal bins, the
    largest relative bin deviation and the ECDF's largest distance from the uniform CDF."""
    if n_ranks % bins:
        raise ValueError(f"{n_ranks} rank values do not split into {bins} equal bins")
    r = np.asarray(ranks, dtype=int)
    counts = np.bincount(r // (n_ranks // bins), minlength=bins)
    e = r.size / bins
    chi2 = float(((counts - e) ** 2 / e).sum())
    grid = np.arange(n_ranks)
    ecdf = (r[None, :] <= grid[:, None]).mean(1)
    ks = float(np.abs(ecdf - (grid + 1) / n_ranks).max())
    return {"counts": counts.tolist(), "chi2": chi2, "df": bins - 1,
            "p_value": float(stats.chi2.sf(chi2, bins - 1)),
            "max_bin_dev": float(np.abs(counts - e).max() / e), "ecdf_max_dev": ks,
            "ecdf_max_dev_scaled": ks * math.sqrt(r.size)}


def run_sbc(p: Problem, reps: int, chains: int = 1, warmup: int = 300, draws: int = 300,
            bins: int = 10, seed0: int = 0, mutate: str = "none", verbose: bool = False
            ) -> dict:
    """R replications of one model; ranks and their uniformity statistics per parameter."""
    t0 = time.perf_counter()
    rows = []
    for r in range(reps):
        rows.append(replicate(p, r, chains, warmup, draws, seed0, mutate))
        if verbose and (r + 1) % 10 == 0:
            print(f"  {p.name}: {r + 1}/{reps} replications, {time.perf_counter() - t0:.0f} s",
                  flush=True)
    names = list(rows[0]["ranks"])
    out = {"model": p.name, "info": p.info, "reps": reps, "L": L_DRAWS, "bins": bins,
           "chains": chains, "warmup": warmup, "draws": draws, "mutate": mutate,
           "seconds": time.perf_counter() - t0,
           "reruns": int(sum(r["draws"] > draws for r in rows)),
           "sampler_errors": [{"rep": r["rep"], "sigma": r["truth"]["sigma"], "error": e}
                              for r in rows for e in r["errors"]],
           "min_ess": float(min(r["min_ess"] for r in rows)),
           "stats": {nm: rank_stats(np.array([r["ranks"][nm] for r in rows]), bins)
                     for nm in names},
           "ranks": {nm: [r["ranks"][nm] for r in rows] for nm in names},
           "rep_seconds": [round(r["seconds"], 3) for r in rows]}
    return out


def bonferroni_alpha(family_alpha: float, n_tests: int) -> float:
    return family_alpha / n_tests


def _print(res: dict, alpha: float) -> None:
    print(f"{res['model']} ({res['mutate']}): R = {res['reps']}, {res['seconds']:.0f} s "
          f"({res['seconds'] / res['reps']:.2f} s/rep), reruns {res['reruns']}, "
          f"min ESS {res['min_ess']:.0f}, sampler errors {len(res['sampler_errors'])}")
    for e in res["sampler_errors"]:
        print(f"    rep {e['rep']} (sigma {e['sigma']:.3g}): {e['error']}")
    for nm, s in res["stats"].items():
        verdict = "FAIL" if s["p_value"] < alpha else "pass"
        print(f"  {nm:<6} chi2 = {s['chi2']:6.2f} (df {s['df']}), p = {s['p_value']:.4f} "
              f"[{verdict} at {alpha:.4g}], max bin dev {s['max_bin_dev']:.0%}, "
              f"ECDF max dev {s['ecdf_max_dev']:.3f}; counts {s['counts']}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reps", type=int, default=200)
    ap.add_argument("--models", nargs="+", default=["direct", "field", "anand"],
                    choices=["direct", "field", "anand", "anand_ridge"])
    ap.add_argument("--chains", type=int, default=1)
    ap.add_argument("--warmup", type=int, default=300)
    ap.add_argument("--draws", type=int, default=300)
    ap.add_argument("--bins", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--family-alpha", type=float, default=0.01)
    ap.add_argument("--mutate", default="none",
                    choices=["none", "half-lik", "double-lik", "short", "half-jacobian",
                             "no-jacobian"])
    ap.add_argument("--out", default="benchmarks/results/sbc.json")
    a = ap.parse_args()
    torch.set_default_dtype(DT)
    makers = {"direct": direct_problem, "field": field_problem, "anand": anand_problem,
              "anand_ridge": anand_ridge_problem}
    results: list[dict] = []

    def doc() -> dict:
        n_tests = sum(len(r["stats"]) for r in results)
        return {"method": "SBC (Talts et al. 2018), chi-square on equal rank bins, Bonferroni",
                "family_alpha": a.family_alpha, "n_tests": n_tests,
                "alpha_per_test": bonferroni_alpha(a.family_alpha, n_tests),
                "torch_threads": torch.get_num_threads(), "results": results}

    for m in a.models:
        p = makers[m]()
        results.append(run_sbc(p, a.reps, a.chains, a.warmup, a.draws, a.bins, a.seed,
                               a.mutate, verbose=True))
        if a.out:  # after each model, so a long study keeps what it has
            Path(a.out).write_text(json.dumps(doc(), indent=1) + "\n")
    d = doc()
    for res in results:
        _print(res, d["alpha_per_test"])
    if a.out:
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
