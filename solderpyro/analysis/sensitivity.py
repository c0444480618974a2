"""Global sensitivity of the observed outputs to the nine Anand constants.

The seed chose s0, Q/R, xi and m "after a sensitivity study". :func:`run_sensitivity` ranks all
nine constants over a prior box by two independent routes:

- **DGSM** (derivative-based global sensitivity measures, Sobol' & Kucherenko 2009) through the
  FE itself: at ``N`` Latin-hypercube points the Jacobian of the outputs with respect to the
  unit-cube coordinates u comes from autograd through the solver; ``nu_i = E[(dy/du_i)^2]``,
  and for inputs uniform on [0, 1] the total Sobol index obeys ``S_T,i <= nu_i / (pi^2 Var y)``.
- **Sobol main and total indices** through a GP surrogate fitted to an LHS of FE runs (kept in
  the crash-safe :class:`~solderpyro.compute.runstore.RunStore`): Saltelli (2010) main-effect and
  Jansen (1999) total-effect estimators on the GP mean, scrambled-Sobol base samples,
  bootstrap intervals over the sample rows.

Indices of several outputs (V_A, V_B at each time) are aggregated variance-weighted:
``S_agg,i = sum_k V_k S_i,k / sum_k V_k`` (Gamboa et al. 2014); the DGSM bound aggregates the
same way, so the aggregated bound is a bound on the aggregated total index.

The input distribution is uniform in the unit-cube coordinates of the box, i.e. log-uniform
for the constants flagged ``log_scale`` (A and h0 by default).
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.stats import qmc

from solderpyro.params import ANAND_NAMES, LIU2008, SEED_BOX, ParameterSpace, check_anand_values

log = logging.getLogger("solderpyro")

#: The four constants the seed calibrated "after a sensitivity study" (seed §4).
SEED_CHOICE: tuple[str, ...] = ("s0", "QR", "xi", "m")
#: The nine-constant box: (lower, upper, log_scale). s0, QR, xi, m: the specimen's prior box
#: (docs/configuration.md, "The reference case"). The other five: around Liu 2008
#: (docs/sensitivity.md): A x/÷ 10 and h0 x/÷ 3 (log scale), s_hat x/÷ 2, n from Wang 2001's
#: 0.0231 to 0.12, a in [1, 2].
NINE_BOX: dict[str, tuple[float, float, bool]] = {
    **{k: (lo, hi, False) for k, (lo, hi) in SEED_BOX.items()},
    "A": (LIU2008["A"] / 10.0, LIU2008["A"] * 10.0, True),
    "h0": (LIU2008["h0"] / 3.0, LIU2008["h0"] * 3.0, True),
    "s_hat": (LIU2008["s_hat"] / 2.0, LIU2008["s_hat"] * 2.0, False),
    "n": (0.02, 0.12, False),
    "a": (1.0, 2.0, False),
}


def sensitivity_box(calibrated: ParameterSpace | None = None,
                    bounds: Mapping[str, tuple[float, float]] | None = None,
                    defaults: Mapping[str, float] | None = None) -> ParameterSpace:
    """The box over all nine Anand constants (ANAND_NAMES order).

    Args:
        calibrated: a configured space (e.g. ``setup.space``); its names keep their bounds and
            scaling (the config's ``materials.calibrate`` box).
        bounds: name -> (lower, upper) overrides in physical units (MPa, K, 1/s); the
            scaling of :data:`NINE_BOX` is kept.
        defaults: the nine constants for :meth:`ParameterSpace.full` (default Liu 2008).

    Returns:
        A :class:`ParameterSpace` with ``n_theta = 9``.
    """
    spec = dict(NINE_BOX)
    if calibrated is not None:
        for j, nm in enumerate(calibrated.names):
            spec[nm] = (calibrated.lower[j], calibrated.upper[j], calibrated.log_scale[j])
    for nm, (lo, hi) in (bounds or {}).items():
        if nm not in spec:
            raise ValueError(f"unknown Anand parameter {nm!r} in the box; valid: "
                             f"{', '.join(ANAND_NAMES)}")
        check_anand_values({nm: lo})
        check_anand_values({nm: hi})
        spec[nm] = (float(lo), float(hi), spec[nm][2])
    return ParameterSpace(ANAND_NAMES, tuple(spec[k][0] for k in ANAND_NAMES),
                          tuple(spec[k][1] for k in ANAND_NAMES),
                          log_scale=tuple(spec[k][2] for k in ANAND_NAMES),
                          defaults=dict(defaults or LIU2008))


# ------------------------------------------------------------------------- estimators
@dataclass(frozen=True)
class SobolResult:
    """Sobol indices of ``d`` inputs for ``n_y`` outputs.

    Attributes:
        S1, ST: ``(d, n_y)`` main and total indices per output.
        var: ``(n_y,)`` output variances (units of y squared).
        S1_agg, ST_agg: ``(d,)`` variance-weighted aggregates over outputs.
        S1_lo, S1_hi, ST_lo, ST_hi: ``(d,)`` bootstrap percentile interval of the aggregates.
        S1_se, ST_se: ``(d,)`` bootstrap standard errors of the aggregates.
        n: base sample size; the function was evaluated ``(d + 2) n`` times.
    """

    S1: torch.Tensor
    ST: torch.Tensor
    var: torch.Tensor
    S1_agg: torch.Tensor
    ST_agg: torch.Tensor
    S1_lo: torch.Tensor
    S1_hi: torch.Tensor
    ST_lo: torch.Tensor
    ST_hi: torch.Tensor
    S1_se: torch.Tensor
    ST_se: torch.Tensor
    n: int


def _saltelli(fA: torch.Tensor, fB: torch.Tensor, fAB: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Partial variances from ``fA, fB (N, n_y)`` and ``fAB (d, N, n_y)``.

    Returns ``V_i (d, n_y)`` (Saltelli 2010), ``V_Ti (d, n_y)`` (Jansen 1999), ``Var (n_y,)``.
    """
    var = torch.cat([fA, fB]).var(0)
    v1 = (fB * (fAB - fA)).mean(1)
    vt = 0.5 * (fA - fAB).square().mean(1)
    return v1, vt, var


def sobol_indices(f: Callable[[torch.Tensor], torch.Tensor], d: int, n: int = 8192,
                  seed: int = 0, n_boot: int = 200, level: float = 0.95,
                  chunk: int = 8192) -> SobolResult:
    """Sobol main and total indices of ``f`` on the unit cube ``[0, 1]^d`` (uniform inputs).

    Args:
        f: ``(M, d) -> (M, n_y)`` or ``(M,)``; evaluated in chunks of ``chunk`` rows, no grad.
        d: number of inputs. n: base sample size, a power of two (scrambled Sobol' points).
        seed: scrambling and bootstrap seed. n_boot: bootstrap resamples of the ``n`` rows.
        level: coverage of the percentile intervals.

    Returns:
        :class:`SobolResult`.
    """
    if n < 16 or n & (n - 1):
        raise ValueError(f"Sobol base sample size must be a power of two >= 16, got {n}")
    if n_boot < 10:
        raise ValueError(f"n_boot must be >= 10, got {n_boot}")
    m = int(math.log2(n))
    ab = torch.as_tensor(qmc.Sobol(2 * d, scramble=True, seed=seed).random_base2(m))
    A, B = ab[:, :d], ab[:, d:]  # (n, d) each
    ABi = A.expand(d, n, d).clone()
    idx = torch.arange(d)
    ABi[idx, :, idx] = B.T  # row block i: A with column i taken from B
    x = torch.cat([A, B, ABi.reshape(d * n, d)])  # ((d + 2) n, d)
    with torch.no_grad():
        y = torch.cat([_as2d(f(x[i:i + chunk])) for i in range(0, x.shape[0], chunk)])
    y = y.to(torch.float64)
    fA, fB, fAB = y[:n], y[n:2 * n], y[2 * n:].reshape(d, n, -1)
    v1, vt, var = _saltelli(fA, fB, fAB)
    g = torch.Generator().manual_seed(seed)
    boot = []
    for _ in range(n_boot):
        r = torch.randint(n, (n,), generator=g)
        b1, bt, bv = _saltelli(fA[r], fB[r], fAB[:, r])
        boot.append(torch.stack([b1.sum(-1), bt.sum(-1)]) / bv.sum())  # (2, d)
    bs = torch.stack(boot)  # (n_boot, 2, d)
    q = torch.tensor([(1 - level) / 2, (1 + level) / 2], dtype=bs.dtype)
    lo, hi = torch.quantile(bs, q, dim=0)  # (2, d) each
    se = bs.std(0)
    return SobolResult(v1 / var, vt / var, var, v1.sum(-1) / var.sum(), vt.sum(-1) / var.sum(),
                       lo[0], hi[0], lo[1], hi[1], se[0], se[1], n)


def _as2d(y: torch.Tensor) -> torch.Tensor:
    return y[:, None] if y.ndim == 1 else y


def jacobian_rows(f: Callable[[torch.Tensor], torch.Tensor], u: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-row Jacobian of a batched function whose rows are independent.

    Because row i of ``f(u)`` depends on row i of ``u`` only, ``d sum_i y[i, k] / d u = J[:, k]``:
    one reverse pass per output column (graph retained between them).

    Args:
        f: ``(N, d) -> (N, n_y)`` (or ``(N,)``), differentiable in its input.
        u: ``(N, d)`` points.

    Returns:
        ``y (N, n_y)`` detached and ``J (N, n_y, d)``, ``J[i, k, j] = dy[i, k] / du[i, j]``.
    """
    u = u.detach().clone().requires_grad_(True)
    y = _as2d(f(u))
    if not y.requires_grad:
        raise RuntimeError("the function's output does not depend on its input (no graph)")
    n_y = y.shape[1]
    J = torch.zeros(u.shape[0], n_y, u.shape[1], dtype=u.dtype)
    for k in range(n_y):
        (g,) = torch.autograd.grad(y[:, k].sum(), u, retain_graph=k < n_y - 1,
                                   allow_unused=True)
        if g is not None:
            J[:, k] = g.detach().to(J)
    return y.detach(), J


@dataclass(frozen=True)
class DgsmResult:
    """Derivative-based measures of ``d`` inputs on the unit cube for ``n_y`` outputs.

    Attributes:
        nu: ``(d, n_y)`` ``E[(dy_k/du_i)^2]`` (units of y squared).
        var: ``(n_y,)`` output variances used for normalization.
        bound: ``(d, n_y)`` ``nu / (pi^2 var)``: upper bound of the total Sobol index.
        bound_agg: ``(d,)`` ``sum_k nu_ik / (pi^2 sum_k var_k)``, bound of the aggregated S_T.
        lo, hi: ``(d,)`` bootstrap percentile interval of ``bound_agg`` (over the points).
        n_points: points the expectation was estimated from.
    """

    nu: torch.Tensor
    var: torch.Tensor
    bound: torch.Tensor
    bound_agg: torch.Tensor
    lo: torch.Tensor
    hi: torch.Tensor
    n_points: int


def dgsm(J: torch.Tensor, var: torch.Tensor, n_boot: int = 200, level: float = 0.95,
         seed: int = 0) -> DgsmResult:
    """DGSM from per-point Jacobians (Sobol' & Kucherenko 2009).

    Args:
        J: ``(N, n_y, d)`` derivatives with respect to the unit-cube coordinates at ``N``
            points uniform on the cube (non-finite rows are dropped).
        var: ``(n_y,)`` variance of each output over the cube (> 0).
        n_boot, level, seed: bootstrap over the points for the interval of ``bound_agg``.

    Returns:
        :class:`DgsmResult`.
    """
    J = J[torch.isfinite(J).all(-1).all(-1)]
    if J.shape[0] < 2:
        raise ValueError(f"DGSM needs >= 2 points with finite derivatives, got {J.shape[0]}")
    if not bool((var > 0).all()):
        raise ValueError(f"output variances must be > 0, got {var.tolist()}")
    sq = J.square().transpose(1, 2)  # (N, d, n_y)
    nu = sq.mean(0)
    den = math.pi**2 * var.sum()
    g = torch.Generator().manual_seed(seed)
    boot = torch.stack([sq[torch.randint(sq.shape[0], (sq.shape[0],), generator=g)]
                        .mean(0).sum(-1) / den for _ in range(n_boot)])  # (n_boot, d)
    q = torch.tensor([(1 - level) / 2, (1 + level) / 2], dtype=boot.dtype)
    lo, hi = torch.quantile(boot, q, dim=0)
    return DgsmResult(nu, var, nu / (math.pi**2 * var), nu.sum(-1) / den, lo, hi, J.shape[0])


# ------------------------------------------------------------------------- the FE study
@dataclass
class SensitivityResult:
    """What :func:`run_sensitivity` computed (files are in ``out``).

    Attributes:
        box: the nine-constant box. outputs: ``n_y`` labels ``V_<point>@<t>s``.
        dgsm: FE derivative measures. sobol: GP-based Sobol indices.
        rows: one dict per constant (the columns of sensitivity.csv).
        verdict: top four by total index vs the seed's choice (see :func:`verdict`).
        loo: the surrogate's leave-one-out RMSE (fraction of spread) and 95 % coverage.
        timings: seconds per stage. n_runs_ok: converged DOE runs used by the GP.
        surrogate_problems: reasons not to trust the GP (LOO check).
        refits: ``(g, d)`` aggregated S_T of GPs refitted without each group of runs, or None.
    """

    out: Path
    box: ParameterSpace
    outputs: list[str]
    dgsm: DgsmResult
    sobol: SobolResult
    rows: list[dict]
    verdict: dict
    loo: dict
    timings: dict = field(default_factory=dict)
    n_runs_ok: int = 0
    surrogate_problems: list[str] = field(default_factory=list)
    refits: torch.Tensor | None = None

    @property
    def st_se_surrogate(self) -> torch.Tensor | None:
        """``(d,)`` jackknife standard error of the aggregated S_T over GP refits, or None."""
        return None if self.refits is None else _jackknife_se(self.refits)


def verdict(names: Sequence[str], st: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor,
            chosen: Sequence[str] = SEED_CHOICE, refits: torch.Tensor | None = None) -> dict:
    """Compare the ``len(chosen)`` largest total indices with a chosen set.

    Args:
        names: ``d`` input names; st, lo, hi: ``(d,)`` total indices and their interval.
        chosen: the set to reproduce (default the seed's s0, QR, xi, m).
        refits: optional ``(g, d)`` total indices of ``g`` delete-a-group GP refits (see
            :func:`jackknife_st`): the surrogate's share of the uncertainty of the k-th/(k+1)-th
            gap.

    Returns:
        dict: ``top`` (names by decreasing ST), ``reproduced`` (bool), ``missing`` (chosen
        but not on top), ``extra`` (on top but not chosen), ``separated`` (the k-th interval
        lies above the (k+1)-th), ``gap`` and ``gap_se_surrogate`` (jackknife standard error,
        NaN without refits), ``text`` (one or two sentences).
    """
    k = len(chosen)
    order = torch.argsort(st, descending=True).tolist()
    top = [names[i] for i in order[:k]]
    missing = [c for c in chosen if c not in top]
    extra = [t for t in top if t not in chosen]
    last = len(order) <= k
    sep = last or bool(lo[order[k - 1]] > hi[order[k]])
    gap = math.nan if last else float(st[order[k - 1]] - st[order[k]])
    se = math.nan
    if refits is not None and not last and refits.shape[0] > 1:
        se = float(_jackknife_se(refits[:, order[k - 1]] - refits[:, order[k]]))
    text = (f"The top {k} by total index are {', '.join(top)}; the seed chose "
            f"{', '.join(chosen)} -> " + ("reproduced" if not missing else
                                          f"not reproduced (seed's {', '.join(missing)} vs "
                                          f"{', '.join(extra)})") + ".")
    if not last:
        text += (f" The gap between the {k}th ({names[order[k - 1]]}) and {k + 1}th "
                 f"({names[order[k]]}) is {gap:.3f}: " + ("resolved" if sep else "not resolved")
                 + " by the Sobol-sampling intervals")
        text += ("." if se != se else f"; surrogate jackknife SE {se:.3f} -> "
                 + ("resolved." if gap > 2 * se else "not resolved."))
    return {"top": top, "reproduced": not missing, "missing": missing, "extra": extra,
            "separated": sep, "gap": gap, "gap_se_surrogate": se, "text": text}


def _jackknife_se(v: torch.Tensor) -> torch.Tensor:
    """Delete-a-group jackknife standard error from ``(g, ...)`` leave-group-out estimates."""
    g = v.shape[0]
    return ((g - 1) / g * (v - v.mean(0)).square().sum(0)).sqrt()


def _ranks(v: torch.Tensor) -> list[int]:
    """1 = largest."""
    order = torch.argsort(v, descending=True).tolist()
    r = [0] * len(order)
    for pos, i in enumerate(order):
        r[i] = pos + 1
    return r


def table_rows(names: Sequence[str], dg: DgsmResult, sb: SobolResult) -> list[dict]:
    """Rows of sensitivity.csv: parameter, dgsm, dgsm_rank, S1, S1_lo, S1_hi, ST, ST_lo,
    ST_hi, rank (ranks: 1 = most influential; rank by ST)."""
    rd, rs = _ranks(dg.bound_agg), _ranks(sb.ST_agg)
    return [{"parameter": nm, "dgsm": float(dg.bound_agg[i]), "dgsm_rank": rd[i],
             "S1": float(sb.S1_agg[i]), "S1_lo": float(sb.S1_lo[i]), "S1_hi": float(sb.S1_hi[i]),
             "ST": float(sb.ST_agg[i]), "ST_lo": float(sb.ST_lo[i]), "ST_hi": float(sb.ST_hi[i]),
             "rank": rs[i]} for i, nm in enumerate(names)]


def fe_jacobian(model: Any, box: ParameterSpace, u: torch.Tensor, batch: int = 16,
                progress: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """Outputs and their Jacobian with respect to the unit-cube coordinates, through the FE.

    Args:
        model: a :class:`~solderpyro.specimen.SpecimenModel` over ``box``.
        box: the parameter box (``n_theta = d``). u: ``(N, d)`` points in [0, 1].
        batch: members per FE solve (memory grows with it: ~0.5 GB per member on the default
            mesh, the autograd graph of the whole cycle).
        progress: tqdm over the time steps of each solve.

    Returns:
        ``y (N, n_y)`` in um (NaN rows for failed members) and ``J (N, n_y, d)`` in um per unit
        of u (non-finite rows where the member failed); ``n_y = n_time * n_out``, time-major.
    """
    ys, Js = [], []
    for i in range(0, u.shape[0], batch):
        def f(x: torch.Tensor) -> torch.Tensor:
            V = model.run(box.from_unit(x), progress=progress).V  # (b, n_time, n_out)
            return V.reshape(x.shape[0], -1)

        y, J = jacobian_rows(f, u[i:i + batch])
        J[~torch.isfinite(y).all(-1)] = float("nan")
        ys.append(y.cpu().to(torch.float64))
        Js.append(J)
    return torch.cat(ys), torch.cat(Js)


def gp_sobol(box: ParameterSpace, theta: torch.Tensor, y: torch.Tensor,
             surrogate: Mapping[str, Any] | None = None, n: int = 8192, seed: int = 0,
             n_boot: int = 200) -> tuple[Any, SobolResult]:
    """Fit a batched GP to runs and compute Sobol indices of its mean over the box.

    Args:
        box: the inputs (unit-cube coordinates: log for log-scale names).
        theta: ``(n_run, d)`` physical inputs; y: ``(n_run, n_y)`` outputs (um).
        surrogate: GPSurrogate options (kernel, ard, mean). n, seed, n_boot: see
            :func:`sobol_indices`.

    Returns:
        the fitted :class:`~solderpyro.surrogate.GPSurrogate` and the :class:`SobolResult`.
    """
    from solderpyro.surrogate import GPSurrogate

    # one GP per output: the Sobol indices are per output (the config's "output" layout, for
    # the calibration's code covariance, does not apply here)
    # (the flow-stress input map is a calibration setting; the nine-constant study keeps the box)
    opts = {k: v for k, v in (surrogate or {}).items() if k in ("kernel", "ard", "mean")}
    gp = GPSurrogate(box, output="batched", **opts).fit(theta, y)
    sb = sobol_indices(lambda x: gp.predict(box.from_unit(x))[0], box.dim, n, seed, n_boot)
    return gp, sb


def jackknife_st(box: ParameterSpace, theta: torch.Tensor, y: torch.Tensor,
                 surrogate: Mapping[str, Any] | None = None, groups: int = 5, n: int = 2048,
                 seed: int = 0) -> torch.Tensor:
    """Aggregated total indices of GPs refitted without each of ``groups`` groups of runs.

    The same Sobol sample serves every refit, so the spread is the surrogate's (which runs it
    saw), not the Monte Carlo error; :func:`_jackknife_se` turns it into a standard error.

    Args:
        box, theta ``(n_run, d)``, y ``(n_run, n_y)``, surrogate: as :func:`gp_sobol`.
        groups: number of groups (runs assigned at random with ``seed``); n: Sobol sample.

    Returns:
        ``(groups, d)`` aggregated S_T of each refit.
    """
    g = torch.Generator().manual_seed(seed)
    grp = torch.randperm(theta.shape[0], generator=g) % groups  # (n_run,)
    out = []
    for j in range(groups):
        keep = grp != j
        out.append(gp_sobol(box, theta[keep], y[keep], surrogate, n, seed, 10)[1].ST_agg)
    return torch.stack(out)


@dataclass(frozen=True)
class SensitivitySettings:
    """The knobs of :func:`run_sensitivity` (the CLI's defaults).

    Attributes:
        n_runs: LHS FE runs for the GP (>= 10; stored in ``store_root``, reused on rerun).
        grad_points: LHS points of the DGSM (>= 2).
        grad_batch: members per autograd FE solve of the DGSM (>= 1).
        times: output times, s (None: ``setup.times``).
        store_root: directory of the :class:`~solderpyro.compute.runstore.RunStore`.
        seed: LHS seed of the DOE (the DGSM design uses ``seed + 1``), Sobol scrambling and
            bootstrap seed.
        n_sobol: Sobol base sample (a power of two >= 16).
        n_boot: bootstrap resamples (>= 10).
        bounds: name -> (lower, upper) overrides of the box in physical units (see
            :func:`sensitivity_box`).
        batch_size: FE runs per DOE solve.
        refits: GP refits without 1/refits of the runs each, for the surrogate's standard
            error of S_T (0 or 1: none; at most ``n_runs``).
        progress: tqdm progress bars.
    """

    n_runs: int = 100
    grad_points: int = 32
    grad_batch: int = 16
    times: Sequence[float] | None = None
    store_root: str | Path = "runs/store"
    seed: int = 0
    n_sobol: int = 8192
    n_boot: int = 200
    bounds: Mapping[str, tuple[float, float]] | None = None
    batch_size: int = 64
    refits: int = 5
    progress: bool = True


def _check_options(st: SensitivitySettings) -> None:
    """Raise ``ValueError`` naming the first bad option (before any FE work)."""
    if st.n_runs < 10:
        raise ValueError(f"--runs must be at least 10 (a 9-input GP), got {st.n_runs}")
    if st.grad_points < 2:
        raise ValueError(f"--grad-points must be at least 2, got {st.grad_points}")
    if st.grad_batch < 1:
        raise ValueError(f"--grad-batch must be at least 1, got {st.grad_batch}")
    if st.n_sobol < 16 or st.n_sobol & (st.n_sobol - 1):
        raise ValueError(f"--sobol-samples must be a power of two >= 16, got {st.n_sobol}")
    if st.n_boot < 10:
        raise ValueError(f"--bootstrap must be at least 10, got {st.n_boot}")
    if st.refits < 0 or st.refits > st.n_runs:
        raise ValueError(f"--refits must be in [0, --runs], got {st.refits}")


def run_sensitivity(setup: Any, out: str | Path,
                    settings: SensitivitySettings = SensitivitySettings(),
                    command: str = "") -> SensitivityResult:
    """Rank the nine Anand constants by their influence on V_A, V_B at ``settings.times``.

    Args:
        setup: a :class:`~solderpyro.config.compose.Setup` (problem, calibrated box, defaults,
            dtype, device, surrogate settings).
        out: output directory (created): sensitivity.csv / .json / .png / .md.
        settings: run sizes, seed, box overrides and store (:class:`SensitivitySettings`).
        command: the command line, for the report.

    Returns:
        :class:`SensitivityResult`.
    """
    from solderpyro.compute.runstore import RunStore
    from solderpyro.design import lhs
    from solderpyro.specimen import SpecimenModel, StoreUse

    st = settings
    _check_options(st)
    times = tuple(sorted(float(t) for t in (st.times or setup.times)))
    end = setup.problem.cycle.end
    if not times or not all(0.0 < t <= end for t in times):
        raise ValueError(f"--times must lie in (0, {end:g}] s, got {times}")
    box = sensitivity_box(setup.space, st.bounds, setup.anand)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    model = SpecimenModel(setup.problem, box, times, dtype=setup.dtype, device=setup.device)
    labels = [f"V_{p}@{t:g}s" for t in times for p in model.output_names]
    tm: dict[str, float] = {}
    t0 = time.perf_counter()
    store = RunStore(st.store_root)
    model.use_store(StoreUse(store, st.batch_size, st.progress))
    h = model.cfg_hash
    assert h is not None
    theta = lhs(box, st.n_runs, st.seed)  # (n_runs, 9)
    log.info("sensitivity DOE: %d LHS runs over the nine-constant box (store %s)", st.n_runs,
             store.config_dir(h))
    doe = model.runs(theta)
    tm["doe_s"] = time.perf_counter() - t0
    ok = doe.ok
    if int(ok.sum()) < 10:
        raise RuntimeError(f"only {int(ok.sum())} of {st.n_runs} FE runs converged")
    y = doe.V.reshape(st.n_runs, -1)[ok]  # (n_ok, n_y), time-major as labels
    var = y.var(0)

    t0 = time.perf_counter()
    u = box.to_unit(lhs(box, st.grad_points, st.seed + 1))  # (N, 9)
    log.info("DGSM: %d points, autograd through the FE in solves of %d", st.grad_points,
             st.grad_batch)
    _, J = fe_jacobian(model, box, u, st.grad_batch, st.progress)
    dg = dgsm(J, var, st.n_boot, seed=st.seed)
    tm["dgsm_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    gp, sb = gp_sobol(box, theta[ok], y, setup.surrogate, st.n_sobol, st.seed, st.n_boot)
    loo = gp.loo()
    problems = gp.check(loo)
    tm["gp_sobol_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    jk = None
    if st.refits > 1:
        log.info("surrogate error: %d GP refits, each without 1/%d of the runs", st.refits,
                 st.refits)
        jk = jackknife_st(box, theta[ok], y, setup.surrogate, st.refits, min(st.n_sobol, 2048),
                          st.seed)
    tm["refits_s"] = time.perf_counter() - t0
    rows = table_rows(box.names, dg, sb)
    res = SensitivityResult(out, box, labels, dg, sb, rows,
                            verdict(box.names, sb.ST_agg, sb.ST_lo, sb.ST_hi, refits=jk),
                            {"rmse_rel": loo.rmse_rel, "coverage95": loo.coverage95},
                            tm, int(ok.sum()), problems, jk)
    write_outputs(res, command)
    return res


_COLS = ("parameter", "dgsm", "dgsm_rank", "S1", "S1_lo", "S1_hi", "ST", "ST_lo", "ST_hi",
         "rank")


def write_outputs(res: SensitivityResult, command: str = "") -> dict[str, Path]:
    """Write sensitivity.csv, sensitivity.json, sensitivity.png and sensitivity.md.

    Returns:
        name -> path of each file written.
    """
    import csv

    out = res.out
    paths = {k: out / f"sensitivity.{k}" for k in ("csv", "json", "png", "md")}
    with open(paths["csv"], "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=_COLS)
        w.writeheader()
        w.writerows(res.rows)
    paths["json"].write_text(json.dumps(_json(res, command), indent=1))
    fig = plot_sensitivity(res)
    fig.savefig(paths["png"], dpi=130)
    paths["md"].write_text(_markdown(res, command))
    for k, p in paths.items():
        log.info("sensitivity %s: %s", k, p)
    return paths


def _json(res: SensitivityResult, command: str) -> dict:
    b, dg, sb = res.box, res.dgsm, res.sobol
    se = res.st_se_surrogate
    per = {nm: {"S1": sb.S1[i].tolist(), "ST": sb.ST[i].tolist(), "nu": dg.nu[i].tolist(),
                "ST_se_surrogate": None if se is None else float(se[i]),
                "ST_refits": None if res.refits is None else res.refits[:, i].tolist(),
                "dgsm_bound": dg.bound[i].tolist(), "dgsm_lo": float(dg.lo[i]),
                "dgsm_hi": float(dg.hi[i]), "S1_se": float(sb.S1_se[i]),
                "ST_se": float(sb.ST_se[i])} for i, nm in enumerate(b.names)}
    return {"command": command, "outputs": res.outputs, "rows": res.rows, "per_parameter": per,
            "output_variance_um2": {"fe_doe": dg.var.tolist(), "gp_sobol": sb.var.tolist()},
            "box": {nm: {"lower": b.lower[i], "upper": b.upper[i], "log_scale": b.log_scale[i],
                         "unit": b.units[i]} for i, nm in enumerate(b.names)},
            "verdict": res.verdict, "surrogate_loo": res.loo,
            "surrogate_problems": res.surrogate_problems, "n_runs_ok": res.n_runs_ok,
            "dgsm_points": dg.n_points, "sobol_base_samples": sb.n, "timings_s": res.timings,
            "bound_violations": bound_violations(res)}


def bound_violations(res: SensitivityResult) -> list[str]:
    """Constants whose GP total index lies above the FE's DGSM bound beyond both intervals
    (ST_lo > dgsm_hi): the surrogate or the DGSM sample is wrong there."""
    dg, sb = res.dgsm, res.sobol
    return [nm for i, nm in enumerate(res.box.names) if float(sb.ST_lo[i]) > float(dg.hi[i])]


def _markdown(res: SensitivityResult, command: str) -> str:
    tm = res.timings
    lines = ["# Sensitivity of V_A, V_B to the nine Anand constants", "",
             f"**Verdict.** {res.verdict['text']}", "",
             f"Outputs: {', '.join(res.outputs)}. FE DOE: {res.n_runs_ok} converged LHS runs "
             f"(GP surrogate, leave-one-out RMSE {res.loo['rmse_rel']:.1%} of the spread, 95 % "
             f"coverage {res.loo['coverage95']:.0%}); Sobol base sample {res.sobol.n}; DGSM at "
             f"{res.dgsm.n_points} points through the FE (autograd).", "",
             "| parameter | box | DGSM bound of S_T | DGSM rank | S1 [95 %] | S_T [95 %] "
             "| S_T surrogate SE | rank |", "|---|---|---|---|---|---|---|---|"]
    b, se = res.box, res.st_se_surrogate
    for i, r in sorted(enumerate(res.rows), key=lambda ir: ir[1]["rank"]):
        sc = " (log)" if b.log_scale[i] else ""
        sei = "–" if se is None else f"{float(se[i]):.3f}"
        lines.append(f"| {r['parameter']} | {b.lower[i]:.4g}–{b.upper[i]:.4g} {b.units[i]}{sc} "
                     f"| {r['dgsm']:.3g} | {r['dgsm_rank']} | {r['S1']:.3f} "
                     f"[{r['S1_lo']:.3f}, {r['S1_hi']:.3f}] | {r['ST']:.3f} "
                     f"[{r['ST_lo']:.3f}, {r['ST_hi']:.3f}] | {sei} | {r['rank']} |")
    lines += ["", "Total index S_T per output (GP mean):", "",
              "| parameter | " + " | ".join(res.outputs) + " |",
              "|---|" + "---|" * len(res.outputs)]
    lines += [f"| {nm} | " + " | ".join(f"{v:.3f}" for v in res.sobol.ST[i].tolist()) + " |"
              for i, nm in enumerate(b.names)]
    viol = bound_violations(res)
    lines += ["", "Indices are variance-weighted over the outputs. The DGSM column is "
              "sum_k nu_ik / (pi^2 sum_k Var_k), an upper bound of the aggregated total index "
              "computed from the FE alone; S1 and S_T come from the GP mean (intervals: "
              "bootstrap over the Sobol sample, not the surrogate's own error). The surrogate "
              "SE is the delete-a-group jackknife of S_T over GPs refitted without each group "
              "of runs (same Sobol sample).",
              "", ("DGSM bound check: every S_T is compatible with its FE bound." if not viol
                   else f"DGSM bound check FAILED for {', '.join(viol)}: S_T above the FE "
                   "bound; suspect the surrogate there."), ""]
    lines += [f"- surrogate warning: {p}" for p in res.surrogate_problems]
    lines += ["", "Timings (s): " + ", ".join(f"{k[:-2]} {v:.1f}" for k, v in tm.items()),
              "", f"Command: `{command}`" if command else "", "",
              "![sensitivity](sensitivity.png)", ""]
    return "\n".join(lines)


def plot_sensitivity(res: SensitivityResult) -> Any:
    """Two panels: S_T and S1 bars with intervals per constant; DGSM bound (log scale) with
    S_T marked. Returns the matplotlib Figure."""
    from solderpyro.reporting.plots import plt

    names = list(res.box.names)
    sb, dg = res.sobol, res.dgsm
    x = np.arange(len(names))
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(8, 6.5), sharex=True)
    for off, val, lo, hi, lab in ((-0.2, sb.ST_agg, sb.ST_lo, sb.ST_hi, "total S_T"),
                                  (0.2, sb.S1_agg, sb.S1_lo, sb.S1_hi, "main S1")):
        v = val.numpy()
        err = np.stack([v - lo.numpy(), hi.numpy() - v]).clip(min=0)
        a1.bar(x + off, v, 0.4, yerr=err, capsize=3, label=lab)
    se = res.st_se_surrogate
    if se is not None:
        a1.errorbar(x - 0.2, sb.ST_agg.numpy(), yerr=1.96 * se.numpy(), fmt="none", ecolor="k",
                    elinewidth=2.5, alpha=0.5, label="S_T +- 1.96 surrogate SE")
    a1.set_ylabel("Sobol index (GP mean)")
    a1.axhline(0, color="0.5", lw=0.6)
    a1.legend()
    a1.set_title(res.verdict["text"].split(" -> ")[0] + " -> "
                 + ("reproduced" if res.verdict["reproduced"] else "not reproduced"),
                 fontsize=8)
    v = dg.bound_agg.numpy()
    err = np.stack([v - dg.lo.numpy(), dg.hi.numpy() - v]).clip(min=0)
    a2.bar(x, v, 0.5, yerr=err, capsize=3, color="C2", label="DGSM bound nu/(pi^2 Var), FE")
    floor = 1e-4 * float(np.max(dg.hi.numpy()))  # S_T below it is drawn on the floor
    a2.plot(x, sb.ST_agg.numpy().clip(min=floor), "k_", ms=14, mew=2, label="S_T (GP)")
    a2.set_yscale("log")
    a2.set_ylim(bottom=floor)
    a2.set_ylabel("bound of S_T")
    a2.legend(fontsize=8)
    for ax in (a1, a2):
        ax.grid(axis="y", alpha=0.3)
    a2.set_xticks(x, [f"{n}*" if n in SEED_CHOICE else n for n in names])
    a2.set_xlabel("Anand constant (* = calibrated by the seed)")
    fig.tight_layout()
    return fig


def parse_bounds(text: str) -> dict[str, tuple[float, float]]:
    """``"A=1e5:1e8,h0=500:3000"`` -> ``{"A": (1e5, 1e8), ...}``; errors name the item."""
    outd: dict[str, tuple[float, float]] = {}
    for item in filter(None, (t.strip() for t in text.split(","))):
        try:
            k, v = item.split("=", 1)
            lo, hi = (float(s) for s in v.split(":"))
        except ValueError:
            raise ValueError(f"--box item {item!r} is not name=lower:upper") from None
        outd[k.strip()] = (lo, hi)
    return outd
