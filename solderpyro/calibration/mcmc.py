"""NUTS through Pyro (or the NumPy sampler of :mod:`.nuts`): several chains, diagnostics,
ArviZ export, the seed's table layout."""

from __future__ import annotations

import csv
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyro
import torch
from pyro.infer import MCMC, NUTS

SUMMARY_COLUMNS = ("parameter", "q2.5", "median", "mean", "q97.5", "r_hat", "ess_bulk",
                   "ess_tail")


def _arviz() -> Any:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        import arviz as az
    return az


def flatten_sites(samples: dict[str, Any], labels: dict[str, list[str]] | None = None
                  ) -> dict[str, np.ndarray]:
    """Sites ``(chain, draw, ...)`` -> scalar columns ``(chain, draw)`` by display name.

    A vector site becomes one column per element, named by ``labels[site]`` or ``site[i]``.
    Accepts torch tensors or array-likes (e.g. NumPyro's jax arrays).
    """
    out = {}
    for site, v in samples.items():
        a = v.detach().cpu().numpy() if isinstance(v, torch.Tensor) else np.asarray(v)
        if a.ndim == 2:
            out[site] = a
            continue
        a = a.reshape(a.shape[0], a.shape[1], -1)
        names = (labels or {}).get(site) or [f"{site}[{i}]" for i in range(a.shape[2])]
        for i, nm in enumerate(names):
            out[nm] = a[:, :, i]
    return out


@dataclass
class Posterior:
    """Posterior draws and sampler diagnostics.

    Attributes:
        samples: site -> ``(chain, draw, ...)`` tensor, in physical units.
        labels: site -> element labels for vector sites (e.g. ``t -> ["s0", "QR"]``).
        divergences: number of divergent transitions per chain.
        seconds: wall time of warm-up plus sampling, all chains.
        raw: the sampler's own sites ``(chain, draw, ...)`` (unit cube, for predictions).
    """

    samples: dict[str, torch.Tensor]
    labels: dict[str, list[str]] = field(default_factory=dict)
    divergences: list[int] = field(default_factory=list)
    seconds: float = float("nan")
    raw: dict[str, torch.Tensor] = field(default_factory=dict)

    @property
    def n_chains(self) -> int:
        return next(iter(self.samples.values())).shape[0]

    def flat(self, site: str) -> torch.Tensor:
        """``(chain * draw, ...)`` draws of one site."""
        v = self.samples[site]
        return v.reshape(-1, *v.shape[2:])

    def columns(self) -> dict[str, np.ndarray]:
        """Scalar parameters by display name -> ``(chain, draw)`` arrays."""
        return flatten_sites(self.samples, self.labels)

    def to_inference_data(self) -> Any:
        """ArviZ InferenceData (posterior group; divergences in sample_stats)."""
        az = _arviz()
        cols = self.columns()
        n_draw = next(iter(cols.values())).shape[1]
        div = np.zeros((self.n_chains, n_draw), dtype=bool)
        for c, k in enumerate(self.divergences):
            div[c, :k] = True  # counts only; positions are not kept
        return az.from_dict(posterior=cols, sample_stats={"diverging": div})

    def summary(self) -> list[dict[str, float | str]]:
        """Rows in the seed's layout (2.5 %, median, mean, 97.5 %) plus R-hat and ESS."""
        az = _arviz()
        idata = self.to_inference_data()
        rhat = az.rhat(idata)
        ess_b = az.ess(idata, method="bulk")
        ess_t = az.ess(idata, method="tail")
        rows: list[dict[str, float | str]] = []
        for nm, a in self.columns().items():
            q = np.quantile(a.reshape(-1), [0.025, 0.5, 0.975])
            rows.append({"parameter": nm, "q2.5": q[0], "median": q[1], "mean": a.mean(),
                         "q97.5": q[2], "r_hat": float(rhat[nm]),
                         "ess_bulk": float(ess_b[nm]), "ess_tail": float(ess_t[nm])})
        return rows

    def min_ess(self) -> float:
        """Smallest bulk ESS over the scalar parameters."""
        return min(float(r["ess_bulk"]) for r in self.summary())

    def save(self, path: str | Path) -> Path:
        """Write the draws as ArviZ NetCDF; returns the path."""
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        self.to_inference_data().to_netcdf(str(p))
        return p


def write_summary(rows: Sequence[dict], path: str | Path,
                  columns: Sequence[str] = SUMMARY_COLUMNS) -> Path:
    """Write summary rows as CSV with the given columns (floats with 6 significant digits)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    with p.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(columns)
        for r in rows:
            w.writerow([r[c] if isinstance(r[c], str) else f"{float(r[c]):.6g}"
                        for c in columns])
    return p


def format_summary(rows: Sequence[dict], columns: Sequence[str] = SUMMARY_COLUMNS) -> str:
    """The summary as an aligned text table."""
    head = f"{columns[0]:<12}" + "".join(f"{c:>11}" for c in columns[1:])
    lines = [head]
    for r in rows:
        lines.append(f"{r[columns[0]]!s:<12}" + "".join(f"{float(r[c]):>11.4g}"
                                                         for c in columns[1:]))
    return "\n".join(lines)


def run_nuts(model: Callable[..., None], args: tuple = (), chains: int = 4, warmup: int = 500,
             draws: int = 1000, seed: int = 0, jit: bool = True, target_accept: float = 0.8,
             max_tree_depth: int = 10, progress: bool = True, threads: int | None = 1,
             full_mass: bool = False, init: str = "uniform", init_draws: int = 256,
             sampler: str = "pyro") -> tuple[dict[str, torch.Tensor], list[int], float]:
    """Run NUTS chains one after another (each seeded ``seed + chain``).

    KOH likelihoods work on matrices of tens to hundreds of rows, where torch's intra-op
    threads cost more than they give (measured: 1 ms per gradient on one thread, up to 100 ms
    with two threads on a busy 2-core machine), so sampling runs on ``threads`` threads
    (None leaves torch's setting alone); the previous setting is restored afterwards.

    Args:
        model: a Pyro model; ``args`` are passed to it.
        chains, warmup, draws: chain count, warm-up and kept draws per chain.
        jit: compile the potential with the PyTorch JIT (falls back to eager if tracing fails).
        full_mass: adapt a dense mass matrix (pays off for correlated posteriors such as the
            full joint's sigma_c / theta / t: 1.7x the ESS per second there).
        init: where the chains start. ``"uniform"`` (default): Pyro's default (uniform in
            (-2, 2) on the unconstrained scale); ``"sir"``: at points resampled, in proportion
            to their likelihood, from ``init_draws`` draws of the prior (:func:`sir_inits`), so
            that chains start where the posterior has its mass and a chain is not left in a
            minor mode that NUTS cannot leave (the specimen calibration's default).
        sampler: ``"pyro"`` (default): Pyro's NUTS on the model's autograd potential.
            ``"fast"``: the NumPy NUTS of :func:`~solderpyro.calibration.nuts.sample_nuts` (the
            same algorithm and Stan-style warm-up) on the analytic log density and gradient of
            :mod:`~solderpyro.calibration.fastkoh`, the same posterior on the same
            unconstrained scale; measured 3-4x (direct) and 11-15x (full joint) the effective
            samples per second of ``"pyro"``, 2-3x NumPyro's (BENCHMARKS.md, issue 4).
            Supports :func:`~.koh.observation_model` with the direct (function) emulator and
            :func:`~.koh.joint_model` with the default priors, the Gaussian kernel, a constant
            mean and no discrepancy; anything else raises NotImplementedError. ``jit`` and
            ``progress`` do not apply to it.

    Returns:
        samples ``site -> (chain, draw, ...)`` (the sampler's sites), divergences per chain,
        wall seconds.
    """
    for nm, v in (("chains", chains), ("warmup", warmup), ("draws", draws),
                  ("init_draws", init_draws)):
        if not isinstance(v, int) or v < (0 if nm == "warmup" else 1):
            raise ValueError(f"run_nuts {nm} must be a positive integer, got {v!r}")
    if init not in ("sir", "uniform"):
        raise ValueError(f"run_nuts init must be 'sir' or 'uniform', got {init!r}")
    if sampler not in ("pyro", "fast"):
        raise ValueError(f"run_nuts sampler must be 'pyro' or 'fast', got {sampler!r}")
    if sampler == "fast":
        return _run_fast(model, args, chains, warmup, draws, seed, target_accept,
                         max_tree_depth, threads, full_mass, init, init_draws)
    per_chain, divs = [], []
    t0 = time.perf_counter()
    with _torch_threads(threads):
        inits = sir_inits(model, args, chains, init_draws, seed) if init == "sir" \
            else [None] * chains
        for c in range(chains):
            pyro.set_rng_seed(seed + c)
            mcmc = _one_chain(model, args, warmup, draws, jit, target_accept, max_tree_depth,
                              progress, c, full_mass, inits[c])
            per_chain.append({k: v.detach() for k, v in mcmc.get_samples().items()})
            d = mcmc.diagnostics()
            divs.append(sum(len(v) for k, v in d.get("divergences", {}).items()))
    seconds = time.perf_counter() - t0
    samples = {k: torch.stack([pc[k] for pc in per_chain]) for k in per_chain[0]}
    return samples, divs, seconds


@contextmanager
def _torch_threads(threads: int | None) -> Iterator[None]:
    """torch's intra-op threads set to ``threads`` (None: left alone), restored on exit."""
    old = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(old)


def _run_fast(model: Callable[..., None], args: tuple, chains: int, warmup: int, draws: int,
              seed: int, target_accept: float, max_tree_depth: int, threads: int | None,
              full_mass: bool, init: str, init_draws: int
              ) -> tuple[dict[str, torch.Tensor], list[int], float]:
    """``run_nuts(sampler="fast")``: :func:`~.nuts.sample_nuts` on the model's
    :class:`~.fastkoh.FlatModel`, draws mapped back to the model's sites."""
    from solderpyro.calibration.fastkoh import flat_model
    from solderpyro.calibration.nuts import sample_nuts

    t0 = time.perf_counter()
    fm = flat_model(model, args)
    limit: Any = nullcontext()
    if threads is not None:
        try:  # BLAS threads: as for torch, one is fastest on these small matrices
            from threadpoolctl import threadpool_limits
            limit = threadpool_limits(threads)
        except ImportError:  # pragma: no cover - threadpoolctl comes with scikit-learn
            pass
    with _torch_threads(threads), limit:
        q0 = None
        if init == "sir":
            pts = sir_inits(model, args, chains, init_draws, seed)
            if all(v is not None for v in pts):
                q0 = np.stack([fm.to_unconstrained(v) for v in pts if v is not None])
        res = sample_nuts(fm.logp_and_grad, fm.dim, chains, warmup, draws, seed, q0,
                          target_accept, max_tree_depth, dense_mass=full_mass)
    return fm.to_samples(res.draws), res.divergences, time.perf_counter() - t0


def sir_inits(model: Callable[..., None], args: tuple, chains: int, n: int = 256,
              seed: int = 0) -> list[dict[str, torch.Tensor] | None]:
    """Chain starting points by sampling-importance-resampling from the prior.

    ``n`` draws of the model's latent sites from their priors are weighted by the likelihood of
    the observed sites (so the weighted draws approximate the posterior) and ``chains`` of them
    are picked by systematic resampling: chains start in the modes in rough proportion to their
    posterior mass. Costs ``n`` model evaluations without gradients.

    Args:
        model: the Pyro model (observed sites carry ``obs=``); args: its arguments.
        chains: how many starting points. n: prior draws. seed: random seed.
    Returns:
        one ``{site: value}`` per chain (constrained values), or ``None`` entries when no draw
        has a finite likelihood (then Pyro's default initialisation is used).
    """
    from pyro import poutine

    pyro.set_rng_seed(seed + 7919)
    pts: list[dict[str, torch.Tensor]] = []
    logw = []
    with torch.no_grad():
        for _ in range(n):
            tr = poutine.trace(model).get_trace(*args)
            tr.compute_log_prob()
            pts.append({k: torch.as_tensor(nd["value"]) for k, nd in tr.nodes.items()
                        if nd["type"] == "sample" and not nd["is_observed"]})
            logw.append(float(sum(nd["log_prob_sum"] for nd in tr.nodes.values()
                                  if nd["type"] == "sample" and nd["is_observed"])))
    lw = np.array(logw, dtype=float)
    lw[~np.isfinite(lw)] = -np.inf
    if not np.isfinite(lw).any():
        return [None] * chains
    w = np.exp(lw - lw.max())
    cdf = np.cumsum(w / w.sum())
    u = (np.random.default_rng(seed).random() + np.arange(chains)) / chains
    return [pts[int(min(np.searchsorted(cdf, ui), n - 1))] for ui in u]


def _one_chain(model: Callable[..., None], args: tuple, warmup: int, draws: int, jit: bool,
               target_accept: float, max_tree_depth: int, progress: bool, chain: int,
               full_mass: bool = False, init: dict[str, torch.Tensor] | None = None) -> MCMC:
    from pyro.infer.autoguide.initialization import init_to_uniform, init_to_value

    strategy = init_to_uniform if init is None else init_to_value(values=init)
    kernel = NUTS(model, jit_compile=jit, ignore_jit_warnings=True, full_mass=full_mass,
                  target_accept_prob=target_accept, max_tree_depth=max_tree_depth,
                  init_strategy=strategy)
    mcmc = MCMC(kernel, num_samples=draws, warmup_steps=warmup, disable_progbar=not progress)
    try:
        mcmc.run(*args)
    except RuntimeError as exc:  # tracing trouble: run eagerly rather than fail
        if not jit:
            raise
        warnings.warn(f"JIT failed for chain {chain} ({exc}); running eagerly", stacklevel=3)
        kernel = NUTS(model, target_accept_prob=target_accept, max_tree_depth=max_tree_depth,
                      full_mass=full_mass, init_strategy=strategy)
        mcmc = MCMC(kernel, num_samples=draws, warmup_steps=warmup, disable_progbar=not progress)
        mcmc.run(*args)
    return mcmc
