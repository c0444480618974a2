"""Stage 6 (when needed), the FE-exact posterior: the FE itself in the likelihood.

Adaptive importance sampling (:mod:`solderpyro.exact.posterior`) from a proposal built on the
surrogate posterior, the FE's best fit and a chi-square profile along the ridge; then, for
parameters the data leave weakly identified, which measurement would narrow them; and the 95 %
profile-likelihood intervals through the FE.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from solderpyro.calibration import Priors
from solderpyro.calibration.intervals import INTERVAL_COLUMNS, with_intervals
from solderpyro.config.compose import Setup
from solderpyro.io.measurements import Measurements
from solderpyro.params import Box
from solderpyro.pipeline.fe_check import misfits

log = logging.getLogger("solderpyro")
#: summary.csv's columns: the central quantiles, then the reported 95 % interval
#: (:mod:`solderpyro.calibration.intervals`: central, or from a box face)
SUMMARY = ("parameter", "q2.5", "median", "mean", "q97.5", *INTERVAL_COLUMNS)


@dataclass(frozen=True)
class ExactRun:
    """The settings of one FE-exact posterior (:func:`fe_exact`).

    Attributes:
        n: FE runs per AMIS round; rounds: AMIS rounds; extra_rounds: up to this many more
            while the weights are not reliable.
        n_profile: grid points of the chi-square profile along the weakest direction (0: no
            profile).
        seed: random seed; n_draws: posterior draws kept.
        lm_iters: Levenberg-Marquardt iterations of the FE's best fit.
        run: the rounds, runs, profile and stopping rule (:class:`ExactRun`).
    """

    n: int
    rounds: int
    n_profile: int = 9
    seed: int = 0
    n_draws: int = 1000
    lm_iters: int = 4
    stop_if_misfit: bool = False
    noise_sd: float | None = None
    extra_rounds: int = 0


def fe_exact(fun: Any, coords: Any, y_obs: torch.Tensor, priors: Priors,
             draws: np.ndarray | None, starts: np.ndarray, run: ExactRun
             ) -> tuple[Any, dict[str, Any]]:
    """The FE-exact posterior of a specimen calibration (:mod:`solderpyro.exact.posterior`).

    The FE's best fit from ``starts`` (Levenberg-Marquardt, ``run.lm_iters`` iterations) and
    its Laplace covariance, the chi-square profiled along the weakest direction's coordinate
    over ``run.n_profile`` grid points (0: no profile), a first proposal from those and the
    surrogate posterior's ``draws``, then ``run.rounds`` AMIS rounds of ``run.n`` FE runs
    each, all in the sampling coordinates ``coords``
    (:func:`solderpyro.exact.coords.sampling_coords`).

    Args:
        fun: ``rows (b, dim) -> (b, n_obs)`` the FE's observed outputs, um (e.g.
            :meth:`~solderpyro.specimen.SpecimenModel.observed_runs` through the run store).
        y_obs: ``(n_obs,)`` um; priors: the calibration's (sigma's prior).
        draws: ``(n, dim)`` surrogate posterior draws (or None); starts: ``(k, dim)`` starts of
            the best fit (e.g. the FE check's best draws), physical units.
        run: the rounds, runs, profile and stopping rule (:class:`ExactRun`).
    Returns:
        ``(ExactPosterior, info)``; ``info`` for the run record: ESS, k-hat, reliable, the number of
        FE runs, the coordinates, the best fit, the profile and each round's diagnostics.
        With ``run.stop_if_misfit`` and a misfitting best fit: ``(None, info)``, ``info["stopped"]``
        saying why.
    """
    from solderpyro.exact.posterior import (
        ExactSampling,
        ProfileOptions,
        exact_posterior,
        fe_profile,
        initial_proposal,
        laplace_cov_w,
    )

    n, rounds, n_profile, seed = run.n, run.rounds, run.n_profile, run.seed
    n_draws, lm_iters, stop_if_misfit, noise_sd = (run.n_draws, run.lm_iters,
                                                   run.stop_if_misfit, run.noise_sd)
    space = coords.space
    y = y_obs.detach().cpu().numpy()
    n_fe = [0]

    def counted(rows: np.ndarray) -> np.ndarray:
        n_fe[0] += len(rows)
        return fun(rows)

    # the fits' noise sd: the stated one, else the RMS residual at the first start
    sig = priors.sigma_known or float(np.sqrt(np.nanmean((counted(starts[:1]) - y) ** 2)))
    best = fe_best_fit(counted, starts, space, y, sig, lm_iters)
    log.info("exact: the FE's best fit chi2 %.1f at %s (%d FE runs); sampling in %s "
             "coordinates", best.chi2, ", ".join(f"{nm}={v:.4g}" for nm, v in zip(
                 space.names, best.x, strict=True)), n_fe[0], coords.name)
    # the misfit rule in units of the noise (sig is the RMS at a start when sigma is unknown)
    c2_noise = float(best.chi2) * (sig / (noise_sd or sig)) ** 2
    best_info = {"x": best.x.tolist(), "chi2": best.chi2, "ssr_um2": float(best.chi2 * sig**2),
                 "rms_over_sigma": float(np.sqrt(c2_noise / y.size))}
    if stop_if_misfit and misfits(c2_noise, y.size):
        why = (f"the FE's own best fit misfits the data (chi2 {c2_noise:.0f} on {y.size} "
               f"values, RMS {best_info['rms_over_sigma']:.2f} noise sd): the model misses "
               "something the data show, so its FE-exact posterior and profile intervals are "
               "not computed (solderpyro diagnose names candidate effects; --exact on "
               "computes them anyway)")
        log.warning("exact: %s", why)
        return None, {"stopped": why, "fe_runs": n_fe[0], "coordinates": coords.name,
                      "best_fit": best_info}
    J = best.jacobian_unit(space.lower, space.upper, space.log_scale)
    cov = (laplace_cov_w(J, coords, best.x, sig) if J is not None
           else np.eye(space.dim) * 0.25)
    prof = None
    if n_profile >= 2:
        prof = fe_profile(counted, coords, best.x, cov, y, sig,
                          ProfileOptions(n_grid=n_profile, iters=4))
        log.info("exact: chi2 profile along %s: %s (%d FE runs so far)", space.names[prof.coord],
                 ", ".join(f"{v:.4g}: {c:.1f}" for v, c in zip(prof.x[:, prof.coord],
                                                                 prof.chi2, strict=True)),
                 n_fe[0])
    q0 = initial_proposal(coords, draws, (best.x, cov), prof, seed)

    def on_round(r: Any) -> None:
        h = r.history[-1]
        log.info("exact: AMIS round %d: %d samples, ESS %.1f, Pareto k-hat %.2f (%d FE runs "
                 "so far)", len(r.history), h["n"], h["ess"], h["khat"], n_fe[0])

    amis_run = ExactSampling(n, rounds, seed=seed, n_draws=n_draws, on_round=on_round,
                             extra_rounds=run.extra_rounds)
    ex = exact_posterior(counted, coords, y, q0, amis_run, priors.sigma_known, priors.sigma_max,
                         prof)
    r = ex.result
    info = {"ess": r.ess, "khat": r.khat, "reliable": r.reliable, "fe_runs": n_fe[0],
            "samples": int(len(r.u)), "coordinates": coords.name, "rounds": r.history,
            "best_fit": best_info,
            **({"profile": {"parameter": space.names[prof.coord],
                            "values": prof.x[:, prof.coord].tolist(),
                            "chi2": prof.chi2.tolist()}} if prof is not None else {})}
    return ex, info


def fe_best_fit(fun: Any, starts: np.ndarray, space: Box, y: np.ndarray, sigma: float,
                iters: int = 4, tol: float | None = None) -> Any:
    """The FE's best fit: Levenberg-Marquardt (:func:`solderpyro.exact.fit.lm_fit`, ``iters``
    iterations) from every start at once, the lowest chi-square kept.

    Args:
        fun: ``rows (b, dim) -> (b, n_obs)`` the FE's observed outputs, um (through the run
            store); starts: ``(k, dim)`` physical units; space: the calibrated box;
        y: ``(n_obs,)`` um; sigma: the fits' noise sd, um; iters, tol: of
        :class:`~solderpyro.exact.fit.LMOptions` (None: all ``iters``).
    Returns:
        the best :class:`~solderpyro.exact.fit.LMFit` (``x (dim,)``, ``chi2`` in ``sigma`` units).
    """
    from solderpyro.exact.fit import LMOptions, lm_fit

    fits = lm_fit(fun, starts, space.lower, space.upper, y, sigma,
                  options=LMOptions(iters=iters, tol=tol))
    return min(fits, key=lambda f: f.chi2)


def exact_rows(ex: Any, surrogate: list[dict]) -> list[dict]:
    """``exact_posterior.csv``'s rows: per parameter of ``surrogate`` (summary rows), the
    FE-exact 2.5 / 50 / 97.5 % and mean, then the surrogate's, then the weights' Kish ESS and
    Pareto k-hat (the same on every row)."""
    by = {r["parameter"]: r for r in ex.rows}
    r_ = ex.result
    return [{**{k: by[s["parameter"]][k] for k in SUMMARY},
             "surrogate_q2.5": float(s["q2.5"]), "surrogate_median": float(s["median"]),
             "surrogate_q97.5": float(s["q97.5"]), "ess": r_.ess, "khat": r_.khat}
            for s in surrogate if s["parameter"] in by]


#: a parameter whose FE-exact 95 % interval spans at least this share of its prior box (on the
#: box's unit scale) is reported as weakly identified, and a measurement that narrows it sought
WEAK_SHARE = 0.4
#: an interval end within this share of the box's width from a bound is set by the prior box
EDGE_SHARE = 0.02


def ridge_ends(x: np.ndarray, weights: np.ndarray, ssr: np.ndarray, k: int
               ) -> tuple[int, int]:
    """Two importance samples at the ends of parameter ``k``'s posterior that fit the data as
    well as the posterior's bulk does.

    Among the samples inside ``k``'s central 95 % interval whose sum of squared residuals is
    at most the posterior's weighted median, the ones with the smallest and the largest
    ``x[:, k]``: two parameter sets the data cannot tell apart, as far apart along ``k`` as the
    posterior reaches.

    Args:
        x: ``(N, dim)`` importance samples (any units); weights: ``(N,)`` their normalized
            weights; ssr: ``(N,)`` their sums of squared residuals, um^2 (inf where the model
            failed); k: the parameter's column.
    Returns:
        the two sample indices ``(low end, high end)``.
    Raises:
        ValueError: when no sample qualifies (all weights zero or all fits failed), or the
            qualifying samples do not spread along ``k``.
    """
    from solderpyro.exact.posterior import weighted_quantiles

    x, w, ssr = np.asarray(x, float), np.asarray(weights, float), np.asarray(ssr, float)
    ok = np.isfinite(ssr) & (w > 0)
    if not ok.any():
        raise ValueError("ridge_ends: no sample with a positive weight and a finite fit")
    lo, hi = weighted_quantiles(x[ok, k], w[ok], (0.025, 0.975))
    med = weighted_quantiles(ssr[ok], w[ok], (0.5,))[0]
    inside = ok & (x[:, k] >= lo) & (x[:, k] <= hi)
    good = inside & (ssr <= med)
    idx = np.nonzero(good if good.sum() >= 2 else inside)[0]
    i_lo, i_hi = int(idx[np.argmin(x[idx, k])]), int(idx[np.argmax(x[idx, k])])
    if x[i_lo, k] == x[i_hi, k]:
        raise ValueError(f"ridge_ends: the posterior has no spread in column {k} (its weight "
                         "sits on one sample)")
    return i_lo, i_hi


def identifiability(setup: Setup, effects: tuple[str, ...], space: Box, rows: list[dict],
                    ex: Any, meas: Measurements, sigma: float) -> dict[str, Any]:
    """Which parameters do the data leave weakly identified, and what would narrow them?

    A parameter whose FE-exact 95 % interval spans at least :data:`WEAK_SHARE` of its prior box
    (unit scale) lies along a ridge of the FE's likelihood: its interval is set as much by the
    prior box and the ridge's volume as by the data, and may miss the truth although the model
    fits. For the weakest one, two importance samples at the ends of its interval that fit as
    well as the posterior's bulk (:func:`ridge_ends`) are run through the FE over the outputs
    not yet measured (:func:`solderpyro.diagnose.separation.separation_options`): where they differ
    by many noise sd, that measurement would narrow the posterior.

    Args:
        effects: the switched-on effects in the order of their parameters in ``space``.
        space: the calibrated box; rows: the FE-exact summary rows (parameter, q2.5, q97.5).
        ex: the :class:`~solderpyro.exact.posterior.ExactPosterior`; meas: the data; sigma: noise
            sd, um.
    Returns:
        ``{"weak": [{"parameter", "share_of_box", "bound_by_prior"}], "ends": {...},
        "options": [...], "advice"}`` (``ends``/``options`` only when a parameter is weak).
    """
    from solderpyro.diagnose.decide import APART_CHI2
    from solderpyro.diagnose.separation import separation_options

    if not sigma > 0:
        raise ValueError(f"identifiability: sigma must be > 0 um, got {sigma}")
    by = {r["parameter"]: r for r in rows}
    weak: list[dict[str, Any]] = []
    bound_only: list[dict[str, Any]] = []
    # the intervals' ends on the box's unit scale (Box.to_unit is column by column)
    U = space.to_unit(torch.tensor([[by[nm][q] for nm in space.names] for q in ("q2.5", "q97.5")],
                                   dtype=torch.float64)).numpy()
    for k, nm in enumerate(space.names):
        u = U[:, k]
        share = float(u[1] - u[0])
        bound = [side for side, hit in (("lower", u[0] <= EDGE_SHARE),
                                        ("upper", u[1] >= 1 - EDGE_SHARE)) if hit]
        if share >= WEAK_SHARE:
            weak.append({"parameter": nm, "share_of_box": share, "bound_by_prior": bound})
        elif bound:
            bound_only.append({"parameter": nm, "share_of_box": share, "bound_by_prior": bound})
    info: dict[str, Any] = {"weak": weak, "weak_share": WEAK_SHARE, "at_bound": bound_only}
    if not weak:
        info["advice"] = ("every parameter's 95 % interval spans less than "
                          f"{WEAK_SHARE:.0%} of its prior box")
        return info
    top = max(weak, key=lambda v: v["share_of_box"])
    nm, bound_k = top["parameter"], top["bound_by_prior"]
    k = list(space.names).index(nm)
    unit = f" {space.units[k]}" if space.units and space.units[k] not in ("", "-") else ""
    head = (f"{nm} is weakly identified by these data: its 95 % interval "
            f"[{by[nm]['q2.5']:.4g}, {by[nm]['q97.5']:.4g}]{unit} spans "
            f"{top['share_of_box']:.0%} of its prior box"
            + (f" and reaches its {' and '.join(bound_k)} bound" if bound_k else ""))
    try:
        w = ex.result.weights()
        ssr = np.asarray(ex.result.extra["ssr"], float)
        i_lo, i_hi = ridge_ends(ex.samples, w, ssr, k)
        X = ex.samples[[i_lo, i_hi]]
        chi2 = (ssr[[i_lo, i_hi]] / sigma**2).tolist()
        labels = [f"{nm} = {X[0, k]:.4g}", f"{nm} = {X[1, k]:.4g}"]
        info["ends"] = {"parameter": nm, "x": X.tolist(), "chi2": chi2,
                        "names": list(space.names)}
        options, failed = separation_options(setup, effects, X, labels, meas, sigma)
    except (RuntimeError, ValueError) as err:
        info["advice"] = f"{head}; no measurement computed: {err}"
        return info
    info["options"] = options
    head += (f"; posterior samples at its two ends ({labels[0]} and {labels[1]}, chi2 "
             f"{chi2[0]:.0f} and {chi2[1]:.0f} on {len(meas)} values) fit as well as the "
             "posterior's median sample, so the interval follows the prior box and the "
             "ridge's width and may miss the truth")
    if failed is not None:
        info["advice"] = (f"{head}; no measurement computed: the FE at {', '.join(failed[0])} "
                          f"did not converge on the extended outputs ({failed[1]})")
    elif options and options[0]["chi2_apart"] >= APART_CHI2:
        o = options[0]
        info["advice"] = (f"{head}. To narrow it, measure {o['measurement']}: the two differ "
                          f"there by up to {o['max_diff_um']:.3g} um "
                          f"({o['max_diff_um'] / sigma:.1f} noise sd) at t = {o['time_s']:g} s, "
                          f"point {o['point']} {tuple(round(v, 2) for v in o['xy_mm'])} mm; "
                          f"expected chi-square between them "
                          f"{o['chi2_apart']:.0f}")
    else:
        info["advice"] = (f"{head}. No measurement tried (points at the extended times, the "
                          "full field at the measured and extended times) separates them; "
                          "another test (a different cycle or dwell) is needed")
    return info


@dataclass
class BestFitPosterior:
    """What a calibration reports for a model that cannot fit the data: the FE's own best fit
    with its Laplace spread, the covariance scaled by the misfit (Birge's ratio).

    Attributes:
        x: ``(dim,)`` the best fit, physical units; chi2: its chi-square in noise units;
        scale: ``sqrt(chi2 / (n - dim))``, the factor on the noise sd (and on the spread);
        theta: ``(N, dim)`` draws of the scaled Laplace Gaussian in the sampling coordinates,
            mapped back (inside the box); sigma: ``(N,)`` um, the noise sd times ``scale``;
        rows: summary rows (``SUMMARY`` keys, plus sigma), the median at the best fit.
    """

    x: np.ndarray
    chi2: float
    scale: float
    theta: np.ndarray
    sigma: np.ndarray
    rows: list[dict[str, Any]]


#: rounds of ``4 n_draws`` Laplace draws :func:`best_fit_posterior` takes to find its draws
#: inside the box
BEST_FIT_ROUNDS = 10


@dataclass(frozen=True)
class BestFitOptions:
    """How :func:`best_fit_posterior` refines the fit and draws its spread.

    Attributes:
        n_draws: draws of the scaled Laplace Gaussian kept (inside the box).
        seed: seed of those draws.
        lm_iters: at most this many more Levenberg-Marquardt steps from the start.
        lm_tol: the steps stop when one lowers chi-square (noise units) by less than this.
    """

    n_draws: int = 1000
    seed: int = 0
    lm_iters: int = 15
    lm_tol: float = 0.5


def best_fit_posterior(fun: Any, coords: Any, x_best: np.ndarray, y: np.ndarray,
                       noise_sd: float, options: BestFitOptions | None = None
                       ) -> BestFitPosterior:
    """The FE's best fit as the reported posterior of a model that misfits the data.

    Why: a surrogate posterior of a model that cannot fit sits where the surrogate's code
    variance absorbs the misfit (box-corner islands, FE chi-square 1e5-7e6 there; BENCHMARKS.md,
    "Hidden effects"), and fits worse, by the FE, than the FE's own best fit. ``lm_iters`` more
    Levenberg-Marquardt steps from ``x_best`` (``dim + 6`` FE rows each, through ``fun``; the
    design's misfit test stops after 4: on the plane-strain data one more step still lowered
    chi-square 4 %) give the fit and its Jacobian; the Laplace covariance in the sampling
    coordinates is scaled by ``chi2 / (n - dim)`` (the misfit taken as extra noise: the usual
    least-squares answer for a model that does not fit), and ``n_draws`` draws of it, inside
    the box, give the intervals (widened to hold the best fit where it lies on a bound).

    The steps run until one lowers chi-square by less than ``lm_tol`` (diagnose's refits'
    tolerance, :data:`~solderpyro.diagnose.refits.LM_TOL`), at most ``lm_iters``: with 4 fixed
    steps the loop's base run reported chi2 21,679 where one step more reached 17,245 and the
    optimum 17,239, and diagnose, which starts from this fit, paid for the rest.

    Args:
        fun: ``rows (b, dim) -> (b, n_obs)`` um, the FE (through the run store); coords: the
            sampling coordinates (:func:`solderpyro.exact.coords.sampling_coords`); x_best:
            ``(dim,)`` physical; y: ``(n_obs,)`` um; noise_sd: um.
        options: ``n_draws``, ``seed``, ``lm_iters``, ``lm_tol`` (:class:`BestFitOptions`;
            None: its defaults).
    Returns:
        :class:`BestFitPosterior`.
    """
    from solderpyro.exact.posterior import laplace_cov_w

    opt = options or BestFitOptions()
    n_draws, seed = opt.n_draws, opt.seed
    space = coords.space
    best = fe_best_fit(fun, np.asarray(x_best, float)[None], space, y, noise_sd, opt.lm_iters,
                       opt.lm_tol)
    n, d = y.size, space.dim
    scale = float(np.sqrt(max(best.chi2 / max(n - d, 1), 1.0)))
    J = best.jacobian_unit(space.lower, space.upper, space.log_scale)
    w0 = coords.to_w(best.x[None])[0]
    cov = laplace_cov_w(J, coords, best.x, noise_sd * scale) if J is not None else None
    if cov is None or not np.isfinite(cov).all():
        cov = np.eye(d) * 0.25
    rng = np.random.default_rng(seed)
    L = np.linalg.cholesky(0.5 * (cov + cov.T) + 1e-12 * np.eye(d))
    theta = np.empty((0, d))
    for _ in range(BEST_FIT_ROUNDS):
        w = w0 + rng.standard_normal((4 * n_draws, d)) @ L.T
        theta = np.concatenate([theta, coords.from_w(w[coords.inside(w)])])[:n_draws]
        if len(theta) == n_draws:
            break
    if len(theta) < n_draws // 10:
        # a fit in a corner that the Gaussian barely reaches inside the box (the moderate
        # residual stress in the Newton form: not one of 4,000 draws inside): its draws
        # clipped to the box, the mass on the faces the data push against, and the fit itself
        # (a draw even where no clipped one has a preimage)
        log.warning("exact: the FE's best fit sits where its Laplace spread barely reaches "
                    "inside the box (%d of %d draws): the draws are clipped to the box",
                    len(theta), BEST_FIT_ROUNDS * 4 * n_draws)
        x = coords.from_w(w)
        x = x[np.isfinite(x).all(1)]
        theta = np.concatenate([theta, np.clip(x, space.lower, space.upper)[:n_draws - len(theta)],
                                best.x[None]])
    sig = np.full(len(theta), noise_sd * scale)
    rows = [{"parameter": nm,
             "q2.5": min(float(np.quantile(theta[:, k], 0.025)), float(best.x[k])),
             "median": float(best.x[k]), "mean": float(theta[:, k].mean()),
             "q97.5": max(float(np.quantile(theta[:, k], 0.975)), float(best.x[k]))}
            for k, nm in enumerate(space.names)]
    rows.append({"parameter": "sigma", "q2.5": sig[0], "median": sig[0], "mean": sig[0],
                 "q97.5": sig[0]})
    # the reported interval, widened like the quantiles to hold the best fit itself
    rows = [{**r, "lo95": min(r["lo95"], r["median"]), "hi95": max(r["hi95"], r["median"])}
            for r in with_intervals(rows, theta, space)]
    return BestFitPosterior(best.x, float(best.chi2), scale, theta, sig, rows)
