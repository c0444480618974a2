"""The adaptive design loop: the calibration places its own FE runs until the FE agrees.

A small space-filling start, then rounds of

    fit the surrogate -> posterior (warm-started) -> FE at a few posterior draws (the check)
    -> stop? -> acquire q runs (:mod:`solderpyro.design.acquisition`: by default the q
    posterior draws where the code variance falls most, greedily in closed form)
    -> one batched FE solve -> refit ...

The engine is generic: it sees the FE, the surrogate fit and the posterior only as callables
(:class:`LoopProblem`), so the same loop runs the specimen calibration
(:mod:`solderpyro.pipeline`) and the toys of the tests.

Stopping rule (both parts must hold; ``n`` observed values, ``s = sqrt(2 n)`` the chi-square's
own sampling sd under the noise):

1. **code**: the surrogate's noise-weighted code variance at the posterior draws is small,
   ``E_post[sum_i var_code(eta_i) / sigma^2] <= code_tol * s``: the code uncertainty inflates
   the chi-square by less than its own sampling spread (per output: code sd <=
   ``(2/n)^(1/4)`` noise sd at ``code_tol = 1``, 0.17 for the 2,232-value field).
2. **FE confirms**: at the ``check`` posterior draws the FE's chi-square equals the one the
   surrogate predicts, ``max_j |chi2_FE(theta_j) - chi2_sur(theta_j)| <= fe_tol * s``,
3. **and the surrogate's error does not tilt the posterior**: the gaps ``g_j = chi2_FE -
   chi2_sur`` differ across the checked draws by at most ``fe_spread`` (chi-square units; 2:
   a weight error of at most e between any two of them). A gap common to all draws only
   rescales the likelihood; a gap that varies moves the posterior. ``check_ends`` of the
   checks sit at the 1 % and 99 % points of the draws along their longest axes (the ends of
   a ridge), the rest spread through the chains: the surrogate's error where its posterior
   *ends* is what rule 2 at draws from the bulk cannot see (measured on the clean field
   data: gaps -2.5 in the bulk, +3.7 at the true constants beyond the surrogate posterior's
   end; the design stopped at 58 runs with 3 of 4 true constants outside the intervals).

It also stops when the next round would exceed ``budget`` FE runs, and then says so.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch

from solderpyro.params import Box
from solderpyro.surrogate import GPSurrogate

log = logging.getLogger("solderpyro")


#: the design's FE runs by default up to :data:`BUDGET_DIMS` FE parameters
BASE_BUDGET = 110
#: past this many FE parameters the default budget grows by a round per parameter
BUDGET_DIMS = 5


@dataclass
class LoopSettings:
    """How the adaptive design runs (all counts are FE runs).

    Attributes:
        start: space-filling (Latin hypercube) runs before the first round.
        batch: q, runs acquired per round (one batched FE solve).
        check: FE runs at posterior draws per round: the FE's confirmation; they join the
            training runs of the next round (no run is wasted).
        budget: the most FE runs the loop makes (start + rounds); the loop stops before a
            round that would exceed it. None (the default): :data:`BASE_BUDGET` runs up to
            :data:`BUDGET_DIMS` FE parameters and one round (``batch + check`` runs) more for
            each parameter past them (:meth:`runs_allowed`). Why: on the forms benchmark a
            recalibration with two effects (9 FE parameters: the surrogate's leave-one-out
            error 41 % of the output's spread at 110 runs) ran its 110 runs out with the FE
            disagreeing, and its FE-exact posterior's weights were not reliable: the FE's own
            best fit with its Laplace spread was reported, the true tau and s0 outside; with
            158 runs (this default) the same case's intervals hold every truth (docs/design.md).
        criterion: ``"loglik"`` (:class:`~.acquisition.qIntegratedLogLikVariance`) or
            ``"variance"`` (:func:`~.acquisition.integrated_code_variance`).
        optimizer: ``"draws"`` (the best q of ``candidates`` posterior draws) or
            ``"optimize"`` (BoTorch's ``optimize_acqf``); see docs/design.md for why
            ``"draws"`` is the default.
        mc_points: posterior draws the criteria integrate over.
        candidates: posterior draws offered to the ``"draws"`` optimizer.
        code_tol, fe_tol: the stopping rule's tolerances in units of sqrt(2 n).
        fe_spread: the most the FE-vs-surrogate chi-square gap may vary across the checked
            draws (chi-square units; the stopping rule's part 3).
        check_ends: how many of the ``check`` draws sit at the ends of the posterior's
            longest axes (pairs: the 1 % and 99 % points along the first ``check_ends // 2``
            principal axes of the draws in the unit box); the rest spread through the chains.
        misfit_check: from this round on, the problem's ``misfit`` test runs (at most once
            per calibration, when the FE misfits the data at every checked draw); when it says
            the FE's own best fit misfits, the loop stops (reason ``"misfit"``): refining the
            surrogate of a model that cannot fit the data does not help it (0: never).
        far_tol: a round whose code chi-square or FE-vs-surrogate gap exceeds ``far_tol``
            x sqrt(2 n) is far from converged: the misfit test then computes the FE's best
            fit even when some checked draw fits (and so localizes the design, below). Why:
            a cold start with the CTE's temperature slope (6 parameters) ran to its budget
            with code chi-square 1e3-6e4 every round, its checked draws fitting, so the test
            never ran.
        localize: when that test finds instead that the model *can* fit (its best fit is
            within noise), the most of its FE runs, best first and at least
            :data:`LOCAL_SPACING` apart in the unit box, that join the training runs (kind
            ``"fe_fit"``, counted in the budget) in place of that round's acquisition, and
            the next posterior's chains start at the best fit (0: neither). Why: a cold start
            with a temperature effect (stress-free temperature, 5 parameters) spent its 110
            runs on a surrogate of the whole box whose posterior never came near the data
            (code chi2 1e4-4e5 every round), while the test's 88 runs had found the FE's
            best fit at 1.00 noise sd in round 2 and were thrown away.
    """

    start: int = 30
    batch: int = 8
    check: int = 4
    budget: int | None = None
    criterion: str = "loglik"
    optimizer: str = "draws"
    mc_points: int = 256
    candidates: int = 512
    code_tol: float = 1.0
    fe_tol: float = 1.0
    fe_spread: float = 2.0
    check_ends: int = 2
    misfit_check: int = 2
    far_tol: float = 10.0
    localize: int = 16

    def validate(self, dim: int) -> None:
        """Raise ``ValueError`` naming the first bad field (``dim``: FE parameters)."""
        from solderpyro.design.acquisition import CRITERIA, OPTIMIZERS

        if self.start < dim + 2:
            raise ValueError(f"design.start must be >= {dim + 2} (parameters + 2), got "
                             f"{self.start}")
        for nm in ("batch", "check", "mc_points", "candidates"):
            if getattr(self, nm) < 1:
                raise ValueError(f"design.{nm} must be >= 1, got {getattr(self, nm)}")
        if self.budget is not None and self.budget < self.start + self.check:
            raise ValueError(f"design.budget ({self.budget}) must be >= design.start + "
                             f"design.check ({self.start + self.check}): one round")
        if self.criterion not in CRITERIA:
            raise ValueError(f"design.criterion must be one of {CRITERIA}, got "
                             f"{self.criterion!r}")
        if self.optimizer not in OPTIMIZERS:
            raise ValueError(f"design.optimizer must be one of {OPTIMIZERS}, got "
                             f"{self.optimizer!r}")
        for nm in ("code_tol", "fe_tol", "fe_spread", "far_tol"):
            if not getattr(self, nm) > 0:
                raise ValueError(f"design.{nm} must be > 0, got {getattr(self, nm)}")
        if not 0 <= self.check_ends <= self.check or self.check_ends % 2:
            raise ValueError(f"design.check_ends must be even and in 0 .. design.check "
                             f"({self.check}), got {self.check_ends}")
        if self.misfit_check < 0:
            raise ValueError(f"design.misfit_check must be >= 0 (0: never), got "
                             f"{self.misfit_check}")
        if self.localize < 0:
            raise ValueError(f"design.localize must be >= 0 (0: never), got {self.localize}")

    def runs_allowed(self, dim: int) -> int:
        """The most FE runs the design makes with ``dim`` FE parameters: ``budget`` where
        set, else :data:`BASE_BUDGET` plus ``batch + check`` for each parameter past
        :data:`BUDGET_DIMS` (never less than one round past the start)."""
        if self.budget is not None:
            return self.budget
        grown = BASE_BUDGET + (self.batch + self.check) * max(0, dim - BUDGET_DIMS)
        return max(grown, self.start + self.check)


@dataclass
class Draws:
    """What the loop needs of a posterior.

    Attributes:
        theta: ``(N, d)`` draws of the FE parameters, physical units.
        sigma: ``(N,)`` noise sd per draw, output units (um).
        offset: ``(N, n_y)`` what observation-side parameters add at each draw (or None).
        posterior: the sampler's own result (passed back as ``warm`` to the next round).
        start: where the next posterior's chains start (``name -> value``, physical units:
            the FE's best fit, set by the loop when it localizes), or None: where this one's
            ended.
        checked: set by the loop after its FE check: ``(theta (k, d), V (k, n_y), chi2
            (k,))``, the checked draws, the FE's outputs there and their chi-squares (inf
            where the FE failed).
        chains: how many chains the draws come from, laid out one after another (the final
            posterior's FE check takes draws of each).
    """

    theta: torch.Tensor
    sigma: torch.Tensor
    offset: torch.Tensor | None = None
    posterior: Any = None
    start: dict[str, float] | None = None
    checked: tuple[torch.Tensor, torch.Tensor, np.ndarray] | None = None
    chains: int = 1


@dataclass
class LoopProblem:
    """The loop's view of a calibration.

    Attributes:
        box: the FE parameters' box (what the runs vary).
        y: ``(n_y,)`` observations.
        fe: ``theta (m, d) physical -> (V (m, n_y), ok (m,) bool)``: one batched FE solve of
            the observed outputs (stored as it finishes; NaN rows where not converged).
        fit: ``(X (n, d), Y (n, n_y)) -> GPSurrogate``.
        sample: ``(gp, previous Draws or None, final: bool) -> Draws``; ``final`` asks for the
            full-length posterior (the rounds' may be shorter, warm-started).
        misfit: optional ``(draws, checked indices (k,), their FE chi-squares (k,), far) ->
            dict or None``: whether the model can fit the data at all (e.g. the FE's own best
            fit from the best checked draws); ``far``: the round is far from converged
            (:attr:`LoopSettings.far_tol`), so a verdict is wanted even where some checked
            draw fits. None: no verdict this round; a dict is recorded as
            :attr:`LoopResult.best_fit`, and its ``"misfits"`` key stops the loop. Its ``"x"``
            (``name -> value``) and ``"runs"`` (``(m, d)`` the FE parameter sets the test ran,
            best chi-square first) localize the design when the model can fit
            (:attr:`LoopSettings.localize`).
    """

    box: Box
    y: torch.Tensor
    fe: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
    fit: Callable[[torch.Tensor, torch.Tensor], GPSurrogate]
    sample: Callable[[GPSurrogate, Draws | None, bool], Draws]
    misfit: Callable[[Draws, np.ndarray, np.ndarray, bool], dict[str, Any] | None] | None = None


@dataclass
class Round:
    """One round of the loop (one line of the log, one row of ``design_rounds.csv``)."""

    round: int
    runs: int  # FE runs so far, this round's check included
    code_chi2: float
    fe_chi2: list[float]
    surrogate_chi2: list[float]
    tolerance: float
    code_ok: bool
    fe_ok: bool
    acquired: int = 0
    acquisition: float = float("nan")
    quantiles: dict[str, list[float]] = field(default_factory=dict)
    seconds: float = 0.0
    timing: dict[str, float] = field(default_factory=dict)  # s per step: fit, posterior, ...
    spread_tolerance: float = float("nan")  # the rule's fe_spread (chi-square)

    @property
    def fe_gap(self) -> float:
        """``max_j |chi2_FE - chi2_surrogate|`` over the checked draws (nan without any)."""
        if not self.fe_chi2:
            return float("nan")
        return float(np.max(np.abs(np.subtract(self.fe_chi2, self.surrogate_chi2))))

    @property
    def fe_spread(self) -> float:
        """``max_j g_j - min_j g_j`` of the gaps ``g = chi2_FE - chi2_surrogate`` (nan
        without any)."""
        if not self.fe_chi2:
            return float("nan")
        g = np.subtract(self.fe_chi2, self.surrogate_chi2)
        return float(np.ptp(g))

    def line(self) -> str:
        d = self.fe_gap
        return (f"design round {self.round}: {self.runs} FE runs; code chi2 "
                f"{self.code_chi2:.3g} ({'ok' if self.code_ok else 'too large'}), |FE - "
                f"surrogate| chi2 {d:.3g} (spread {self.fe_spread:.2g}; "
                f"{'ok' if self.fe_ok else 'disagree'}), tolerance "
                f"{self.tolerance:.3g}; +{self.acquired} runs; {self.seconds:.1f} s ("
                + ", ".join(f"{k} {v:.1f}" for k, v in self.timing.items()) + ")")


@dataclass
class LoopResult:
    """The loop's outcome.

    Attributes:
        gp: the last surrogate; draws: its full-length posterior.
        X, Y, ok: every FE run the loop made ``(n, d)``, ``(n, n_y)``, ``(n,)``; kind: per
            run ``"start"``, ``"acquired"`` or ``"check"``; round: per run.
        rounds: the per-round records. reason: why it stopped (``"converged"``,
            ``"budget"`` or ``"misfit"``: the FE's own best fit misfits the data). message:
            that, in words. best_fit: the problem's ``misfit`` verdict where one was made.
        budget: the most FE runs the design was allowed (:meth:`LoopSettings.runs_allowed`
            for the box's dimension: the set budget, or the default's for that many
            parameters).
    """

    gp: GPSurrogate
    draws: Draws
    X: torch.Tensor
    Y: torch.Tensor
    ok: torch.Tensor
    kind: list[str]
    round: list[int]
    rounds: list[Round]
    reason: str
    message: str
    best_fit: dict[str, Any] | None = None
    budget: int | None = None

    @property
    def converged(self) -> bool:
        return self.reason == "converged"

    def as_dict(self) -> dict[str, Any]:
        return {"reason": self.reason, "message": self.message, "fe_runs": int(len(self.X)),
                "budget": self.budget,
                **({"best_fit": self.best_fit} if self.best_fit else {}),
                "rounds": [asdict(r) for r in self.rounds]}


def chi2_terms(gp: GPSurrogate, d: Draws, y: torch.Tensor, rows: np.ndarray
               ) -> tuple[np.ndarray, float]:
    """The surrogate's chi-square at ``d.theta[rows]`` (mean prediction) ``(m,)``, and its
    code chi-square ``E_post[sum_i var_i / sigma^2]`` over all of ``d``."""
    with torch.no_grad():
        mu, var = gp.predict(d.theta)
    mu, var = mu.reshape(len(d.theta), -1), var.reshape(len(d.theta), -1)
    off = 0 if d.offset is None else d.offset
    r = (y - mu - off) / d.sigma[:, None]
    code = float((var / d.sigma[:, None] ** 2).sum(1).mean())
    return r[rows].square().sum(1).numpy(), code


def fe_at_draws(p: LoopProblem, gp: GPSurrogate, d: Draws, y: torch.Tensor, rows: np.ndarray,
                code_draws: int | None = None
                ) -> tuple[torch.Tensor, torch.Tensor, np.ndarray, np.ndarray, float]:
    """The FE check at ``d.theta[rows]``: the FE's outputs there, their chi-squares (the
    residual ``y - (FE + observation-side offset)``, inf where the FE failed), the
    surrogate's chi-squares at the same draws and its code chi-square (:func:`chi2_terms`,
    over all of ``d`` or, with ``code_draws``, that many spread through it). Sets
    ``d.checked``.

    Returns:
        ``V (k, n_y)``, ``ok (k,)``, FE chi2 ``(k,)``, surrogate chi2 ``(k,)``, code chi2.
    """
    th = d.theta[rows]
    V, ok = p.fe(th)
    off = 0 if d.offset is None else d.offset[rows]
    # the residual exactly as chi2_terms takes it for the surrogate, offset subtracted: with
    # the opposite sign every calibration with Moire rigid motion disagrees with the FE by
    # ~5e5 in chi-square and never stops
    fe_c2 = (((y - V - off) / d.sigma[rows, None]) ** 2).sum(1).numpy()
    fe_c2[~ok.numpy()] = np.inf
    if code_draws is None:
        sur_c2, code = chi2_terms(gp, d, y, rows)
    else:  # the code chi-square over fewer draws (6,000 took seconds of GP prediction)
        sub = np.unique(np.concatenate([spread_indices(len(d.theta), code_draws), rows]))
        sur_c2, code = chi2_terms(gp, Draws(d.theta[sub], d.sigma[sub], None
                                            if d.offset is None else d.offset[sub]),
                                  y, np.searchsorted(sub, rows))
    d.checked = (th, V, fe_c2)
    return V, ok, fe_c2, sur_c2, code


def _quantiles(theta: torch.Tensor, names: list[str]) -> dict[str, list[float]]:
    """The 2.5, 50 and 97.5 % quantiles of each column of ``theta (N, d)``, by name."""
    q = torch.quantile(theta, torch.tensor([0.025, 0.5, 0.975], dtype=torch.float64), 0)
    return {nm: q[:, j].tolist() for j, nm in enumerate(names)}


def stop_rule(code_chi2: float, fe_chi2: np.ndarray, sur_chi2: np.ndarray, n: int,
              s: LoopSettings) -> tuple[bool, bool, float]:
    """``(code_ok, fe_ok, tolerance)`` of the stopping rule (module docstring)."""
    tol = math.sqrt(2 * n)
    fe = np.asarray(fe_chi2, float)
    gap = fe - np.asarray(sur_chi2, float)
    fe_ok = (bool(fe.size) and bool(np.all(np.isfinite(fe)))
             and bool(np.max(np.abs(gap)) <= s.fe_tol * tol)
             and bool(np.ptp(gap) <= s.fe_spread))
    return code_chi2 <= s.code_tol * tol, fe_ok, tol


class StageClock:
    """Seconds per named step since the last call (summed when a name repeats); with
    ``log_each`` every step is also a log line (``stage NAME: 1.2 s``)."""

    def __init__(self, log_each: bool = False) -> None:
        self.seconds: dict[str, float] = {}
        self._log = log_each
        self._t = time.perf_counter()

    def __call__(self, name: str) -> None:
        now = time.perf_counter()
        self.seconds[name] = round(self.seconds.get(name, 0.0) + now - self._t, 2)
        if self._log:
            log.info("stage %s: %.1f s", name, now - self._t)
        self._t = now


def check_indices(unit: np.ndarray, m: int, ends: int) -> np.ndarray:
    """``m`` distinct draws for the FE check: ``ends`` of them (pairs) the draws nearest the
    1 % and 99 % points along the draws' first ``ends // 2`` principal axes, the others spread
    through the chains (:func:`spread_indices`).

    Args:
        unit: ``(N, d)`` draws in the unit box. m: how many (``<= N``). ends: even, ``<= m``.
    Returns:
        ``(min(m, N),)`` indices into ``unit``.
    """
    N = len(unit)
    out: list[int] = []
    if ends and N > m:
        c = unit - unit.mean(0)
        _, _, vt = np.linalg.svd(c, full_matrices=False)
        for a in range(min(ends // 2, vt.shape[0])):
            z = c @ vt[a]
            for q in (0.01, 0.99):
                order = np.argsort(np.abs(z - np.quantile(z, q)))
                out.append(int(next(i for i in order if i not in out)))
    rest = np.asarray([i for i in range(N) if i not in out], dtype=int)
    return np.concatenate([np.asarray(out, dtype=int),
                           rest[spread_indices(len(rest), m - len(out))]])


#: the least distance (unit box) between two of the FE best fit's runs that join the design,
#: and between them and the runs already in it: the fit's difference steps (0.1 % of the box)
#: would be near-duplicates of its iterates, which add no information and ill-condition the GP
LOCAL_SPACING = 0.02


def spaced_rows(cand: np.ndarray, have: np.ndarray, m: int, spacing: float = LOCAL_SPACING
                ) -> np.ndarray:
    """At most ``m`` of ``cand``, taken in order, each at least ``spacing`` (Euclidean) from
    the ones taken before and from every row of ``have``.

    Args:
        cand: ``(k, d)`` candidate rows in the unit box, in order of preference; rows with a
            non-finite entry are skipped. have: ``(n, d)`` rows already taken (unit box).
    Returns:
        ``(<= m,)`` indices into ``cand``.
    """
    kept: list[int] = []
    ref = [np.asarray(h, float) for h in have]
    for i, c in enumerate(np.asarray(cand, float)):
        if len(kept) >= m:
            break
        if not np.all(np.isfinite(c)):
            continue
        if ref and np.min(np.linalg.norm(np.asarray(ref) - c, axis=1)) < spacing:
            continue
        kept.append(i)
        ref.append(c)
    return np.asarray(kept, dtype=int)


#: FE runs per chain that check the final posterior (:func:`chain_check_indices`). Why: the
#: rounds' short posteriors (350 iterations per chain) and their four check draws missed an
#: island that only the surrogate fitted; the final run's longer chains reached it (the
#: kinematic-hardening field case: one chain of four at FE chi2 6,800-23,000
#: where the surrogate predicted ~2,170, R-hat 1.53), and the FE check of the reported run
#: looked only at its best draw
FINAL_CHECK_PER_CHAIN = 2


def _n_chains(d: Draws) -> int:
    return max(1, int(d.chains))


def _chain_of(d: Draws, i: int) -> int:
    """The chain (0-based) of draw ``i`` of ``d`` (draws laid out chain after chain, as
    :func:`chain_check_indices` reads them)."""
    c = _n_chains(d)
    return min(int(i) // max(len(d.theta) // c, 1), c - 1)


def chain_check_indices(d: Draws, per_chain: int) -> np.ndarray:
    """``per_chain`` draws of every chain of ``d`` (its draws laid out chain after chain),
    spread through each chain's second half: where the final posterior's chains went.

    Returns:
        ``(chains * per_chain,)`` indices into ``d.theta`` (fewer where a chain is shorter).
    """
    N, c = len(d.theta), _n_chains(d)
    per = N // c
    out = []
    for k in range(c):
        lo = k * per + per // 2
        out.extend((lo + spread_indices(per - per // 2, per_chain + 1)[1:]).tolist())
    return np.asarray(sorted(set(out)), dtype=int)


def spread_indices(n: int, m: int) -> np.ndarray:
    """``min(m, n)`` distinct indices spread evenly over ``0 .. n - 1`` (first and last
    included): draws taken evenly through the chains."""
    return np.linspace(0, n - 1, min(m, n)).round().astype(int)


def run_loop(p: LoopProblem, s: LoopSettings, seed: int = 0, X0: torch.Tensor | None = None,
             names: list[str] | None = None,
             on_round: Callable[[LoopResult], None] | None = None,
             kinds: list[str] | None = None) -> LoopResult:
    """Run the adaptive design (module docstring) on ``p`` with settings ``s``: the rounds
    (:func:`design_rounds`), then the full-length posterior checked by the FE in every chain
    (:func:`final_posterior`), both on ``p.y``.

    Args:
        p: the calibration as the loop sees it. s: settings (validated here).
        seed: of the start design and the acquisition's optimizer.
        X0: ``(n0, d)`` the start design (physical); default a Latin hypercube of ``s.start``.
        names: parameter names for the per-round quantiles (default ``p.box.names``).
        on_round: called after every round with the result so far (saving, plotting).
        kinds: ``(n0,)`` what each row of ``X0`` is (``"start"``, ``"fe_fit"``: runs placed
            at a known FE best fit before the first round); default all ``"start"``.

    Returns:
        :class:`LoopResult`; its ``draws`` are the final posterior's.
    """
    res = design_rounds(p, s, seed, X0, names, on_round, kinds)
    return final_posterior(p, res, s, names, on_round)


def acquire(gp: GPSurrogate, draws: Draws, box: Box, s: LoopSettings, y: torch.Tensor,
            pending: torch.Tensor, q: int, seed: int) -> tuple[torch.Tensor, float]:
    """The next ``q`` FE runs of a round (``s.criterion`` optimized by ``s.optimizer``) over
    the posterior ``draws`` of surrogate ``gp``; ``y (n_y,)`` the data, ``pending (k, d)`` the
    round's checked draws (already being run), ``seed`` the optimizer's.

    Returns:
        ``(q, d)`` parameter rows (physical, inside ``box``) and the criterion's value.
    """
    from solderpyro.design.acquisition import (
        AcquisitionPoints,
        greedy_draws,
        integrated_code_variance,
        loglik_terms,
        propose,
        qIntegratedLogLikVariance,
    )
    from solderpyro.design.model import botorch_model, observed_weights

    N = len(draws.theta)
    mi = spread_indices(N, s.mc_points)
    mc = box.to_unit(draws.theta[mi])
    sig = float(draws.sigma.median())
    cand_th = draws.theta[spread_indices(N, s.candidates)]
    off_mc = None if draws.offset is None else draws.offset[mi]
    if s.optimizer == "draws":  # closed form, the same choice as BoTorch's (tested)
        pts = AcquisitionPoints(draws.theta[mi], cand_th, pending)
        idx, val = greedy_draws(gp, s.criterion, pts, q, sig, y, off_mc)
        Xu = box.to_unit(cand_th[idx])
    else:
        model = botorch_model(gp)
        pend = box.to_unit(pending)
        if s.criterion == "loglik":
            g, M = loglik_terms(gp, draws.theta[mi], y, sig, off_mc)
            acq: Any = qIntegratedLogLikVariance(model, mc, g, M, X_pending=pend)
        else:
            acq = integrated_code_variance(model, mc, observed_weights(gp, sig), X_pending=pend)
        Xu, val = propose(acq, box.dim, q, "optimize", seed=seed)
    th = box.from_unit(Xu).clamp(torch.tensor(box.lower, dtype=torch.float64),
                                 torch.tensor(box.upper, dtype=torch.float64))
    return th, val


@dataclass
class _Rounds:
    """What the rounds carry from one to the next.

    Attributes:
        X, V, ok: every FE run so far: ``(n, d)`` physical, ``(n, n_y)`` um, ``(n,)`` bool.
        kind, round: per run, what it is (``"start"``, ``"check"``, ``"fe_fit"``,
            ``"acquired"``) and the round that made it (0: the start design).
        rounds: the round records. gp, draws: the last surrogate and its posterior.
        best_fit: the problem's ``misfit`` verdict once one was made.
    """

    X: torch.Tensor
    V: torch.Tensor
    ok: torch.Tensor
    kind: list[str]
    round: list[int]
    rounds: list[Round] = field(default_factory=list)
    gp: GPSurrogate | None = None
    draws: Draws | None = None
    best_fit: dict[str, Any] | None = None

    @property
    def misfits(self) -> bool:
        """The verdict says the model misfits the data."""
        return bool(self.best_fit and self.best_fit.get("misfits"))

    def add(self, X: torch.Tensor, V: torch.Tensor, ok: torch.Tensor, kind: str, r: int
            ) -> None:
        """Append FE runs ``X (m, d)``, ``V (m, n_y)``, ``ok (m,)`` of one kind, round ``r``."""
        self.X = torch.cat([self.X, X])
        self.V = torch.cat([self.V, V])
        self.ok = torch.cat([self.ok, ok])
        self.kind += [kind] * len(X)
        self.round += [r] * len(X)

    def result(self, reason: str, message: str, budget: int) -> LoopResult:
        assert self.gp is not None and self.draws is not None
        return LoopResult(self.gp, self.draws, self.X, self.V, self.ok, self.kind, self.round,
                          self.rounds, reason, message, self.best_fit, budget)


def _start_runs(p: LoopProblem, s: LoopSettings, seed: int, X0: torch.Tensor | None,
                kinds: list[str] | None) -> _Rounds:
    """The start design (``X0`` or a Latin hypercube of ``s.start``) and its FE runs."""
    from solderpyro.design import lhs

    X = lhs(p.box, s.start, seed) if X0 is None else X0.to(torch.float64)
    if kinds is not None and len(kinds) != len(X):
        raise ValueError(f"run_loop: kinds has {len(kinds)} entries for {len(X)} start rows")
    V, ok = p.fe(X)
    return _Rounds(X, V, ok, list(kinds) if kinds is not None else ["start"] * len(X),
                   [0] * len(X))


def _fit_and_check(p: LoopProblem, s: LoopSettings, st: _Rounds, y: torch.Tensor, r: int,
                   names: list[str], lap: StageClock) -> tuple[Round, np.ndarray, np.ndarray]:
    """Round ``r``'s surrogate, its posterior and the FE check at ``s.check`` of its draws
    (those runs join ``st``); ``y (n_y,)`` the data.

    Returns:
        the round's record (stopping rule applied), the checked draws' indices ``(k,)`` and
        their FE chi-squares ``(k,)``.
    """
    gp = st.gp = p.fit(st.X[st.ok], st.V[st.ok])
    lap("fit")
    draws = st.draws = p.sample(gp, st.draws, False)
    lap("posterior")
    chk = check_indices(p.box.to_unit(draws.theta).numpy(), s.check, s.check_ends)
    Vc, okc, fe_c2, sur_c2, code = fe_at_draws(p, gp, draws, y, chk)
    lap("check")
    code_ok, fe_ok, tol = stop_rule(code, fe_c2, sur_c2, int(y.numel()), s)
    st.add(draws.theta[chk], Vc, okc, "check", r)
    rec = Round(r, len(st.X), code, fe_c2.tolist(), sur_c2.tolist(), tol, code_ok, fe_ok,
                quantiles=_quantiles(draws.theta, names), spread_tolerance=s.fe_spread)
    return rec, chk, fe_c2


def _misfit_test(p: LoopProblem, s: LoopSettings, st: _Rounds, rec: Round, chk: np.ndarray,
                 fe_c2: np.ndarray, lap: StageClock) -> Any:
    """The problem's misfit test, once, from round ``s.misfit_check`` on while the rule does
    not hold; its verdict goes to ``st.best_fit``.

    Returns:
        the ``(m, d)`` FE parameter sets the test ran (best first) where it ran, else None.
    """
    if (rec.code_ok and rec.fe_ok or p.misfit is None or st.best_fit is not None
            or not s.misfit_check or rec.round < s.misfit_check):
        return None
    assert st.draws is not None
    far = max(rec.code_chi2, rec.fe_gap) > s.far_tol * rec.tolerance  # nan (no check): not far
    st.best_fit = p.misfit(st.draws, chk, fe_c2, far)
    runs = st.best_fit.pop("runs", None) if st.best_fit else None
    lap("misfit")
    return runs


def _localize(p: LoopProblem, s: LoopSettings, st: _Rounds, fe_runs: Any, rec: Round,
              lap: StageClock) -> bool:
    """Where the FE's own best fit fits the data: up to ``s.localize`` of the misfit test's
    runs ``fe_runs`` join the design (spaced, within the budget) and the next posterior
    starts at the best fit. Returns whether it localized."""
    if not (st.best_fit and s.localize and fe_runs is not None):
        return False
    assert st.draws is not None
    box = p.box
    room = s.runs_allowed(st.X.shape[1]) - len(st.X) - s.check  # room for the next check
    cand = torch.as_tensor(np.asarray(fe_runs, float), dtype=torch.float64)
    keep = spaced_rows(box.to_unit(cand).numpy(), box.to_unit(st.X).numpy(),
                       max(0, min(s.localize, room)))
    if len(keep):
        th_new = cand[torch.as_tensor(keep)]
        Vn, okn = p.fe(th_new)
        st.add(th_new, Vn, okn, "fe_fit", rec.round)
        rec.acquired = len(keep)
    st.draws.start = dict(st.best_fit["x"])
    log.info("design: the FE's own best fit fits the data: %d of its runs join the "
             "design and the next posterior starts there", len(keep))
    lap("localize")
    return True


def _acquire_runs(p: LoopProblem, s: LoopSettings, st: _Rounds, y: torch.Tensor,
                  chk: np.ndarray, rec: Round, seed: int, lap: StageClock) -> None:
    """Acquire up to ``s.batch`` runs (within the budget, room kept for the next check) with
    the round's checked draws ``chk`` pending, and run the FE there; ``seed``: the
    optimizer's."""
    room = s.runs_allowed(st.X.shape[1]) - len(st.X) - s.check  # room for the next check
    if room < 1:
        return
    assert st.gp is not None and st.draws is not None
    qn = min(s.batch, room)
    th_new, val = acquire(st.gp, st.draws, p.box, s, y, st.draws.theta[chk], qn, seed)
    lap("acquire")
    Vn, okn = p.fe(th_new)
    lap("fe")
    st.add(th_new, Vn, okn, "acquired", rec.round)
    rec.acquired, rec.acquisition = qn, val


def _one_round(p: LoopProblem, s: LoopSettings, st: _Rounds, y: torch.Tensor, r: int,
               seed: int, names: list[str]) -> Round:
    """Round ``r``: fit, posterior, FE check, then (unless the rule holds or the model
    misfits) localize at the FE's best fit or acquire. Returns its record (kept in ``st``)."""
    t0 = time.perf_counter()
    if int(st.ok.sum()) < p.box.dim + 2:
        raise RuntimeError(f"design: only {int(st.ok.sum())} of {len(st.X)} FE runs converged")
    lap = StageClock()
    rec, chk, fe_c2 = _fit_and_check(p, s, st, y, r, names, lap)
    fe_runs = _misfit_test(p, s, st, rec, chk, fe_c2, lap)
    go_on = not (rec.code_ok and rec.fe_ok) and not st.misfits
    if go_on and not _localize(p, s, st, fe_runs, rec, lap):
        _acquire_runs(p, s, st, y, chk, rec, seed + r, lap)
    rec.seconds = time.perf_counter() - t0
    rec.timing = lap.seconds
    st.rounds.append(rec)
    log.info(rec.line())
    return rec


def _outcome(st: _Rounds, s: LoopSettings, n: int) -> tuple[str, str]:
    """``(reason, message)`` of the rounds' stop; ``n`` observed values."""
    last, r, runs = st.rounds[-1], len(st.rounds), len(st.X)
    tol = last.tolerance
    if last.code_ok and last.fe_ok:
        return "converged", (
            f"the design converged after {r} rounds and {runs} FE runs: the code chi2 at the "
            f"posterior draws ({last.code_chi2:.3g}) and the FE-vs-surrogate chi2 at "
            f"{len(last.fe_chi2)} of them are within sqrt(2n) = {tol:.3g}, and the "
            f"FE-vs-surrogate gap varies by {last.fe_spread:.2g} <= {s.fe_spread:g} "
            "across them")
    if st.misfits:
        assert st.best_fit is not None
        return "misfit", (
            f"the design stopped after {r} rounds and {runs} FE runs: the FE's own best fit "
            f"misfits the data (chi2 {st.best_fit['chi2']:.0f} on {n} values, RMS "
            f"{st.best_fit['rms_over_sigma']:.2f} noise sd): the model misses something the "
            "data show, and more FE runs for its surrogate cannot fix that (solderpyro "
            "diagnose names candidate effects)")
    why = [] if last.code_ok else [f"code chi2 {last.code_chi2:.3g}"]
    if not last.fe_ok:
        why.append("the FE disagrees with the surrogate at posterior draws (max |d chi2| "
                   f"{last.fe_gap:.3g} against sqrt(2n) = {tol:.3g}, varying by "
                   f"{last.fe_spread:.2g} against {s.fe_spread:g})")
    return "budget", (
        f"the FE budget ran out ({runs} of {s.runs_allowed(st.X.shape[1])} runs, {r} rounds) "
        f"before the surrogate was confirmed: {'; '.join(why)}" + (
            "" if last.code_ok else f" (code chi2 tolerance sqrt(2n) = {tol:.3g})"))


def design_rounds(p: LoopProblem, s: LoopSettings, seed: int = 0,
                  X0: torch.Tensor | None = None, names: list[str] | None = None,
                  on_round: Callable[[LoopResult], None] | None = None,
                  kinds: list[str] | None = None) -> LoopResult:
    """The rounds of the adaptive design (arguments as :func:`run_loop`) until the stopping
    rule holds, the FE's own best fit misfits, or the budget would be exceeded.

    Returns:
        :class:`LoopResult` with ``reason`` and ``message`` set; its ``draws`` are the last
        round's posterior (``draws.checked``: that round's FE check), not yet the final one
        (:func:`final_posterior`). ``on_round`` is not called with it.
    """
    s.validate(p.box.dim)
    budget = s.runs_allowed(p.box.dim)
    y = p.y.to(torch.float64)
    names = names or list(p.box.names)
    st = _start_runs(p, s, seed, X0, kinds)
    r = 0
    while True:
        r += 1
        rec = _one_round(p, s, st, y, r, seed, names)
        if rec.code_ok and rec.fe_ok or st.misfits or len(st.X) + s.check > budget:
            break  # converged, misfits, or the next round's check would exceed the budget
        if on_round is not None:
            on_round(st.result("running", "", budget))
    return st.result(*_outcome(st, s, int(y.numel())), budget)


def final_posterior(p: LoopProblem, res: LoopResult, s: LoopSettings,
                    names: list[str] | None = None,
                    on_round: Callable[[LoopResult], None] | None = None) -> LoopResult:
    """The full-length posterior after :func:`design_rounds` ``res``, on ``p.y`` (the data
    the caller passes: e.g. corrected for the FE's discretization error), checked by the FE
    at draws of every chain; where the FE disagrees with the surrogate there, those runs join
    the design, the surrogate is refitted and the posterior drawn again (within the budget).
    After a ``"misfit"`` stop the last round's draws are kept.

    Returns:
        the :class:`LoopResult` with the final draws, every FE run and round record.
    """
    budget = s.runs_allowed(p.box.dim)
    gp, draws, best_fit = res.gp, res.draws, res.best_fit
    X, V, ok = res.X, res.Y, res.ok
    kind, rnd_of, rounds = list(res.kind), list(res.round), list(res.rounds)
    reason, msg, r = res.reason, res.message, len(res.rounds)
    names = names or list(p.box.names)
    y = p.y.to(torch.float64)
    n = int(y.numel())
    if reason == "misfit":
        # the reported result is the FE's own best fit; the surrogate posterior only seeds the
        # FE check and the diagnosis, and the last round's draws are of this same surrogate
        # (no run joined it since): not drawn again at full length (~20 s of the loop's base
        # run, a posterior in islands with R-hat 2.8 whatever its length)
        log.info("design: the surrogate posterior is the last round's (%d draws), not drawn "
                 "again: the model misfits, the FE's best fit is the result", len(draws.theta))
        final = draws
    else:
        final = p.sample(gp, draws, True)
        while True:  # the FE confirms the final posterior in every chain (below)
            t0 = time.perf_counter()
            chk = chain_check_indices(final, FINAL_CHECK_PER_CHAIN)
            if len(X) + len(chk) > budget:
                break
            th_chk = final.theta[chk]
            Vc, okc, fe_c2, sur_c2, code = fe_at_draws(p, gp, final, y, chk, code_draws=400)
            lap_s = time.perf_counter() - t0
            tol = math.sqrt(2 * n)
            gap = np.abs(fe_c2 - np.asarray(sur_c2, float))
            # islands, not the rounds' spread rule: a gap within fe_tol sqrt(2n) at every
            # checked draw (eight draws of four chains vary by more than fe_spread where the
            # surrogate is right; an island's gap is thousands)
            fe_ok = bool(np.all(np.isfinite(gap)) and np.max(gap) <= s.fe_tol * tol)
            code_ok = code <= s.code_tol * tol
            X, V, ok = torch.cat([X, th_chk]), torch.cat([V, Vc]), torch.cat([ok, okc])
            kind += ["check"] * len(chk)
            r += 1
            rnd_of += [r] * len(chk)
            rec = Round(r, len(X), code, fe_c2.tolist(), sur_c2.tolist(), tol, code_ok, fe_ok,
                        quantiles=_quantiles(final.theta, names), spread_tolerance=s.fe_spread)
            rec.seconds = time.perf_counter() - t0
            rec.timing = {"check": lap_s}
            rounds.append(rec)
            log.info("design: the final posterior checked by the FE in every chain: %s",
                     rec.line())
            if fe_ok:
                break
            bad = sorted({_chain_of(final, i)
                          for i, g in zip(chk, gap, strict=True) if not g <= s.fe_tol * tol})
            if len(X) + len(chk) > budget:
                reason, msg = "budget", (
                    f"the FE budget ran out ({len(X)} of {budget} runs) with the final "
                    f"posterior's chain(s) {[c + 1 for c in bad]} where the FE disagrees with "
                    f"the surrogate (max |d chi2| {rec.fe_gap:.3g} against sqrt(2n) = "
                    f"{tol:.3g}): the surrogate fits there, the FE does not")
                break
            log.warning("design: the final posterior's chain(s) %s reach where the FE "
                        "disagrees with the surrogate (max |d chi2| %.3g against %.3g): those "
                        "runs join the design, the surrogate is refitted and the final "
                        "posterior drawn again", [c + 1 for c in bad], rec.fe_gap, tol)
            gp = p.fit(X[ok], V[ok])
            final = p.sample(gp, final, True)
            msg += (f"; the final posterior's chain(s) {[c + 1 for c in bad]} first reached "
                    "where only the surrogate fitted: the FE's runs there joined the design "
                    f"({len(X)} FE runs)")
    res = LoopResult(gp, final, X, V, ok, kind, rnd_of, rounds, reason, msg, best_fit, budget)
    if on_round is not None:
        on_round(res)
    return res
