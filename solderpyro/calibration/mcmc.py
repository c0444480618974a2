"""NUTS on KOH posteriors (:func:`run_nuts`: one sampler, chains in parallel, warm starts),
diagnostics, ArviZ export, the seed's table layout."""

from __future__ import annotations

import csv
import logging
import math
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

from solderpyro.params import Box

log = logging.getLogger("solderpyro")

SUMMARY_COLUMNS = ("parameter", "q2.5", "median", "mean", "q97.5", "r_hat", "ess_bulk",
                   "ess_tail")


def import_arviz() -> Any:
    """The ``arviz`` module, imported with its FutureWarnings silenced (the import is slow, so
    it happens where ArviZ is first needed)."""
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
        warm: the sampler's adapted state (:class:`WarmStart`), to start a related run.
        stats: per chain: step size, mean acceptance, gradient evaluations.
        diverging: ``(chain, draw)`` bool, which draws came from a divergent transition
            (None: only the counts are known).
        sample_stats: the sampler's per-draw statistics, each ``(chain, draw)``, by ArviZ's
            names (:data:`~.nuts.SAMPLE_STATS`: energy, step_size, tree_depth, n_steps,
            acceptance_rate, lp, diverging); empty where the sampler kept none.
    """

    samples: dict[str, torch.Tensor]
    labels: dict[str, list[str]] = field(default_factory=dict)
    divergences: list[int] = field(default_factory=list)
    seconds: float = float("nan")
    raw: dict[str, torch.Tensor] = field(default_factory=dict)
    warm: WarmStart | None = None
    stats: list[dict[str, float]] = field(default_factory=list)
    diverging: np.ndarray | None = None
    sample_stats: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def n_draws(self) -> int:
        """Draws per chain (after any run-on: :meth:`extend`)."""
        return next(iter(self.samples.values())).shape[1]

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

    def to_inference_data(self, predictive: dict[str, Any] | None = None) -> Any:
        """ArviZ InferenceData: the ``posterior`` group; ``sample_stats`` with the sampler's
        per-draw statistics (:attr:`sample_stats`: energy, step size, tree depth, leapfrog
        steps, acceptance, lp, diverging; ``az.bfmi`` and ``az.plot_energy`` read them) or, for
        a posterior made without them, ``diverging`` alone; with ``predictive`` also
        ``observed_data``, ``posterior_predictive`` and ``log_likelihood`` (variable ``y``,
        dimension ``obs``), so that ``az.plot_ppc``, ``az.loo`` and ``az.compare`` work on the
        file directly. The ``draw`` dimension holds every draw of each chain.

        Args:
            predictive: ``{"y": (n_obs,) data, "index": (k,) flat indices into (chain, draw)
                taken at the same draws of every chain (:func:`thin_index`), "observed":
                (k, n_obs) predictive draws of a new measurement, "log_likelihood": (k, n_obs)
                pointwise log density of the data (nats)}``, optionally ``"coords"``:
                ``{name: (n_obs,) array}`` coordinates of the ``obs`` dimension (``"label"``
                becomes its index, the others, e.g. time_s, point, x_mm, y_mm, ride along;
                without them ``obs`` is ``0..n_obs-1``).
        """
        az = import_arviz()
        cols = self.columns()
        n_draw = next(iter(cols.values())).shape[1]
        if self.diverging is not None:
            div = np.asarray(self.diverging, dtype=bool)
        else:  # counts only (a posterior made without the flags): the first k of each chain
            div = np.zeros((self.n_chains, n_draw), dtype=bool)
            for c, k in enumerate(self.divergences):
                div[c, :k] = True
        stats = {k: np.asarray(v) for k, v in self.sample_stats.items()}
        stats["diverging"] = div
        idata = az.from_dict(posterior=cols, sample_stats=stats)
        if predictive is not None:
            idata.add_groups(**_predictive_groups(predictive, self.n_chains, n_draw))
        return idata

    def summary(self) -> list[dict[str, float | str]]:
        """Rows in the seed's layout (2.5 %, median, mean, 97.5 %) plus R-hat and ESS."""
        az = import_arviz()
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

    def extend(self, more: Posterior) -> Posterior:
        """These chains continued by ``more``'s (the same chains run on from their last
        draws, e.g. :func:`run_nuts` with ``warm=self.warm``): every site's draws and
        per-draw statistics concatenated along the draw axis, divergences added, the time
        summed, ``more``'s warm state kept. (``lp`` and ``energy`` are in the coordinates each
        run sampled in: a continuation in freshly fitted ridge coordinates has them on another
        scale, and BFMI over the join mixes the two.)

        Raises:
            ValueError: ``more`` has other sites or another number of chains.
        """
        if set(more.samples) != set(self.samples) or more.n_chains != self.n_chains:
            raise ValueError(f"Posterior.extend: the continuation has sites "
                             f"{sorted(more.samples)} x {more.n_chains} chains, this posterior "
                             f"{sorted(self.samples)} x {self.n_chains}")
        samples = {k: torch.cat([v, more.samples[k]], 1) for k, v in self.samples.items()}
        raw = {k: torch.cat([v, more.raw[k]], 1) for k, v in self.raw.items() if k in more.raw}
        div = (np.concatenate([self.diverging, more.diverging], 1)
               if self.diverging is not None and more.diverging is not None else None)
        stats = [{**a, "n_grad": a["n_grad"] + b["n_grad"]}
                 for a, b in zip(self.stats, more.stats, strict=True)]
        # per-draw statistics where both runs kept the same ones
        per_draw = {k: np.concatenate([v, more.sample_stats[k]], 1)
                    for k, v in self.sample_stats.items() if k in more.sample_stats}
        return Posterior(samples, dict(self.labels),
                         [a + b for a, b in zip(self.divergences, more.divergences, strict=True)],
                         self.seconds + more.seconds, raw, more.warm, stats, div, per_draw)

    def min_ess(self) -> float:
        """Smallest bulk ESS over the scalar parameters."""
        return min(float(r["ess_bulk"]) for r in self.summary())

    def save(self, path: str | Path, predictive: dict[str, np.ndarray] | None = None
             ) -> Path:
        """Write the draws as ArviZ NetCDF (with ``predictive``: the groups of
        :meth:`to_inference_data`); returns the path."""
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        self.to_inference_data(predictive).to_netcdf(str(p))
        return p


def thin_index(chains: int, draws: int, most: int) -> np.ndarray:
    """Flat indices into ``(chain, draw)`` of at most ``most`` draws, the same evenly spread
    draws of every chain (``(chains * m,)``, chain-major), so that the thinned draws keep
    their chains (ArviZ's LOO takes its relative efficiency from them)."""
    m = max(1, min(draws, most // max(chains, 1)))
    pos = np.linspace(0, draws - 1, m).round().astype(int)
    return (np.arange(chains)[:, None] * draws + pos[None]).reshape(-1)


def _predictive_groups(pr: dict[str, np.ndarray], chains: int, draws: int
                       ) -> dict[str, Any]:
    """``observed_data``, ``posterior_predictive`` and ``log_likelihood`` as xarray
    Datasets (see :meth:`Posterior.to_inference_data`); float32 for the draws (file size)."""
    import xarray as xr

    idx = np.asarray(pr["index"], int)
    m = len(idx) // chains
    if m * chains != len(idx) or not np.array_equal(idx.reshape(chains, m) // draws,
                                                    np.repeat(np.arange(chains)[:, None], m, 1)):
        raise ValueError("predictive draws must be the same draws of every chain (thin_index)")
    pos = idx[:m] % draws
    y = np.asarray(pr["y"], float)
    coords: Any = pr.get("coords") or {}
    extra = {k: np.asarray(v) for k, v in coords.items()}
    for k, v in extra.items():
        if v.shape != y.shape:
            raise ValueError(f"predictive coords[{k!r}] has shape {v.shape}, the data "
                             f"{y.shape}")
    obs = extra.pop("label", np.arange(len(y)))
    obs_co = {"obs": obs, **{k: ("obs", v) for k, v in extra.items()}}
    co = {"chain": np.arange(chains), "draw": pos, **obs_co}

    def ds(name: str) -> Any:
        v = np.asarray(pr[name], np.float32).reshape(chains, m, len(y))
        return xr.Dataset({"y": (("chain", "draw", "obs"), v)}, coords=co)

    return {"observed_data": xr.Dataset({"y": (("obs",), y)}, coords=obs_co),
            "posterior_predictive": ds("observed"), "log_likelihood": ds("log_likelihood")}


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


@dataclass
class WarmStart:
    """A finished run's adapted sampler state, by coordinate name, to start a related run
    (a recalibration with one more effect, a round with more FE runs) where it applies.

    Attributes:
        coords: names of the unconstrained coordinates (calibrated parameters by their box
            names, then the other sites, e.g. ``sigma``).
        q: ``(chains, d)`` the chains' last positions (unconstrained).
        inv_metric: ``(d,)`` or ``(d, d)`` the adapted inverse mass matrix (chains averaged).
        step_size: the adapted step size (median over chains).
        point: where the related run's FE refit of the new model ended (``name -> value``,
            physical units, e.g. from ``solderpyro diagnose``), or None; :meth:`placed` starts
            the chains there.
        draws: ``(N, d)`` draws of the run (unconstrained, columns :attr:`coords`, thinned),
            or None: a run of the same model fits its :class:`~.ridgemap.RidgeMap` to them.
        mapped: where the run sampled in ridge coordinates, ``(RidgeMap, inverse metric,
            step size)`` in those coordinates (chains averaged; the step the chains' median):
            :func:`run_nuts` with ``ridge="same"`` continues the chains in them with no new
            warm-up. Kept in memory only (:meth:`save` does not write it).
    """

    coords: list[str]
    q: np.ndarray
    inv_metric: np.ndarray
    step_size: float
    point: dict[str, float] | None = None
    unit: np.ndarray | None = None
    unit_names: list[str] | None = None
    draws: np.ndarray | None = None
    mapped: Any = None

    def unit_for(self, names: Sequence[str], chains: int) -> np.ndarray:
        """``(chains, p)`` the chains' positions on the unit cube of a box with these names:
        from :attr:`unit` where it holds the name, else from a logit coordinate of that name
        (a state written before :attr:`unit` existed), else 0.5 (the box's middle)."""
        out = np.full((chains, len(names)), 0.5)
        rows = np.arange(chains)
        for j, nm in enumerate(names):
            if self.unit is not None and self.unit_names and nm in self.unit_names:
                out[:, j] = self.unit[rows % self.unit.shape[0], self.unit_names.index(nm)]
            elif nm in self.coords:
                out[:, j] = 1.0 / (1.0 + np.exp(-self.q[rows % self.q.shape[0],
                                                        self.coords.index(nm)]))
        return out

    def placed(self, box: Box, sigma_log: bool, jitter: float = 0.02, seed: int = 0
               ) -> WarmStart:
        """This state with every chain started at :attr:`point` (unchanged when it is None).

        Why: a run whose model missed an effect can leave its chains in separate minor modes
        (R-hat > 1.01), and their last positions then start the recalibration there; the FE's
        own refit with the effect is where the new posterior is (measured on the Moire-motion
        field case: every transition of every round divergent from the old positions).

        Args:
            box: the new calibration box (its names are the parameters).
            sigma_log: the sigma site is log-transformed (a known noise sd); then a
                ``point["sigma"]`` (um) starts it too.
            jitter: sd of the per-chain offsets on the logit scale of the unit cube
                (dispersed starts for R-hat). seed: their random seed.
        Returns:
            a :class:`WarmStart` whose :attr:`unit` positions (on ``box.names``) are the
            point's, jittered; coordinates, metric and step size are this state's (taken by
            name when the sampler starts, :meth:`apply`).
        """
        from solderpyro.calibration.koh import SITE_SIGMA

        if not self.point:
            return self
        chains = self.q.shape[0]
        unit = self.unit_for(box.names, chains)
        rng = np.random.default_rng(seed)
        known = [k for k, nm in enumerate(box.names) if nm in self.point]
        if known:
            x = torch.tensor([[self.point.get(nm, (lo + hi) / 2) for nm, lo, hi in zip(
                box.names, box.lower, box.upper, strict=True)]], dtype=torch.float64)
            u = box.to_unit(x).numpy()[0].clip(1e-4, 1.0 - 1e-4)
            z = np.log(u) - np.log1p(-u)
            for k in known:
                unit[:, k] = 1.0 / (1.0 + np.exp(-(z[k] + jitter * rng.standard_normal(chains))))
        q = self.q.copy()
        sg = self.point.get(SITE_SIGMA)
        if sigma_log and sg is not None and sg > 0 and SITE_SIGMA in self.coords:
            q[:, self.coords.index(SITE_SIGMA)] = (math.log(sg)
                                                   + jitter * rng.standard_normal(chains))
        return WarmStart(list(self.coords), q, self.inv_metric, self.step_size, None, unit,
                         list(box.names))

    def apply(self, coords: Sequence[str], chains: int, dense: bool
              ) -> tuple[np.ndarray, np.ndarray, float]:
        """Starting points ``(chains, d')``, inverse metric and step size for a model whose
        coordinates are ``coords``: shared names take this run's values; a new coordinate
        starts at 0 (its box's middle) with unit inverse metric."""
        idx = [self.coords.index(c) if c in self.coords else -1 for c in coords]
        d = len(coords)
        q = np.zeros((chains, d))
        for j, i in enumerate(idx):
            if i >= 0:
                q[:, j] = self.q[np.arange(chains) % self.q.shape[0], i]
        old = self.inv_metric if self.inv_metric.ndim == 2 else np.diag(self.inv_metric)
        inv = np.eye(d)
        for a, ia in enumerate(idx):
            for b, ib in enumerate(idx):
                if ia >= 0 and ib >= 0:
                    inv[a, b] = old[ia, ib]
        return q, (inv if dense else inv.diagonal().copy()), self.step_size

    def save(self, path: str | Path) -> Path:
        """Write to ``path`` (``.npz``)."""
        p = Path(path)
        arrays: dict[str, Any] = {"coords": np.array(self.coords), "q": self.q,
                                  "inv_metric": self.inv_metric, "step_size": self.step_size}
        if self.unit is not None and self.unit_names:
            arrays |= {"unit": self.unit, "unit_names": np.array(self.unit_names)}
        if self.draws is not None:
            arrays["draws"] = self.draws
        np.savez(p, **arrays)
        return p

    @classmethod
    def load(cls, path: str | Path) -> WarmStart:
        """Read what :meth:`save` wrote.

        Raises:
            FileNotFoundError: naming the file.
        """
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"{p} is missing: the run directory has no sampler state "
                                    "(written by 'solderpyro calibrate' of this version)")
        with np.load(p) as z:
            unit = z["unit"] if "unit" in z.files else None
            names = [str(c) for c in z["unit_names"]] if "unit_names" in z.files else None
            return cls([str(c) for c in z["coords"]], z["q"], z["inv_metric"],
                       float(z["step_size"]), None, unit, names,
                       z["draws"] if "draws" in z.files else None)


@dataclass
class NutsRun:
    """What :func:`run_nuts` returns.

    Attributes:
        samples: ``site -> (chain, draw, ...)`` in the model's constrained units.
        divergences: divergent transitions after warm-up, per chain.
        seconds: wall time (warm-up and sampling, all chains).
        warm: the adapted state, to warm-start a related run.
        stats: per chain: step size, mean acceptance, gradient evaluations.
        diverging: ``(chain, draw)`` bool, which kept draws came from a divergent transition.
        sample_stats: per kept draw, each ``(chain, draw)``: energy, step_size, tree_depth,
            n_steps, acceptance_rate, lp, diverging (:attr:`~.nuts.NutsResult.sample_stats`;
            ``lp`` and ``energy`` in the coordinates the chains ran in, nats).
    """

    samples: dict[str, torch.Tensor]
    divergences: list[int]
    seconds: float
    warm: WarmStart
    stats: list[dict[str, float]]
    diverging: np.ndarray | None = None
    sample_stats: dict[str, np.ndarray] = field(default_factory=dict)


def default_workers(chains: int) -> int:
    """Processes for ``chains`` chains: one per available core, at most one per chain."""
    import os

    try:
        ncpu = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        ncpu = os.cpu_count() or 1
    return max(1, min(chains, ncpu))


@dataclass(frozen=True)
class NutsOptions:
    """The settings of :func:`run_nuts` (every one has a default).

    Attributes:
        chains, warmup, draws: chain count, warm-up and kept draws per chain (4, 500, 1000).
        seed: chain ``c`` is seeded ``seed + c``.
        target_accept: the dual-averaging target of the mean acceptance statistic (0.8).
        max_tree_depth: at most ``2**max_tree_depth - 1`` leapfrog steps per iteration (10).
        progress: log one line per chain (else at DEBUG level).
        threads: torch (and BLAS) threads while sampling (small matrices: one is fastest);
            None leaves them alone; restored afterwards.
        full_mass: adapt a dense mass matrix (correlated posteriors).
        init: ``"uniform"``: uniform in (-2, 2) on the unconstrained scale; ``"sir"``: at
            points resampled, in proportion to their likelihood, from ``init_draws`` prior
            draws (:func:`sir_inits`), so no chain is left in a minor mode.
        workers: chains run in this many forked processes at once (None: one per core, at
            most one per chain); chain ``c`` is seeded ``seed + c`` whatever ``workers`` is,
            so the draws equal the serial run's.
        warm: a related run's :class:`WarmStart`: chains start at its last positions and
            mass matrix (by coordinate name; ``init`` is then ignored). Where it holds draws
            of the same coordinates (a previous round of the same model), the chains run in
            the :class:`~.ridgemap.RidgeMap` coordinates fitted to them: the same posterior,
            its curved ridge straightened (measured: 1.07-2.0x min ESS/s).
        ridge: ``"auto"`` (the map where the draws bend, :func:`ridge_map`), ``"always"``
            (wherever the warm start holds draws of these coordinates, bent or not: what the
            simulation-based calibration of the mapped sampler uses), ``"never"``, or
            ``"same"``: the map ``warm`` sampled in, with its adapted metric and step
            (:attr:`WarmStart.mapped`; a continuation of those chains, ``warmup`` 0; where
            ``warm`` has none, as ``"never"``).
        mapped_accept: the target acceptance in ridge coordinates (at least ``target_accept``;
            None: :data:`MAPPED_ACCEPT`).

    Raises:
        ValueError: naming the setting (as ``run_nuts <name> ...``) when one is out of range.
    """

    chains: int = 4
    warmup: int = 500
    draws: int = 1000
    seed: int = 0
    target_accept: float = 0.8
    max_tree_depth: int = 10
    progress: bool = True
    threads: int | None = 1
    full_mass: bool = False
    init: str = "uniform"
    init_draws: int = 256
    workers: int | None = None
    warm: WarmStart | None = None
    ridge: str = "auto"
    mapped_accept: float | None = None

    def __post_init__(self) -> None:
        for nm in ("chains", "warmup", "draws", "init_draws"):
            v = getattr(self, nm)
            if not isinstance(v, int) or v < (0 if nm == "warmup" else 1):
                raise ValueError(f"run_nuts {nm} must be a positive integer, got {v!r}")
        if self.init not in ("sir", "uniform"):
            raise ValueError(f"run_nuts init must be 'sir' or 'uniform', got {self.init!r}")
        w = self.workers
        if w is not None and (not isinstance(w, int) or w < 1):
            raise ValueError(f"run_nuts workers must be a positive integer, got {w!r}")
        if self.ridge not in ("auto", "always", "never", "same"):
            raise ValueError(f"run_nuts ridge must be 'auto', 'always', 'never' or 'same', got "
                             f"{self.ridge!r}")
        ma = self.mapped_accept
        if ma is not None and not 0.0 < ma < 1.0:
            raise ValueError(f"run_nuts mapped_accept must be in (0, 1), got {ma}")


def run_nuts(model: Callable[..., None], args: tuple = (),
             options: NutsOptions | None = None) -> NutsRun:
    """NUTS on a Pyro model's posterior: the one sampler of solderpyro.

    The model's log density is taken on a flat unconstrained vector (Pyro's transforms and
    log-Jacobians): analytic, with hand-derived gradients, where one is declared for the
    model and covers the configuration (:func:`~.fastkoh.flat_model`: for :mod:`.koh`'s
    models direct, full joint, modular PCA through the reduced likelihood of
    :mod:`.reduced`), else Pyro's own potential energy with autograd (:mod:`.potential`:
    discrepancy, custom priors, local regions, any model). The trajectories are Stan's NUTS
    with its windowed warm-up (:func:`~.nuts.sample_nuts`), checked against Pyro's NUTS on
    the same posteriors in the tests.

    Args:
        model: a Pyro model; ``args`` are passed to it.
        options: the sampler's settings (:class:`NutsOptions`; None: its defaults).

    Returns:
        :class:`NutsRun`: samples ``site -> (chains, draws, ...)`` in the model's units.
    """
    from solderpyro.calibration.fastkoh import flat_model
    from solderpyro.calibration.nuts import NutsSettings, sample_nuts

    o = options or NutsOptions()
    t0 = time.perf_counter()
    lvl = logging.INFO if o.progress else logging.DEBUG
    with _torch_threads(o.threads), _blas_threads(o.threads):
        fm = flat_model(model, args)
        names = coord_names(fm, args)
        st = _in_ridge_coords(_chain_starts(model, args, fm, names, o), names, o, lvl)
        ns = NutsSettings(chains=o.chains, warmup=o.warmup, draws=o.draws, seed=o.seed,
                          target_accept=_target_accept(o, st.rmap),
                          max_tree_depth=o.max_tree_depth, dense_mass=o.full_mass,
                          workers=o.workers or default_workers(o.chains))
        res = sample_nuts(st.f, fm.dim, ns, st.q0, inv_metric=st.inv0, step_size=st.step0,
                          on_chain=_chain_logger(o, lvl))
    return _nuts_run(res, fm, st.rmap, names, args, o, t0)


@dataclass
class _Start:
    """The chains' log density ``f`` (``q (d,) -> (log density, gradient (d,))``), starting
    points ``q0 (chains, d)``, inverse metric ``inv0 ((d,) or (d, d))`` and step size (None
    where the sampler chooses), and the ridge map ``rmap`` the coordinates are in (None:
    the flat model's own)."""

    f: Callable[[np.ndarray], tuple[float, np.ndarray]]
    q0: np.ndarray | None = None
    inv0: np.ndarray | None = None
    step0: float | None = None
    rmap: Any = None


def _blas_threads(threads: int | None) -> Any:
    """A context limiting the BLAS threads to ``threads`` (None, or no threadpoolctl: none)."""
    if threads is None:
        return nullcontext()
    try:  # BLAS threads: as for torch, one is fastest on these small matrices
        from threadpoolctl import threadpool_limits
        return threadpool_limits(threads)
    except ImportError:  # pragma: no cover - threadpoolctl comes with scikit-learn
        return nullcontext()


def _chain_starts(model: Callable[..., None], args: tuple, fm: Any, names: list[str],
                  o: NutsOptions) -> _Start:
    """Where the chains start on ``fm``'s flat vector: a warm start's positions, metric and
    step (by coordinate name, the calibrated parameters at its unit-cube positions), SIR
    points (``init="sir"``), or None (the sampler's uniform draws)."""
    st = _Start(fm.logp_and_grad)
    if o.warm is not None:
        st.q0, st.inv0, st.step0 = o.warm.apply(names, o.chains, o.full_mass)
        box = _theta_box(args)
        if box is not None:  # the parameters' positions whatever their coordinates
            st.q0 = _with_theta(fm, st.q0, o.warm.unit_for(box.names, o.chains))
    elif o.init == "sir":
        pts = sir_inits(model, args, o.chains, o.init_draws, o.seed)
        if all(v is not None for v in pts):
            st.q0 = np.stack([fm.to_unconstrained(v) for v in pts if v is not None])
    return st


def _in_ridge_coords(st: _Start, names: list[str], o: NutsOptions, lvl: int) -> _Start:
    """``st`` carried into ridge coordinates where ``o.ridge`` and the warm start ask for
    them: ``"same"``, the warm start's own map, metric and step; else a map fitted to its
    draws (:func:`ridge_map`), the metric their covariance there, the step searched afresh."""
    warm = o.warm
    if (o.ridge == "same" and warm is not None and warm.mapped is not None
            and list(warm.coords) == list(names)):
        assert st.q0 is not None
        rmap = warm.mapped[0]
        log.log(lvl, "NUTS: the chains run on in the ridge coordinates they sampled in")
        return _Start(rmap.wrap(st.f), rmap.inverse(st.q0), warm.mapped[1], warm.mapped[2],
                      rmap)
    if o.ridge in ("never", "same"):
        return st
    rmap = ridge_map(warm, names, bent=o.ridge == "auto")
    if rmap is None:
        return st
    assert warm is not None and warm.draws is not None and st.q0 is not None
    W = rmap.inverse(warm.draws)
    log.log(lvl, "NUTS: in ridge coordinates fitted to %d draws of the previous posterior",
            len(warm.draws))
    return _Start(rmap.wrap(st.f), rmap.inverse(st.q0), np.cov(W.T) if o.full_mass else W.var(0),
                  None, rmap)


def _target_accept(o: NutsOptions, rmap: Any) -> float:
    """NUTS's target acceptance: ``o.target_accept``, at least :data:`MAPPED_ACCEPT` (or
    ``o.mapped_accept``) in ridge coordinates."""
    if rmap is None:
        return o.target_accept
    return max(o.target_accept, MAPPED_ACCEPT if o.mapped_accept is None else o.mapped_accept)


def _chain_logger(o: NutsOptions, lvl: int) -> Callable[[int, dict], None]:
    """``on_chain(c, stats)`` for :func:`~.nuts.sample_nuts`: one log line per chain."""
    def on_chain(c: int, st: dict) -> None:
        log.log(lvl, "NUTS chain %d/%d: %d + %d iterations in %.1f s (step %.3g, %d "
                "gradients, %d divergent)", c + 1, o.chains, o.warmup, o.draws, st["seconds"],
                st["step_size"], st["n_leapfrog"], st["divergences"])
    return on_chain


def _nuts_run(res: Any, fm: Any, rmap: Any, names: list[str], args: tuple, o: NutsOptions,
              t0: float) -> NutsRun:
    """The :class:`NutsRun` of :func:`~.nuts.sample_nuts`'s result ``res``: draws back in the
    flat model's coordinates, constrained samples, and the warm state for a next run."""
    from solderpyro.calibration.koh import SITE_T

    Q = res.draws if rmap is None else rmap.forward(res.draws)[0]
    flat = Q.reshape(-1, Q.shape[-1])
    # the mass matrix for a next run in these (unmapped) coordinates: the draws' own
    # covariance where the chains ran in mapped ones
    inv = (np.mean(np.stack(res.inv_metric), 0) if rmap is None else
           (np.cov(flat.T) if o.full_mass else flat.var(0)))
    samples = fm.to_samples(Q)
    box = _theta_box(args)
    unit = (samples[SITE_T][:, -1].reshape(o.chains, -1).cpu().numpy().astype(float)
            if box is not None and SITE_T in samples else None)
    keep = np.linspace(0, len(flat) - 1, min(len(flat), WARM_DRAWS)).round().astype(int)
    ws = WarmStart(names, Q[:, -1].copy(), inv, float(np.median(res.step_size)),
                   None, unit, list(box.names) if unit is not None and box else None,
                   flat[keep].copy() if chains_agree(Q) else None,
                   None if rmap is None else (rmap, np.mean(np.stack(res.inv_metric), 0),
                                              float(np.median(res.step_size))))
    stats = [{"step_size": float(a), "accept_prob": float(b), "n_grad": float(c)}
             for a, b, c in zip(res.step_size, res.accept_prob, res.n_leapfrog, strict=True)]
    return NutsRun(samples, res.divergences, time.perf_counter() - t0, ws, stats,
                   res.diverging, dict(res.sample_stats))


#: draws a :class:`WarmStart` keeps (thinned evenly through the chains) for a next run's map
WARM_DRAWS = 1000
#: NUTS's target acceptance in ridge coordinates. Why: the map takes the step from ~0.1 to
#: ~0.5; with a first form of the map (quadratic terms in every coordinate) the default 0.8
#: cost 0.5 % of transitions as divergences on the CTE-slope posterior (29-39 of 6,000, a
#: scratch run), 0.9 one. With the bend test, `benchmarks/ridge_coords.py` on that posterior:
#: 0.8 -> 7 divergent, min ESS/s 2.78x the plain coordinates; 0.9 -> 4, 1.46x;
#: not re-chosen since
MAPPED_ACCEPT = 0.9
#: the largest R-hat of chains whose draws a next run's ridge map is fitted to
MAP_RHAT = 1.1


def chains_agree(draws: np.ndarray) -> bool:
    """Whether ``draws (chains, n, d)`` describe one posterior: rank-normalized split R-hat
    (ArviZ) at most :data:`MAP_RHAT` for every coordinate. Why: chains in separate surrogate
    islands (a model that misfits) give a quadratic map fitted to several modes at once, which
    bends the posterior instead of straightening it (the loop's base run: 100 gradients per
    iteration at step 0.06 in such coordinates, 7-15 without them)."""
    import arviz as az

    if draws.shape[0] < 2 or draws.shape[1] < 4:
        return False
    r = az.rhat(az.convert_to_dataset({"q": draws}))["q"].values
    return bool(np.all(np.isfinite(r)) and np.max(r) <= MAP_RHAT)


def ridge_map(warm: WarmStart | None, names: Sequence[str], bent: bool = True) -> Any:
    """The :class:`~.ridgemap.RidgeMap` of ``warm``'s draws when they are of exactly the
    coordinates ``names`` (a previous round of the same model), enough, and curved (some
    coordinate keeps its quadratic terms: else a dense mass matrix does what the map would;
    ``bent=False`` drops that condition), else None."""
    from solderpyro.calibration.ridgemap import MIN_DRAWS, RidgeMap

    if (warm is None or warm.draws is None or list(warm.coords) != list(names)
            or len(names) < 2 or len(warm.draws) < MIN_DRAWS
            or not np.all(np.isfinite(warm.draws))):
        return None
    m = RidgeMap(warm.draws)
    return m if any(m.curved) or not bent else None


def _theta_box(args: tuple) -> Any:
    """The calibration box of a :mod:`.koh` model's inputs (None for other models)."""
    if not args:
        return None
    a0 = args[0]
    return getattr(a0, "theta_box", None) or getattr(getattr(a0, "data", None), "theta_box",
                                                     None)


def _with_theta(fm: Any, q0: np.ndarray, unit: np.ndarray) -> np.ndarray:
    """``q0 (chains, d)`` with the theta site's coordinates set to the unit-cube positions
    ``unit (chains, p)``, through the model's own transform (logit or flow coordinates)."""
    from solderpyro.calibration.koh import SITE_T

    if SITE_T not in {s.name for s in getattr(fm, "sites", [])}:
        return q0
    samp = fm.to_samples(q0[:, None, :])
    out = q0.copy()
    for c in range(q0.shape[0]):
        vals = {k: v[c, 0] for k, v in samp.items()}
        vals[SITE_T] = torch.as_tensor(unit[c].clip(1e-9, 1.0 - 1e-9))
        out[c] = fm.to_unconstrained(vals)
    return out


def coord_names(fm: Any, args: tuple) -> list[str]:
    """Names of a flat model's coordinates: the calibrated parameters by their box names
    (from the model's inputs), other sites by ``site`` or ``site[i]``."""
    from solderpyro.calibration.koh import SITE_T

    box = _theta_box(args)
    names = list(getattr(fm, "coord_names", []))
    if not names:
        names = [f"{s.name}[{i}]" if s.vector else s.name for s in fm.sites
                 for i in range(s.size)]
    if box is not None:
        t_idx = [i for i, n in enumerate(names) if n.startswith(SITE_T + "[")]
        if len(t_idx) == box.dim:
            for i, nm in zip(t_idx, box.names, strict=True):
                names[i] = nm
    for i, suffix in getattr(fm, "coord_suffix", {}).items():
        names[i] += suffix
    return names


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
