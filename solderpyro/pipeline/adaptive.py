"""Stage 2-3 together, the adaptive design: the calibration places its own FE runs.

Wires :mod:`solderpyro.design.loop` to the specimen: the FE through the run store
(:meth:`~.problem.CalibrationProblem.fe`), the surrogate fit (:mod:`.surrogate`) and the
warm-started posterior (:mod:`.posterior`). Three steps, the data flowing one way: the rounds
(:func:`adaptive_design`) on the measured data; the discretization correction
(:func:`correct_discretization`), which returns corrected data; the final posterior
(:func:`final_design_posterior`) on the data it is given.

After every round it writes ``design.csv`` (every FE run: round, kind, parameters, converged),
``design_rounds.json`` and ``design.png`` (marginals per round, code chi-square per round,
where the runs went), so a crashed run leaves its record; the FE runs themselves are in the run
store, and a rerun with the same settings proposes the same runs (every step is seeded), so it
reuses them instead of solving again.
"""

from __future__ import annotations

import csv
import json
import logging
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from solderpyro.config.settings import CalibrationSettings
from solderpyro.design import lhs
from solderpyro.design.loop import (
    Draws,
    LoopProblem,
    LoopResult,
    design_rounds,
    final_posterior,
)
from solderpyro.params import Box
from solderpyro.pipeline.fe_check import misses
from solderpyro.pipeline.posterior import as_draws, sample_posterior
from solderpyro.pipeline.problem import CalibrationProblem, ObservedData
from solderpyro.pipeline.surrogate import fit_surrogate
from solderpyro.surrogate import GPSurrogate

log = logging.getLogger("solderpyro")


def loop_problem(cp: CalibrationProblem, s: CalibrationSettings,
                 warm: Any = None) -> LoopProblem:
    """The design loop's view of ``cp`` (:class:`LoopProblem`): its data ``cp.y``, the FE
    through the run store, the surrogate fit and the warm-started posterior (``warm``: a
    :class:`~solderpyro.calibration.mcmc.WarmStart` for the first round's posterior)."""
    last: list[float | None] = [None]  # the latest posterior's noise sd (PCA truncation)

    def fit(X: torch.Tensor, Y: torch.Tensor) -> GPSurrogate:
        return fit_surrogate(cp, s.surrogate, X, Y, last[0])

    def sample(gp: GPSurrogate, prev: Draws | None, final: bool) -> Draws:
        w = prev.posterior[0].warm if prev is not None else warm
        if prev is not None and prev.start and w is not None:  # the loop localized
            w = replace(w, point=prev.start).placed(cp.space, cp.priors.sigma_known is not None,
                                                    seed=s.seed)
        post, inp = sample_posterior(cp, gp, s.sampler, s.seed, w, final, s.progress)
        d = as_draws(cp, post, inp)
        last[0] = float(d.sigma.median())
        return d

    return LoopProblem(cp.gp_box, cp.y, cp.fe, fit, sample, misfit_test(cp))


def adaptive_design(cp: CalibrationProblem, s: CalibrationSettings, out: Path,
                    warm: Any = None, refit: dict[str, float] | None = None) -> LoopResult:
    """The adaptive design's rounds on the specimen (:func:`~solderpyro.design.loop.
    design_rounds`), their record kept in ``out``.

    Args:
        cp: the problem (the measured data). s: the settings (``s.design``: the loop's;
            ``s.sampler``: NUTS). out: the run directory. warm: a
            :class:`~solderpyro.calibration.mcmc.WarmStart` for the first round's posterior
            (e.g. the run this one adds an effect to).
        refit: the FE's best fit of this very model where one is known (``name -> value``,
            physical units; ``solderpyro diagnose``'s refit, :func:`~.warm.refit_point`): up
            to ``s.design.localize`` runs around it join the start design
            (:func:`refit_design`).

    Returns:
        the rounds' :class:`~solderpyro.design.loop.LoopResult` (its ``draws``: the last
        round's posterior); :func:`final_design_posterior` draws the final one.
    """
    p = loop_problem(cp, s, warm)
    ds, budget = s.design, s.design.runs_allowed(cp.gp_box.dim)
    log.info("design: %d Latin-hypercube runs over %s, then rounds of %d acquired + %d check "
             "runs (%s criterion) up to %d FE runs", ds.start, ", ".join(cp.gp_box.names),
             ds.batch, ds.check, ds.criterion, budget)
    X0 = lhs(cp.gp_box, ds.start, s.seed)
    kinds = ["start"] * len(X0)
    near = refit_design(cp, refit, X0, min(ds.localize, budget - ds.start - ds.check), s.seed)
    if near is not None:
        X0 = torch.cat([X0, near])
        kinds += ["fe_fit"] * len(near)
    return design_rounds(p, ds, s.seed, X0, names=list(cp.gp_box.names),
                         on_round=lambda r: save_design(r, cp.gp_box.names, out), kinds=kinds)


def final_design_posterior(cp: CalibrationProblem, s: CalibrationSettings, out: Path,
                           rounds: LoopResult) -> LoopResult:
    """The design's final posterior on ``cp``'s data (corrected, where the calibration
    corrected them), checked by the FE in every chain
    (:func:`~solderpyro.design.loop.final_posterior`); its record kept in ``out``.

    Returns:
        the :class:`~solderpyro.design.loop.LoopResult`; its ``draws.posterior`` is the
        final ``(Posterior, ObsInputs)``.
    """
    return final_posterior(loop_problem(cp, s), rounds, s.design, list(cp.gp_box.names),
                           on_round=lambda r: save_design(r, cp.gp_box.names, out))


def correction_point(checked_c2: np.ndarray, best_fit: dict[str, Any] | None, box: Box,
                     dim: int) -> int | np.ndarray | None:
    """Where the discretization error is estimated: the best checked draw (its index into
    ``checked_c2``, the draws' chi-squares), or the design's own FE best fit (``best_fit``:
    the loop's record, ``"x"`` name -> value and ``"chi2"``; returned as ``(box.dim,)``
    physical values in ``box``'s order) where the draws miss it
    (:func:`~.fe_check.misses` in the ``dim`` calibrated parameters: a posterior around the
    fit lies on the same ridge, where the error is the same); None where neither is finite.

    Why: the error changes across the box by more than the data resolve; where the design's
    budget ran out with the surrogate's posterior away from where the FE fits, the best
    checked draw can misfit badly (4.77 noise sd on the forms benchmark's quadratic CTE with
    a linear modulus, the FE's best fit 1.16), and the data corrected there were fitted 1.31
    noise sd off, 1.67 against the measured data.
    """
    c2 = np.where(np.isfinite(checked_c2), np.asarray(checked_c2, float), np.inf)
    x = box.row((best_fit or {}).get("x"))
    bf_c2 = float((best_fit or {}).get("chi2", np.inf))
    if x is not None and np.isfinite(bf_c2) and misses(c2.min(), bf_c2, dim):
        return x
    return int(np.argmin(c2)) if np.isfinite(c2).any() else None


def correct_discretization(cp: CalibrationProblem, d: Draws,
                           best_fit: dict[str, Any] | None = None) -> ObservedData:
    """``cp``'s data with the FE's discretization error taken off
    (:meth:`~.problem.ObservedData.corrected`), estimated by one refinement
    (:func:`~.fe_check.discretization_error`, one FE run more) at the best of ``d``'s checked
    draws (the FE's outputs there come with them), or at the design's own FE best fit
    (``best_fit``, the loop's record) where the draws miss it (:func:`correction_point`).
    When no checked draw converged or the refined run fails (logged) the data come back
    uncorrected, and the calibration's discretization check says so.

    Returns:
        the data every later stage uses (:meth:`~.problem.CalibrationProblem.with_data`).
    """
    from solderpyro.pipeline.fe_check import discretization_error

    if d.checked is None:
        return cp.data
    th, V, c2 = d.checked
    at = correction_point(np.asarray(c2, float), best_fit, cp.gp_box, cp.space.dim)
    if at is None:
        log.warning("discretization: no checked draw converged; the data are not corrected")
        return cp.data
    if isinstance(at, np.ndarray):
        x, V_at, where = at, None, "the design's own FE best fit"
    else:
        x, V_at, where = th[at].numpy(), V[at].numpy(), "the best checked draw"
    delta = discretization_error(cp, x, V=V_at)
    if not np.all(np.isfinite(delta)):
        log.warning("discretization: the refined FE run failed; the data are not corrected")
        return cp.data
    sig = float(cp.priors.sigma_known or d.sigma.median())
    chi = float(np.sum(delta ** 2) / sig ** 2)
    log.info("discretization: the FE's error by one refinement at %s (chi2 %.3g, RMS %.3g um) "
             "is taken off the data for the final posterior", where, chi,
             float(np.sqrt(np.mean(delta ** 2))))
    return cp.data.corrected(delta, at=dict(zip(cp.gp_box.names, map(float, x), strict=True)),
                             chi2=chi, sigma=sig)


#: the Laplace approximation at a known FE best fit is widened by this factor (in sd) for the
#: runs placed around it: the posterior's 95 % region is ~2 sd, and a linearization is too
#: narrow along a curved ridge
REFIT_WIDEN = 2.0


def refit_design(cp: CalibrationProblem, point: dict[str, float] | None, have: torch.Tensor, m: int,
                 seed: int = 0) -> torch.Tensor | None:
    """FE runs around a known FE best fit of this model, for the start design.

    When a recalibration starts where ``solderpyro diagnose`` refitted exactly its effects
    (``point``: :func:`~solderpyro.pipeline.warm.refit_point`), the new posterior lies around
    that refit, and a surrogate of the whole box learns it only after several rounds (the
    loop's recalibration with the modulus' temperature slope: 6 rounds, 94 runs, code chi2
    2.65e3 in the first). Here: one Levenberg-Marquardt iteration from the point (its
    Jacobian, through the run store), then ``m`` runs drawn from its Laplace approximation
    widened :data:`REFIT_WIDEN` times (unit box; draws outside it dropped), at least
    :data:`~solderpyro.design.loop.LOCAL_SPACING` apart and from ``have``; the end of that
    iteration (the point, or a step better) first.

    Args:
        cp: the problem. point: ``name -> value`` (physical units) covering every calibrated
            parameter (else None is returned). have: ``(n, n_fe)`` the runs already planned.
        m: the most runs to place. seed: of the draws.
    Returns:
        ``(<= m, n_fe)`` FE parameter rows (physical units), or None.
    """
    from solderpyro.design.loop import spaced_rows
    from solderpyro.pipeline.fe_exact import fe_best_fit

    space = cp.space
    row = space.row(point)
    if point is None or row is None or m < 1:
        return None
    x0 = np.clip(row, space.lower, space.upper)[None]
    y = cp.y.detach().cpu().numpy()
    sig = float(cp.priors.sigma_known or point.get("sigma") or 0.0)
    if not sig > 0:
        return None
    fit = fe_best_fit(cp.observed, x0, space, y, sig, 1)
    Ju = fit.jacobian_unit(space.lower, space.upper, space.log_scale)
    u0 = space.to_unit(torch.as_tensor(fit.x[None], dtype=torch.float64)).numpy()[0]
    if Ju is None or not np.isfinite(Ju).all():
        cand = u0[None]
    else:
        H = Ju.T @ Ju / sig**2
        cov = np.linalg.pinv(H + 1e-9 * np.trace(H) * np.eye(len(H)))
        rng = np.random.default_rng(seed)
        z = u0 + REFIT_WIDEN * rng.multivariate_normal(np.zeros(len(u0)), cov, size=8 * m,
                                                        method="eigh")
        # draws outside the box are dropped, not clipped: a clipped draw of a long ridge
        # lands on a face far from the posterior (measured on the toy of the tests)
        cand = np.vstack([u0, z[((z >= 0.0) & (z <= 1.0)).all(1)]])
    gp_u = cand[:, :cp.n_fe]  # the FE-side parameters: what the surrogate sees
    keep = spaced_rows(gp_u, cp.gp_box.to_unit(have).numpy(), m)
    if not len(keep):
        return None
    rows = cp.gp_box.from_unit(torch.as_tensor(gp_u[keep], dtype=torch.float64))
    log.info("design: the diagnosis's FE refit of this model (chi2 %.0f) places %d runs "
             "around it in the start design", fit.chi2, len(rows))
    return rows


def misfit_test(cp: CalibrationProblem, lm_iters: int = 4) -> Any:
    """The design loop's ``misfit`` test for the specimen (:class:`LoopProblem`).

    When the FE misfits the data at every checked posterior draw (the FE check's rule,
    :func:`~.fe_check.misfits`), or the loop says the round is ``far`` from converged, the
    FE's own best fit decides whether the model can fit the data at all: Levenberg-Marquardt
    (``lm_iters`` iterations, through the run store) from the two best checked draws and the
    literature constants, over every calibrated parameter (observation-side ones included).
    Returns None while the checked draws fit and the round is not far (no verdict), else
    ``{"x": {name: value}, "chi2", "rms_over_sigma", "misfits", "fe_runs", "starts",
    "runs"}``; ``"runs"`` ``(fe_runs, n_fe)``
    are the FE parameter sets the fit ran, lowest chi-square first (the loop adds some of them
    to the design when the model can fit: :attr:`~solderpyro.design.loop.LoopSettings.
    localize`).

    Why: on data with a hidden effect the base model's design never converges (its posterior
    jumps between surrogate islands in box corners, every round); without this stop it runs
    to its budget and then through the FE-exact step (517 s of a 759 s ``benchmarks/loop.py``
    run).
    """
    from solderpyro.pipeline.fe_check import misfits
    from solderpyro.pipeline.fe_exact import fe_best_fit

    n = int(cp.y.numel())
    y = cp.y.detach().cpu().numpy()
    space = cp.space

    def test(d: Draws, chk: np.ndarray, fe_c2: np.ndarray, far: bool) -> dict[str, Any] | None:
        all_misfit = misfits(float(np.min(fe_c2)), n)
        if not far and not all_misfit:
            return None
        post = d.posterior[0]
        full = post.flat("t").detach().cpu().numpy()
        # the two best checked draws and the literature constants (the other columns at the
        # posterior median), in one batched fit: the draws of a misfitting model's surrogate
        # posterior sit in islands, and diagnose, which starts from this fit, need not scout
        # from the literature constants again (that scouting took 24 of its 74 s in the loop)
        anand = cp.setup.anand
        lit = np.array([anand.get(nm, v) for nm, v in zip(space.names, np.median(full, 0),
                                                          strict=True)], float)
        starts = np.concatenate([full[chk[np.argsort(fe_c2)[:2]]],
                                 np.clip(lit, space.lower, space.upper)[None]])
        sig = float(cp.priors.sigma_known or d.sigma.median())
        seen: list[tuple[np.ndarray, np.ndarray]] = []  # (rows, their chi-squares)

        def counted(rows: np.ndarray) -> np.ndarray:
            V = cp.observed(rows)
            seen.append((rows, (((y - V) / sig) ** 2).sum(1)))
            return V

        # the three advance together for half the steps, the best one alone for the rest
        # (120 FE rows in all steps from all three took 16.7 s of the loop's base run)
        half = max(1, lm_iters // 2)
        best = fe_best_fit(counted, starts, space, y, sig, half)
        if lm_iters > half:
            best = fe_best_fit(counted, best.x[None], space, y, sig, lm_iters - half)
        rows = np.concatenate([r for r, _ in seen])
        c2 = np.concatenate([c for _, c in seen])
        c2 = np.where(np.isfinite(c2), c2, np.inf)
        out = {"x": dict(zip(space.names, map(float, best.x), strict=True)),
               "chi2": float(best.chi2), "rms_over_sigma": float(np.sqrt(best.chi2 / n)),
               "misfits": misfits(float(best.chi2), n), "fe_runs": len(rows),
               "starts": ["best checked draw", "second checked draw", "literature constants"],
               "runs": rows[np.argsort(c2, kind="stable"), :cp.n_fe]}
        log.info("design: %s; the FE's own best fit: chi2 %.0f (%.2f noise sd, %d FE runs)%s",
                 "the FE misfits at every checked draw" if all_misfit else
                 "the round is far from converged", out["chi2"],
                 out["rms_over_sigma"], out["fe_runs"],
                 ": the model misses something" if out["misfits"] else ": the model can fit")
        return out

    return test


def save_design(r: LoopResult, names: Any, out: Path) -> None:
    """``design.csv``, ``design_rounds.json`` and ``design.png`` of the loop so far."""
    out.mkdir(parents=True, exist_ok=True)
    X = r.X.numpy()
    with (out / "design.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["run", "round", "kind", *names, "converged"])
        for i in range(len(X)):
            w.writerow([i, r.round[i], r.kind[i], *[repr(float(v)) for v in X[i]],
                        int(bool(r.ok[i]))])
    (out / "design_rounds.json").write_text(json.dumps(r.as_dict(), indent=1, default=float)
                                            + "\n")
    try:
        plot_design(r, list(names), out / "design.png")
    except Exception:  # a figure never costs the run its record
        log.warning("design.png not drawn", exc_info=True)


def plot_design(r: LoopResult, names: list[str], path: Path) -> Path:
    """One figure of the loop: per parameter, the posterior's median and 95 % interval per
    round with the runs placed in it; the code chi-square and the FE-vs-surrogate chi-square
    per round against the stopping tolerance; and the runs in the first two parameters."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = len(names)
    ncol = max(d, 2)
    fig, grid = plt.subplots(2, ncol, figsize=(3.0 * ncol, 6.4), squeeze=False)
    axes = [*grid[0, :d], grid[1, 0], grid[1, 1]]  # parameters on top; rule and runs below
    for ax in [*grid[0, d:], *grid[1, 2:]]:
        ax.axis("off")
    rounds = [q.round for q in r.rounds]
    bf = (r.best_fit or {}).get("x") or {}
    X = r.X.numpy()
    rnd = np.asarray(r.round)
    kinds = np.asarray(r.kind)
    for j, nm in enumerate(names):
        ax = axes[j]
        q = np.array([rec.quantiles[nm] for rec in r.rounds])  # (R, 3)
        ax.fill_between(rounds, q[:, 0], q[:, 2], color="C0", alpha=0.25, label="95 % interval")
        ax.plot(rounds, q[:, 1], "C0o-", ms=3, label="median")
        for kind, mk, c in (("acquired", "x", "C3"), ("check", "+", "C2"),
                            ("fe_fit", "d", "C4")):
            m = kinds == kind
            if m.any():
                ax.plot(rnd[m] + 0.15, X[m, j], mk, color=c, ms=4,
                        label="the FE best fit's runs" if kind == "fe_fit" else f"{kind} runs")
        if nm in bf:
            ax.axhline(bf[nm], color="k", ls=":", lw=1.0, label="the FE's own best fit")
        ax.set_xlabel("round")
        ax.set_title(nm, fontsize=9)
        if j == 0:
            ax.legend(fontsize=6)
    ax = axes[d]
    code = [rec.code_chi2 for rec in r.rounds]
    dfe = [rec.fe_gap for rec in r.rounds]
    tol = r.rounds[-1].tolerance
    ax.semilogy(rounds, code, "C0o-", label="code chi2 at posterior draws")
    ax.semilogy(rounds, np.maximum(dfe, 1e-3), "C3s-", label="max |FE - surrogate| chi2")
    ax.axhline(tol, color="k", ls="--", lw=0.8, label="tolerance sqrt(2n)")
    spread = [rec.fe_spread for rec in r.rounds]
    ax.semilogy(rounds, np.maximum(spread, 1e-3), "C1^-",
                label="spread of that gap over the checks")
    ax.axhline(r.rounds[-1].spread_tolerance, color="C1", ls=":", lw=0.8,
               label="spread tolerance")
    ax.set_xlabel("round")
    # where the curves are not: they fall from the upper left over many rounds, and stay at
    # the top when a misfit stops the design after two
    ax.legend(fontsize=5.5, loc="best", framealpha=0.85)
    ax.set_title("stopping rule", fontsize=9)
    ax = axes[d + 1]
    if d >= 2:
        for kind, mk, c in (("start", "o", "0.6"), ("acquired", "x", "C3"), ("check", "+", "C2"),
                            ("fe_fit", "d", "C4")):
            m = kinds == kind
            if m.any():
                ax.plot(X[m, 0], X[m, 1], mk, color=c, ms=4,
                        label="FE best fit's" if kind == "fe_fit" else kind)
        if names[0] in bf and names[1] in bf:
            ax.plot(bf[names[0]], bf[names[1]], "k*", ms=10, label="FE best fit")
        ax.set_xlabel(names[0])
        ax.set_ylabel(names[1])
        ax.legend(fontsize=6)
        ax.set_title("where the runs went", fontsize=9)
    else:
        ax.axis("off")
    from matplotlib.ticker import MaxNLocator

    for a in axes[:d + 1]:  # rounds are whole numbers
        a.xaxis.set_major_locator(MaxNLocator(integer=True))
    fig.suptitle(f"adaptive design: {len(X)} FE runs, {len(r.rounds)} rounds"
                 + (f" ({r.reason})" if r.reason in ("converged", "budget", "misfit") else ""),
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path

