"""A lean No-U-Turn sampler in NumPy for small, cheap log densities.

The algorithm is Stan's (Hoffman & Gelman 2014 as revised by Betancourt 2017): a trajectory is
doubled forwards or backwards at random; a point is drawn from it by multinomial sampling
(uniform progressive sampling within a subtree, biased progressive sampling at the top); the
doubling stops at the generalized U-turn criterion ``v_- . rho > 0 and v_+ . rho > 0``
(``rho`` the summed momenta, ``v = M^-1 p`` at the two ends), checked on every merged subtree
and, as Stan does since 2.21, also across the two halves of every merge (the left half plus the
first point of the right one, and the last point of the left half plus the right one); a
leapfrog step whose energy error exceeds ``max_energy_error`` is divergent and ends the
trajectory. Warm-up is Stan's: dual-averaging step size (target acceptance 0.8, gamma 0.05,
t0 10, kappa 0.75) and a diagonal or dense mass matrix estimated in windows (75 initial
iterations, then windows of 25, 50, 100, ... up to 50 before the end of warm-up), regularized
towards 1e-3 I as Stan does, the step size re-initialized after each update.

Everything works on a flat unconstrained vector ``q (d,)`` and a user function
``logp_and_grad(q) -> (log density (float), gradient (d,))``; per leapfrog step the sampler
adds a few NumPy operations on ``(d,)`` vectors (~10-20 us), so a cheap analytic gradient
(:mod:`solderpyro.calibration.fastkoh`) makes the whole step a fraction of a millisecond.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

LogpGrad = Callable[[np.ndarray], tuple[float, np.ndarray]]

_LOG_08 = math.log(0.8)


@dataclass
class NutsResult:
    """Draws and diagnostics of :func:`sample_nuts`.

    Attributes:
        draws: ``(chains, draws, d)`` unconstrained draws after warm-up.
        divergences: divergent transitions after warm-up, per chain.
        seconds: wall time of everything (warm-up and sampling, all chains).
        step_size: adapted step size per chain.
        inv_metric: adapted inverse mass matrix per chain, ``(d,)`` (diagonal) or ``(d, d)``.
        accept_prob: mean acceptance statistic of the kept draws, per chain.
        n_leapfrog: gradient evaluations per chain (warm-up included).
        tree_depth: ``(chains, draws)`` tree depth of each kept draw.
        diverging: ``(chains, draws)`` bool, whether the transition that made each kept draw
            diverged (where they sit shows what the sampler could not follow).
        sample_stats: per kept draw, each ``(chains, draws)``, ArviZ's names
            (:data:`SAMPLE_STATS`): ``energy`` (the Hamiltonian ``-log p(q) + p M^-1 p / 2``
            at the selected point, nats), ``step_size``, ``tree_depth``, ``n_steps``
            (leapfrog steps of the transition), ``acceptance_rate`` (the mean acceptance
            statistic over the tree), ``lp`` (the log density at the draw, unconstrained
            scale, nats), ``diverging``.
    """

    draws: np.ndarray
    divergences: list[int] = field(default_factory=list)
    seconds: float = float("nan")
    step_size: list[float] = field(default_factory=list)
    inv_metric: list[np.ndarray] = field(default_factory=list)
    accept_prob: list[float] = field(default_factory=list)
    n_leapfrog: list[int] = field(default_factory=list)
    tree_depth: np.ndarray | None = None
    diverging: np.ndarray | None = None
    sample_stats: dict[str, np.ndarray] = field(default_factory=dict)


#: the per-draw statistics of :attr:`NutsResult.sample_stats`, named as ArviZ's
#: ``sample_stats`` group names them (``az.bfmi`` and ``az.plot_energy`` read ``energy``)
SAMPLE_STATS = ("energy", "step_size", "tree_depth", "n_steps", "acceptance_rate", "lp",
                "diverging")


class _Metric:
    """Euclidean metric: momentum sampling and velocities ``M^-1 p``."""

    def __init__(self, inv_metric: np.ndarray) -> None:
        self.inv = inv_metric
        self.dense = inv_metric.ndim == 2
        if self.dense:
            # M = inv^-1 = L^-T L^-1 with inv = L L^T: p = L^-T z has covariance M
            self.chol = np.linalg.cholesky(inv_metric)
            self.chol_t_inv = np.linalg.inv(self.chol.T)
        else:
            self.sd_inv = 1.0 / np.sqrt(inv_metric)

    def sample_p(self, rng: np.random.Generator, d: int) -> np.ndarray:
        z = rng.standard_normal(d)
        return self.chol_t_inv @ z if self.dense else z * self.sd_inv

    def velocity(self, p: np.ndarray) -> np.ndarray:
        return self.inv @ p if self.dense else self.inv * p


def _logaddexp(a: float, b: float) -> float:
    if a > b:
        return a + math.log1p(math.exp(b - a))
    if b == -math.inf:
        return b
    return b + math.log1p(math.exp(a - b))


class _Chain:
    """One chain's NUTS transitions (state: position, log density, gradient)."""

    def __init__(self, f: LogpGrad, q: np.ndarray, lp: float, g: np.ndarray,
                 rng: np.random.Generator, metric: _Metric, step: float,
                 settings: NutsSettings) -> None:
        self.f, self.q, self.lp, self.g = f, q, lp, g
        self.rng, self.metric, self.step = rng, metric, step
        self.max_depth, self.max_de = settings.max_tree_depth, settings.max_energy_error
        self.n_grad = 0

    # -------------------------------------------------------------- step-size heuristic
    def init_step(self) -> None:
        """Stan's heuristic: double or halve the step until one leapfrog's acceptance crosses
        0.8 (momentum resampled each try)."""
        d = self.q.shape[0]
        direction = 0
        for _ in range(100):
            p = self.metric.sample_p(self.rng, d)
            v = self.metric.velocity(p)
            h0 = -self.lp + 0.5 * float(p @ v)
            eps = self.step
            p1 = p + 0.5 * eps * self.g
            q1 = self.q + eps * self.metric.velocity(p1)
            lp1, g1 = self.f(q1)
            self.n_grad += 1
            p1 = p1 + 0.5 * eps * g1
            h = -lp1 + 0.5 * float(p1 @ self.metric.velocity(p1))
            dh = h0 - h if math.isfinite(h) else -math.inf
            if direction == 0:
                direction = 1 if dh > _LOG_08 else -1
            if direction == 1 and not dh > _LOG_08:
                break
            if direction == -1 and not dh < _LOG_08:
                break
            self.step = eps * 2.0 if direction == 1 else eps * 0.5
            if self.step > 1e7 or self.step < 1e-300:
                raise RuntimeError(f"NUTS step-size search failed (step {self.step:g}): the "
                                   "posterior is improper or the gradient is wrong")

    # ------------------------------------------------------------------- one transition
    def transition(self) -> tuple[float, int, bool, int, float]:
        """One NUTS iteration; updates the state. Returns (acceptance statistic, tree depth,
        divergent, leapfrog steps, energy: the Hamiltonian at the selected point, nats)."""
        f, rng, metric, max_de = self.f, self.rng, self.metric, self.max_de
        vel = metric.velocity
        p0 = metric.sample_p(rng, self.q.shape[0])
        v0 = vel(p0)
        h0 = -self.lp + 0.5 * float(p0 @ v0)
        state0 = (self.q, p0, self.g, self.lp, v0)
        eps_abs = self.step
        rand = rng.random
        exp = math.exp
        n_grad = 0

        def crit(va: np.ndarray, vb: np.ndarray, rho: np.ndarray) -> bool:
            return bool(va @ rho > 0.0) and bool(vb @ rho > 0.0)

        def turning(lt: tuple, rt: tuple, rho: np.ndarray) -> bool:
            # lt / rt: (minus, plus, rho, ...) of the earlier / later half in time
            if not crit(lt[0][4], rt[1][4], rho):
                return True
            if not crit(lt[0][4], rt[0][4], lt[2] + rt[0][1]):
                return True
            return not crit(lt[1][4], rt[1][4], rt[2] + lt[1][1])

        # a tree: (minus end, plus end, rho, proposal, log weight, turning, divergent,
        #          sum of acceptance probabilities, leapfrog steps)
        def build(state: tuple, depth: int, eps: float) -> tuple:
            nonlocal n_grad
            if depth == 0:
                q, p, g, _, _ = state
                p = p + (0.5 * eps) * g
                q = q + eps * vel(p)
                lp, g = f(q)
                n_grad += 1
                p = p + (0.5 * eps) * g
                v = vel(p)
                h = -lp + 0.5 * float(p @ v)
                de = h - h0 if h == h else math.inf  # NaN -> infinite energy error
                new = (q, p, g, lp, v)
                return (new, new, p, new, -de, False, de > max_de,
                        1.0 if de <= 0.0 else exp(-de), 1)
            t1 = build(state, depth - 1, eps)
            if t1[5] or t1[6]:
                return t1
            t2 = build(t1[1] if eps > 0 else t1[0], depth - 1, eps)
            acc, nl = t1[7] + t2[7], t1[8] + t2[8]
            if t2[5] or t2[6]:
                return (t1[0], t1[1], t1[2], t1[3], t1[4], t2[5], t2[6], acc, nl)
            lw = _logaddexp(t1[4], t2[4])
            prop = t2[3] if rand() < exp(t2[4] - lw) else t1[3]
            lt, rt = (t1, t2) if eps > 0 else (t2, t1)
            rho = lt[2] + rt[2]
            return (lt[0], rt[1], rho, prop, lw, turning(lt, rt, rho), False, acc, nl)

        minus = plus = state0
        whole = (minus, plus, p0, state0, 0.0, False, False, 0.0, 0)
        prop = state0
        lw = 0.0
        sum_acc, n_leap, depth, divergent = 0.0, 0, 0, False
        while depth < self.max_depth:
            forward = rand() > 0.5
            eps = eps_abs if forward else -eps_abs
            t = build(whole[1] if forward else whole[0], depth, eps)
            depth += 1
            sum_acc += t[7]
            n_leap += t[8]
            if t[6]:
                divergent = True
                break
            if t[5]:
                break
            if t[4] > lw or rand() < exp(t[4] - lw):
                prop = t[3]
            lw = _logaddexp(lw, t[4])
            lt, rt = (whole, t) if forward else (t, whole)
            rho = lt[2] + rt[2]
            whole = (lt[0], rt[1], rho, prop, lw, False, False, 0.0, 0)
            if turning(lt, rt, rho):
                break
        self.q, self.lp, self.g = prop[0], prop[3], prop[2]
        self.n_grad += n_grad
        energy = -prop[3] + 0.5 * float(prop[1] @ prop[4])
        return sum_acc / max(n_leap, 1), depth, divergent, n_leap, energy


class _DualAveraging:
    """Stan's step-size adaptation (Nesterov dual averaging)."""

    def __init__(self, step: float, delta: float, gamma: float = 0.05, t0: float = 10.0,
                 kappa: float = 0.75) -> None:
        self.delta, self.gamma, self.t0, self.kappa = delta, gamma, t0, kappa
        self.restart(step)

    def restart(self, step: float) -> None:
        self.mu = math.log(10.0 * step)
        self.counter, self.s_bar, self.x_bar = 0, 0.0, 0.0

    def learn(self, accept: float) -> float:
        self.counter += 1
        accept = min(1.0, accept)
        eta = 1.0 / (self.counter + self.t0)
        self.s_bar = (1.0 - eta) * self.s_bar + eta * (self.delta - accept)
        x = self.mu - self.s_bar * math.sqrt(self.counter) / self.gamma
        x_eta = self.counter ** (-self.kappa)
        self.x_bar = (1.0 - x_eta) * self.x_bar + x_eta * x
        return math.exp(x)

    def final(self) -> float:
        return math.exp(self.x_bar)


class _Windows:
    """Stan's windowed metric adaptation schedule (75 / 25, 50, ... / 50)."""

    def __init__(self, n_warmup: int, init_buffer: int = 75, term_buffer: int = 50,
                 base_window: int = 25) -> None:
        self.n = n_warmup
        self.active = n_warmup >= 20
        if init_buffer + base_window + term_buffer > n_warmup:
            init_buffer = int(0.15 * n_warmup)
            term_buffer = int(0.1 * n_warmup)
            base_window = n_warmup - (init_buffer + term_buffer)
        self.init_buffer, self.term_buffer = init_buffer, term_buffer
        self.counter, self.size = 0, base_window
        self.next_window = init_buffer + base_window - 1

    def in_window(self) -> bool:
        return (self.active and self.counter >= self.init_buffer
                and self.counter < self.n - self.term_buffer and self.counter != self.n)

    def window_ends(self) -> bool:
        return self.active and self.counter == self.next_window and self.counter != self.n

    def compute_next(self) -> None:
        last = self.n - self.term_buffer - 1
        if self.next_window == last:
            return
        self.size *= 2
        self.next_window = self.counter + self.size
        if self.next_window != last and self.next_window + 2 * self.size >= self.n - \
                self.term_buffer:
            self.next_window = last


def _check_logp(f: LogpGrad, q: np.ndarray, name: str) -> tuple[float, np.ndarray]:
    lp, g = f(q)
    lp = float(lp)
    g = np.asarray(g, dtype=float)
    if g.shape != q.shape:
        raise ValueError(f"logp_and_grad returned a gradient of shape {g.shape} for {name} of "
                         f"shape {q.shape}")
    if not math.isfinite(lp) or not np.all(np.isfinite(g)):
        raise ValueError(f"{name}: the log density or its gradient is not finite there "
                         f"(logp={lp})")
    return lp, g


@dataclass(frozen=True)
class NutsSettings:
    """The knobs of :func:`sample_nuts`.

    Attributes:
        chains, warmup, draws: chain count, warm-up iterations and kept draws per chain.
        seed: chain ``c`` is seeded with ``seed + c``.
        target_accept: the dual-averaging target of the mean acceptance statistic, in (0, 1).
        max_tree_depth: at most ``2**max_tree_depth - 1`` leapfrog steps per iteration.
        dense_mass: adapt a dense inverse mass matrix (else diagonal).
        max_energy_error: an energy error above this is a divergence.
        init_radius, init_tries: without ``init``, starting points are uniform in
            ``(-init_radius, init_radius)`` per coordinate (Pyro's default), redrawn up to
            ``init_tries`` times until the log density and its gradient are finite.
        workers: processes running chains at once (fork; 1: in this process). Each chain's
            random stream is its own, so results are identical for any ``workers``.
    """

    chains: int = 4
    warmup: int = 500
    draws: int = 1000
    seed: int = 0
    target_accept: float = 0.8
    max_tree_depth: int = 10
    dense_mass: bool = False
    max_energy_error: float = 1000.0
    init_radius: float = 2.0
    init_tries: int = 100
    workers: int = 1


def sample_nuts(logp_and_grad: LogpGrad, dim: int, settings: NutsSettings = NutsSettings(),
                init: np.ndarray | None = None, inv_metric: np.ndarray | None = None,
                step_size: float | None = None,
                on_chain: Callable[[int, dict], None] | None = None) -> NutsResult:
    """Run NUTS chains, chain ``c`` seeded with ``settings.seed + c`` (so the draws do not
    depend on ``settings.workers``: chains in parallel give exactly the serial result).

    Args:
        logp_and_grad: ``q (dim,)`` -> (log density up to a constant (float), its gradient
            ``(dim,)``), on the unconstrained scale (log-Jacobians included).
        dim: the dimension ``d`` of the unconstrained vector.
        settings: chain counts and lengths, seed, adaptation and workers
            (:class:`NutsSettings`).
        init: starting points ``(dim,)`` (all chains) or ``(chains, dim)``; None: random
            (``settings.init_radius``, ``settings.init_tries``).
        inv_metric: a warm start's inverse mass matrix ``(dim,)`` or ``(dim, dim)`` (e.g. the
            previous posterior's), used from the first iteration; the windows still adapt it.
        step_size: a warm start's step size (the step-size search starts there; with
            ``warmup=0`` it is used as it is: the continuation of adapted chains).
        on_chain: called as ``on_chain(c, stats)`` when chain ``c`` ends (seconds,
            divergences, step size, leapfrog steps), e.g. to log a line per chain.

    Returns:
        :class:`NutsResult` with draws ``(chains, draws, dim)``.

    Raises:
        ValueError: bad sizes or a given ``init`` where the log density is not finite.
    """
    st = settings
    chains = st.chains
    for nm, v, lo in (("dim", dim, 1), ("chains", chains, 1), ("warmup", st.warmup, 0),
                      ("draws", st.draws, 1), ("max_tree_depth", st.max_tree_depth, 1),
                      ("workers", st.workers, 1)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
            raise ValueError(f"sample_nuts {nm} must be an integer >= {lo}, got {v!r}")
    if not 0.0 < st.target_accept < 1.0:
        raise ValueError(f"sample_nuts target_accept must be in (0, 1), got "
                         f"{st.target_accept}")
    inits: np.ndarray | None = None
    if init is not None:
        inits = np.asarray(init, dtype=float)
        if inits.shape == (dim,):
            inits = np.tile(inits, (chains, 1))
        if inits.shape != (chains, dim):
            raise ValueError(f"sample_nuts init must have shape ({dim},) or ({chains}, {dim}), "
                             f"got {np.shape(init)}")
    metric0 = _initial_metric(inv_metric, dim, st.dense_mass)
    if step_size is not None and not (math.isfinite(step_size) and step_size > 0):
        raise ValueError(f"sample_nuts step_size must be positive, got {step_size}")
    t0 = time.perf_counter()
    job = _ChainJob(logp_and_grad, dim, inits, st, metric0, step_size or 1.0,
                    st.warmup == 0 and step_size is not None)
    outs = _map_chains(job, chains, st.workers, on_chain)
    res = NutsResult(np.stack([o["draws"] for o in outs]),
                     tree_depth=np.stack([o["depth"] for o in outs]),
                     diverging=np.stack([o["diverging"] for o in outs]),
                     sample_stats={k: np.stack([o["stats"][k] for o in outs])
                                   for k in SAMPLE_STATS})
    for o in outs:
        res.divergences.append(o["divergences"])
        res.step_size.append(o["step_size"])
        res.inv_metric.append(o["inv_metric"])
        res.accept_prob.append(o["accept_prob"])
        res.n_leapfrog.append(o["n_leapfrog"])
    res.seconds = time.perf_counter() - t0
    return res


def _initial_metric(inv_metric: np.ndarray | None, dim: int, dense: bool) -> np.ndarray:
    """The first inverse metric: the identity, or a warm start's (diagonal <-> dense as asked)."""
    if inv_metric is None:
        return np.eye(dim) if dense else np.ones(dim)
    m = np.asarray(inv_metric, dtype=float)
    if m.shape not in ((dim,), (dim, dim)) or not np.all(np.isfinite(m)):
        raise ValueError(f"sample_nuts inv_metric must be finite with shape ({dim},) or "
                         f"({dim}, {dim}), got {m.shape}")
    if dense and m.ndim == 1:
        m = np.diag(m)
    elif not dense and m.ndim == 2:
        m = m.diagonal().copy()
    if (m.diagonal() if m.ndim == 2 else m).min() <= 0:
        raise ValueError("sample_nuts inv_metric must be positive definite")
    return m


@dataclass
class _ChainJob:
    """Everything one chain needs (shared by the chains; forked into worker processes)."""

    f: LogpGrad
    dim: int
    inits: np.ndarray | None
    s: NutsSettings
    metric0: np.ndarray
    step0: float
    keep_step: bool = False

    def __call__(self, c: int) -> dict:
        # a trajectory that leaves the typical set overflows the density (exp, log of 0): the
        # sampler rejects a non-finite energy as it should, so NumPy's warnings about it are
        # noise (tens of lines in a log that should have one per chain)
        with np.errstate(over="ignore", divide="ignore", invalid="ignore", under="ignore"):
            return self._chain(c)

    def _chain(self, c: int) -> dict:
        t0 = time.perf_counter()
        rng = np.random.default_rng(self.s.seed + c)
        f = self.f
        if self.inits is not None:
            q = self.inits[c].copy()
            lp, g = _check_logp(f, q, f"init[{c}]")
        else:
            for k in range(self.s.init_tries):
                q = rng.uniform(-self.s.init_radius, self.s.init_radius, self.dim)
                try:
                    lp, g = _check_logp(f, q, "init")
                    break
                except (ValueError, FloatingPointError, np.linalg.LinAlgError):
                    if k == self.s.init_tries - 1:
                        raise ValueError(f"no finite log density at {self.s.init_tries} "
                                         "random initial points: give init") from None
        out = _run_chain(self, q, lp, g, rng)
        out["seconds"] = time.perf_counter() - t0
        return out


_FORKED: _ChainJob | None = None  # the job a forked worker runs (inherited, not pickled)


def _forked_chain(c: int) -> dict:
    assert _FORKED is not None
    return _FORKED(c)


def _map_chains(job: _ChainJob, chains: int, workers: int,
                on_chain: Callable[[int, dict], None] | None) -> list[dict]:
    """Run chains ``0..chains-1``: in this process, or in ``workers`` forked processes (the
    log density is inherited by the fork, so closures over tensors need no pickling)."""
    import multiprocessing as mp

    workers = min(workers, chains)
    if workers <= 1 or "fork" not in mp.get_all_start_methods():
        outs = []
        for c in range(chains):
            outs.append(job(c))
            if on_chain is not None:
                on_chain(c, outs[-1])
        return outs
    from concurrent.futures import ProcessPoolExecutor, as_completed

    global _FORKED
    _FORKED = job
    try:
        with ProcessPoolExecutor(workers, mp_context=mp.get_context("fork")) as ex:
            futs = {ex.submit(_forked_chain, c): c for c in range(chains)}
            res: dict[int, dict] = {}
            for fu in as_completed(futs):
                res[futs[fu]] = fu.result()
                if on_chain is not None:
                    on_chain(futs[fu], res[futs[fu]])
    finally:
        _FORKED = None
    return [res[c] for c in range(chains)]


def _run_chain(job: _ChainJob, q: np.ndarray, lp: float, g: np.ndarray,
               rng: np.random.Generator) -> dict:
    d = q.shape[0]
    dense, warmup = job.s.dense_mass, job.s.warmup
    metric = _Metric(job.metric0)
    ch = _Chain(job.f, q, lp, g, rng, metric, job.step0, job.s)
    if not job.keep_step:
        ch.init_step()
    da = _DualAveraging(ch.step, job.s.target_accept)
    win = _Windows(warmup)
    window: list[np.ndarray] = []
    for _ in range(warmup):
        acc = ch.transition()[0]
        ch.step = da.learn(acc)
        if win.in_window():
            window.append(ch.q)
        if win.window_ends():
            win.compute_next()
            x = np.asarray(window)
            n = x.shape[0]
            if dense:
                cov = np.atleast_2d(np.cov(x, rowvar=False))
                inv = (n / (n + 5.0)) * cov + 1e-3 * (5.0 / (n + 5.0)) * np.eye(d)
            else:
                inv = (n / (n + 5.0)) * x.var(axis=0, ddof=1) + 1e-3 * (5.0 / (n + 5.0))
            window = []
            ch.metric = _Metric(inv)
            ch.init_step()
            da.restart(ch.step)
        win.counter += 1
    if warmup > 0:
        ch.step = da.final()
    n = job.s.draws
    out = np.empty((n, d))
    st = {"energy": np.empty(n), "step_size": np.full(n, ch.step), "lp": np.empty(n),
          "tree_depth": np.empty(n, dtype=np.int64), "n_steps": np.empty(n, dtype=np.int64),
          "acceptance_rate": np.empty(n), "diverging": np.zeros(n, dtype=bool)}
    for i in range(n):
        acc, depth, div, n_leap, energy = ch.transition()
        out[i] = ch.q
        st["energy"][i], st["lp"][i], st["acceptance_rate"][i] = energy, ch.lp, acc
        st["tree_depth"][i], st["n_steps"][i], st["diverging"][i] = depth, n_leap, div
    return {"draws": out, "depth": st["tree_depth"], "diverging": st["diverging"], "stats": st,
            "divergences": int(st["diverging"].sum()), "step_size": ch.step,
            "inv_metric": ch.metric.inv, "accept_prob": sum(st["acceptance_rate"].tolist()) / n,
            "n_leapfrog": ch.n_grad}
