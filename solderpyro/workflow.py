"""The specimen calibration end to end: DOE -> run store -> surrogate -> KOH/NUTS -> report.

:func:`calibrate_specimen` is what ``solderpyro calibrate`` runs. Data flow (one direction):
measurements (shared/data-format.md) -> the model outputs they observe (times x points) ->
Latin hypercube over the parameter box -> batched FE runs in a crash-safe
:class:`~solderpyro.store.RunStore` -> GP surrogate of the observed outputs (one GP per output,
or a PCA basis for full-field data) with leave-one-out validation -> modular KOH posterior with
NUTS -> summary table (seed Table V layout), InferenceData, figures and ``report.md``.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.stats import qmc

from solderpyro.calibration import Priors, calibrate_emulator, predict_observation_model
from solderpyro.calibration.emulators import GPEmulator, ObservedEmulator
from solderpyro.calibration.mcmc import Posterior, format_summary, write_summary
from solderpyro.calibration.predictive import Bands
from solderpyro.configure import Setup
from solderpyro.design import lhs
from solderpyro.effects import EffectSet, effect_set
from solderpyro.fem.problem import reference_grid
from solderpyro.fem.solver import SpecimenSolver
from solderpyro.io.measurements import Measurements
from solderpyro.params import LIU2008, Box, LocalBox, anand_tensor
from solderpyro.store import RunStore, run_doe
from solderpyro.surrogate import GPSurrogate, LooResult

log = logging.getLogger("solderpyro")
SUMMARY = ("parameter", "q2.5", "median", "mean", "q97.5")


def calibration_box(setup: Setup, fx: EffectSet | None = None) -> Box:
    """The calibrated parameters: ``setup.space`` (Anand constants), then the parameters of the
    switched-on effects ``fx`` (bound to the data's times), with their prior boxes."""
    sp = setup.space
    if fx is None or len(fx) == 0:
        return sp
    eb = fx.box
    return Box(tuple(sp.names) + tuple(eb.names), tuple(sp.lower) + tuple(eb.lower),
               tuple(sp.upper) + tuple(eb.upper), tuple(sp.log_scale) + tuple(eb.log_scale),
               tuple(sp.units) + tuple(eb.units))


OBSERVATION_SEAM = "observation operator"


def split_effects(setup: Setup, times: tuple[float, ...]
                  ) -> tuple[EffectSet | None, EffectSet | None, EffectSet | None]:
    """The switched-on effects bound to ``times``: all (FE-side first, then observation-side),
    those the FE must simulate, and the observation-side ones (applied after the surrogate);
    None where empty."""
    if not setup.effects:
        return None, None, None
    fx = effect_set(setup.effects, times, setup.effect_bounds)
    obs = [e.name for e in fx.effects if e.seam == OBSERVATION_SEAM]
    fe = [e.name for e in fx.effects if e.seam != OBSERVATION_SEAM]

    def mk(names: list[str]) -> EffectSet | None:
        return effect_set(names, times, setup.effect_bounds) if names else None

    return mk(fe + obs), mk(fe), mk(obs)


def observation_offset(fx_obs: EffectSet, problem: Any, names: Sequence[str], n_time: int,
                       ti: np.ndarray, oi: np.ndarray) -> Any:
    """``q (n_q,) -> (n_obs,)``: what additive observation effects add to each observation, um
    (they act on V after the FE: ``EffectSet.observe`` of a zero field)."""
    pts = output_points(problem)
    x = torch.tensor([pts[n][0] for n in names], dtype=torch.float64)
    x_O = float(problem.origin[0])
    tt, oo = torch.as_tensor(ti), torch.as_tensor(oi)

    def offset(q: torch.Tensor) -> torch.Tensor:
        z = torch.zeros(1, n_time, len(names), dtype=q.dtype)
        return fx_obs.observe(z, x, x_O, q.reshape(1, -1))[0, tt, oo]

    return offset


def fe_params(setup: Setup, theta: torch.Tensor) -> torch.Tensor:
    """Solver rows ``(n, 9 + n_eff)`` from calibrated ``theta (n, n_anand + n_eff)``: the nine
    Anand constants (defaults for those not calibrated), then the effects' parameters."""
    n = setup.space.n_theta
    return torch.cat([setup.space.full(theta[:, :n]), theta[:, n:]], 1)


def fe_exact(fun: Any, coords: Any, y_obs: torch.Tensor, priors: Priors,
             draws: np.ndarray | None, starts: np.ndarray, n: int, rounds: int,
             n_profile: int = 9, seed: int = 0, n_draws: int = 1000, lm_iters: int = 4
             ) -> tuple[Any, dict[str, Any]]:
    """The FE-exact posterior of a specimen calibration (:mod:`solderpyro.exact`).

    The FE's best fit from ``starts`` (Levenberg-Marquardt, ``lm_iters`` iterations) and its
    Laplace covariance, the chi-square profiled along the weakest direction's coordinate over
    ``n_profile`` grid points (0: no profile), a first proposal from those and the surrogate
    posterior's ``draws``, then ``rounds`` AMIS rounds of ``n`` FE runs each, all in the
    sampling coordinates ``coords`` (:func:`solderpyro.coords.sampling_coords`).

    Args:
        fun: ``rows (b, dim) -> (b, n_obs)`` the FE's observed outputs, um (e.g.
            :func:`fe_observed` through the run store).
        y_obs: ``(n_obs,)`` um; priors: the calibration's (sigma's prior).
        draws: ``(n, dim)`` surrogate posterior draws (or None); starts: ``(k, dim)`` starts of
            the best fit (e.g. the FE check's best draws), physical units.
    Returns:
        ``(ExactPosterior, info)``; ``info`` for run.json: ESS, k-hat, reliable, the number of
        FE runs, the coordinates, the best fit, the profile and each round's diagnostics.
    """
    from solderpyro.exact import exact_posterior, fe_profile, initial_proposal, laplace_cov_w
    from solderpyro.fit import lm_fit

    space = coords.space
    y = y_obs.detach().cpu().numpy()
    n_fe = [0]

    def counted(rows: np.ndarray) -> np.ndarray:
        n_fe[0] += len(rows)
        return fun(rows)

    # the fits' noise sd: the stated one, else the RMS residual at the first start
    sig = priors.sigma_known or float(np.sqrt(np.nanmean((counted(starts[:1]) - y) ** 2)))
    fits = lm_fit(counted, starts, space.lower, space.upper, y, sig, iters=lm_iters)
    best = min(fits, key=lambda f: f.chi2)
    J = best.jacobian_unit(space.lower, space.upper, space.log_scale)
    cov = (laplace_cov_w(J, coords, best.x, sig) if J is not None
           else np.eye(space.dim) * 0.25)
    log.info("exact: the FE's best fit chi2 %.1f at %s (%d FE runs); sampling in %s "
             "coordinates", best.chi2, ", ".join(f"{nm}={v:.4g}" for nm, v in zip(
                 space.names, best.x, strict=True)), n_fe[0], coords.name)
    prof = None
    if n_profile >= 2:
        prof = fe_profile(counted, coords, best.x, cov, y, sig, n_grid=n_profile, iters=4)
        log.info("exact: chi2 profile along %s: %s (%d FE runs so far)", space.names[prof.coord],
                 ", ".join(f"{v:.4g}: {c:.1f}" for v, c in zip(prof.x[:, prof.coord],
                                                                 prof.chi2, strict=True)),
                 n_fe[0])
    q0 = initial_proposal(coords, draws, (best.x, cov), prof, seed)

    def on_round(r: Any) -> None:
        h = r.history[-1]
        log.info("exact: AMIS round %d: %d samples, ESS %.1f, Pareto k-hat %.2f (%d FE runs "
                 "so far)", len(r.history), h["n"], h["ess"], h["khat"], n_fe[0])

    ex = exact_posterior(counted, coords, y, q0, n, rounds, priors.sigma_known,
                         priors.sigma_max, seed, n_draws, prof, on_round)
    r = ex.result
    info = {"ess": r.ess, "khat": r.khat, "reliable": r.reliable, "fe_runs": n_fe[0],
            "samples": int(len(r.u)), "coordinates": coords.name, "rounds": r.history,
            "best_fit": {"x": best.x.tolist(), "chi2": best.chi2},
            **({"profile": {"parameter": space.names[prof.coord],
                            "values": prof.x[:, prof.coord].tolist(),
                            "chi2": prof.chi2.tolist()}} if prof is not None else {})}
    return ex, info


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
    from solderpyro.exact import weighted_quantiles

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
    not yet measured (:func:`solderpyro.diagnose.run.separation_options`): where they differ
    by many noise sd, that measurement would narrow the posterior.

    Args:
        effects: the switched-on effects in the order of their parameters in ``space``.
        space: the calibrated box; rows: the FE-exact summary rows (parameter, q2.5, q97.5).
        ex: the :class:`~solderpyro.exact.ExactPosterior`; meas: the data; sigma: noise sd, um.
    Returns:
        ``{"weak": [{"parameter", "share_of_box", "bound_by_prior"}], "ends": {...},
        "options": [...], "advice"}`` (``ends``/``options`` only when a parameter is weak).
    """
    from solderpyro.diagnose.run import APART_CHI2, separation_options

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
class SpecimenCalibration:
    """What :func:`calibrate_specimen` produced (files are in ``out``)."""

    out: Path
    posterior: Posterior
    summary: list[dict]
    loo: LooResult
    n_runs_ok: int
    n_runs_failed: int


def output_points(problem: Any) -> dict[str, tuple[float, float]]:
    """Every label a measurement may name: the problem's points (A, B) and the 31 x 18 grid.

    Returns:
        label -> (x_mm, y_mm), for ``read_measurements(valid_points=...)``.
    """
    labels, pts = reference_grid()
    return {**{k: (float(v[0]), float(v[1])) for k, v in problem.points.items()},
            **{lab: (float(x), float(y)) for lab, (x, y) in zip(labels, pts, strict=True)}}


def observation_index(meas: Measurements, times: tuple[float, ...], names: tuple[str, ...]
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Where each measured row sits in the model output ``(n_time, n_out)``.

    Returns:
        ``(n_obs,)`` time indices and ``(n_obs,)`` output indices.

    Raises:
        ValueError naming the first row whose time or point is not a model output.
    """
    ti = np.searchsorted(np.asarray(times), meas.time_s)
    oi = np.empty(len(meas), dtype=int)
    lookup = {n: j for j, n in enumerate(names)}
    for r in range(len(meas)):
        t, p = float(meas.time_s[r]), str(meas.point[r])
        if ti[r] >= len(times) or abs(times[ti[r]] - t) > 1e-6:
            raise ValueError(f"measurement row {r + 1}: time {t} s is not an output time")
        if p not in lookup:
            raise ValueError(f"measurement row {r + 1}: point {p!r} is not a model output; "
                             f"valid: A, B or grid labels g_ii_jj")
        oi[r] = lookup[p]
    return ti, oi


RUN_FILES = ("run.json", "data.csv", "draws.npz")
#: the sampler's adapted state in a run directory (:class:`~solderpyro.calibration.mcmc.WarmStart`)
WARM_FILE = "sampler_state.npz"


def save_run(out: Path, meas: Measurements, space: Box, effects: tuple[str, ...],
             post: Posterior, bands: Any, y_obs: torch.Tensor, y_liu: torch.Tensor,
             priors: Priors, record: dict[str, Any],
             draws: tuple[np.ndarray, np.ndarray] | None = None) -> None:
    """Keep what a later ``solderpyro diagnose`` needs in the run directory.

    Writes ``data.csv`` (the measurements, exact round trip), ``draws.npz`` (flat posterior
    draws ``theta (n, dim)`` in physical units with ``names``, ``sigma (n,)`` in um, the
    predictive ``process (n_pred, n_obs)`` and ``observed (n_pred, n_obs)`` draws with their
    noise ``sigma_pred (n_pred,)``, ``y_obs`` and
    the Liu-constants model ``y_liu``, all in um) and ``run.json`` (settings, parameter box).
    ``draws``: ``(theta (n, dim), sigma (n,))`` to save instead of ``post``'s (the FE-exact
    posterior's resampled draws).
    """
    from solderpyro.io.measurements import write_measurements

    write_measurements(out / "data.csv", meas)
    theta, sigma = draws if draws is not None else (post.flat("t").numpy(),
                                                     post.flat("sigma").numpy())
    np.savez(out / "draws.npz", theta=theta, sigma=sigma,
             names=np.array(space.names), process=bands.draws.numpy(),
             observed=bands.obs_draws.numpy(), y_obs=y_obs.numpy(), y_liu=y_liu.numpy(),
             sigma_pred=(bands.sigma if bands.sigma is not None
                         else torch.full((bands.draws.shape[0],), float("nan"))).numpy())
    info = {**record, "parameters": list(space.names), "lower": list(space.lower),
            "upper": list(space.upper), "sigma_known": priors.sigma_known,
            "effects": list(effects),
            "times_s": [float(t) for t in meas.times()], "points": list(meas.points())}
    (out / "run.json").write_text(json.dumps(info, indent=2, default=str) + "\n")
    if post.warm is not None:  # a recalibration can start from here (--warm-from)
        post.warm.save(out / WARM_FILE)


def _posterior_region(t: torch.Tensor, box: Box) -> Box:
    """The region the posterior draws ``t (n, d)`` occupy: their 0.5-99.5 % range widened by
    half its width on each side, inside ``box``."""
    ql, qh = torch.quantile(t, 0.005, 0), torch.quantile(t, 0.995, 0)
    wd = qh - ql
    lo = torch.maximum(ql - 0.5 * wd, torch.tensor(box.lower, dtype=t.dtype))
    hi = torch.minimum(qh + 0.5 * wd, torch.tensor(box.upper, dtype=t.dtype))
    return Box(box.names, tuple(lo.tolist()), tuple(hi.tolist()), box.log_scale, box.units)


def fe_observed(solver: SpecimenSolver, setup: Setup, times: tuple[float, ...], ti: np.ndarray,
                oi: np.ndarray, rows: np.ndarray, n_fe: int, obs_offset: Any = None,
                store: RunStore | None = None, cfg_hash: str | None = None,
                batch_size: int = 64) -> np.ndarray:
    """The FE's observed outputs ``(b, n_obs)`` um for parameter rows ``(b, space.dim)``
    (FE-side parameters first, ``n_fe`` of them, then observation-side ones, which
    ``obs_offset: q -> (n_obs,)`` adds); NaN rows for members that did not converge.

    With ``store`` and ``cfg_hash`` the runs go through :func:`~solderpyro.store.run_doe`:
    stored as soon as each batch of ``batch_size`` finishes, and read back when already there.
    """
    P = fe_params(setup, torch.tensor(np.asarray(rows)[:, :n_fe], dtype=torch.float64))
    if store is not None and cfg_hash is not None:
        res: Any = run_doe(solver, store, cfg_hash, P, times, batch_size, progress=False)
    else:
        res = solver.solve(P, times)
    V = res.V.detach().cpu().numpy()[:, ti, oi]
    if obs_offset is not None:
        V = V + np.stack([obs_offset(torch.tensor(r[n_fe:])).detach().numpy() for r in rows])
    V[~res.ok.cpu().numpy()] = np.nan
    return V


#: the FE check warns when even the best of the checked posterior draws misfits by more than
#: this many noise sd (the yardstick of issue 6: a fit at the noise level is within 1.5 sd) ...
FE_CHECK_RMS = 1.5
#: ... and its chi-square exceeds this quantile of chi2(n) (guards small n against chance)
FE_CHECK_QUANTILE = 0.999
#: posterior draws the FE check runs (one batched FE solve)
FE_CHECK_DRAWS = 8


def fe_check(V: np.ndarray, y_obs: torch.Tensor, sigma: float) -> dict[str, Any]:
    """Does the FE itself fit where the surrogate posterior lies?

    A surrogate posterior can sit where the GP, not the FE, fits the data (a GP error in a
    region of large code variance soaks up the misfit). The FE at a few posterior draws shows
    it: if even the best of them misfits, the posterior is the surrogate's. (The marginal
    medians are no test point: for a weakly identified, curved posterior they can lie off the
    ridge where the model fits.)

    Args:
        V: ``(b, n_obs)`` FE outputs at ``b`` posterior draws, um (NaN rows: not converged);
        y_obs: ``(n_obs,)`` um; sigma: noise sd, um.
    Returns:
        ``{"chi2", "n", "rms_um", "rms_over_sigma", "draws", "ok"}`` of the best-fitting draw;
        ``ok`` is False when its RMS residual exceeds :data:`FE_CHECK_RMS` noise sd and its
        chi-square the :data:`FE_CHECK_QUANTILE` quantile of chi2(n) (or no draw converged).
    """
    from scipy.stats import chi2 as chi2_dist

    y = y_obs.detach().cpu().numpy()
    r = np.atleast_2d(np.asarray(V, float)) - y
    c2 = np.where(np.isfinite(r).all(1), ((r / sigma) ** 2).sum(1), np.inf)
    k = int(np.argmin(c2))
    n = int(y.size)
    rms = float(np.sqrt(c2[k] / n)) * sigma if np.isfinite(c2[k]) else float("nan")
    bad = not np.isfinite(c2[k]) or (rms > FE_CHECK_RMS * sigma
                                      and c2[k] > chi2_dist.ppf(FE_CHECK_QUANTILE, n))
    return {"chi2": float(c2[k]), "n": n, "rms_um": rms, "rms_over_sigma": rms / sigma,
            "draws": int(r.shape[0]), "ok": not bad}


def fe_anchor(solver: SpecimenSolver, setup: Setup, times: tuple[float, ...],
              ti: np.ndarray, oi: np.ndarray, y_obs: torch.Tensor, sigma: float, space: Box,
              n_fe: int, start: torch.Tensor, X: torch.Tensor, Y: torch.Tensor,
              obs_offset: Any = None, iters: int = 5, n_sd: float = 4.0,
              extra: np.ndarray | None = None, n_best_runs: int = 4,
              store: RunStore | None = None, cfg_hash: str | None = None) -> dict[str, Any]:
    """The FE's own best fit to the data, and the region around it where a refinement puts
    runs.

    A surrogate posterior can sit where the GP, not the FE, fits (a GP error that the code
    variance does not cover). Levenberg-Marquardt through the FE (:func:`solderpyro.fit.lm_fit`)
    from several starts at once (the posterior median, the ``n_best_runs`` stored runs that fit
    best, and ``extra``, e.g. posterior draws) finds where the exact model fits: the FE's
    chi-square can have several minima (a stress-free temperature trades off against s0: on
    the hidden-effect data, one at the truth and one at s0 = 8.5 MPa, 48 higher, behind a
    barrier of +840), and a single start finds the one its basin holds.

    Args:
        solver: set up for the FE-side effects; times, ti, oi: outputs and the observation
            index (:func:`observation_index`); y_obs: ``(n_obs,)`` um; sigma: noise sd, um.
        space: all calibrated parameters (FE-side first, ``n_fe`` of them, then
            observation-side); start: ``(space.dim,)`` posterior median.
        X, Y: ``(n_runs, n_fe)`` stored runs and ``(n_runs, n_obs)`` their outputs, um.
        obs_offset: ``q -> (n_obs,)`` additive observation effects (None: none).
        n_sd: half-width of the returned box in Laplace sd (at least 2 % of the box width).
        extra: ``(k, space.dim)`` more starts (physical units), or None.
        store, cfg_hash: keep the Levenberg-Marquardt's FE runs in the run store.
    Returns:
        ``{"x": (space.dim,) best fit, "chi2", "chi2_start": chi2 at the posterior median,
        "box": Box over the FE-side parameters, "cov_unit": (space.dim, space.dim) Laplace
        covariance on ``space``'s unit scale (log where flagged; a direction the data do not
        constrain gets a prior sd of half the box), "minima": [(chi2, x), ...] the distinct
        minima the starts reached, best first}``.
    """
    from solderpyro.fit import lm_fit

    y = y_obs.detach().cpu().numpy()
    lo, hi = np.array(space.lower, float), np.array(space.upper, float)

    def fun(rows: np.ndarray) -> np.ndarray:
        return fe_observed(solver, setup, times, ti, oi, rows, n_fe, obs_offset, store, cfg_hash)

    s0 = start.detach().cpu().numpy().astype(float)
    starts = [s0]
    c2 = (((Y - y_obs) / sigma) ** 2).sum(1)
    for i in torch.argsort(c2)[:n_best_runs].tolist():
        s1 = s0.copy()
        s1[:n_fe] = X[i].detach().cpu().numpy()
        starts.append(s1)
    if extra is not None:
        starts += [np.clip(np.asarray(r, float), lo, hi) for r in np.atleast_2d(extra)]
    fits = lm_fit(fun, np.stack(starts), lo, hi, y, sigma, iters=iters)
    order = sorted(range(len(fits)), key=lambda k: fits[k].chi2)
    best = fits[order[0]]
    minima: list[tuple[float, list[float]]] = []
    w = hi - lo
    for k in order:  # distinct minima: 2 % of the box apart in some coordinate
        f = fits[k]
        if np.isfinite(f.chi2) and all((np.abs(f.x - np.array(m[1])) / w).max() > 0.02
                                       for m in minima):
            minima.append((float(f.chi2), f.x.tolist()))
    sd = np.maximum(best.laplace_sd(lo, hi, sigma), 0.02 * (hi - lo))[:n_fe]
    x_fe = best.x[:n_fe]
    box = Box(space.names[:n_fe], tuple(np.maximum(x_fe - n_sd * sd, lo[:n_fe]).tolist()),
              tuple(np.minimum(x_fe + n_sd * sd, hi[:n_fe]).tolist()),
              space.log_scale[:n_fe], space.units[:n_fe])
    return {"x": best.x, "chi2": float(best.chi2), "chi2_start": float(fits[0].history[0]),
            "box": box, "cov_unit": laplace_cov_unit(best, space, sigma), "minima": minima}


def laplace_cov_unit(fit: Any, space: Box, sigma: float) -> np.ndarray:
    """Laplace covariance ``(space.dim, space.dim)`` of an :class:`~solderpyro.fit.LMFit` on
    ``space``'s unit scale (log where flagged): ``(J_u' J_u / sigma^2 + 4 I)^-1``, the ``4 I``
    a prior sd of half the box so that a direction the data do not constrain spans the box.

    Args:
        fit: with ``J (n_obs, dim)``, df/du on the linear unit scale, um (None: the prior).
        sigma: noise sd, um.
    """
    p = space.dim
    if fit.J is None or fit.J.shape[1] != p:
        return np.eye(p) * 0.25
    J = fit.jacobian_unit(space.lower, space.upper, space.log_scale)
    return np.linalg.inv(J.T @ J / sigma**2 + 4.0 * np.eye(p))


def local_region(space: Box, center: np.ndarray, cov_unit: np.ndarray, half: float
                 ) -> LocalBox:
    """The +-``half`` sd parallelepiped (:class:`~solderpyro.params.LocalBox`) of
    ``N(center, cov_unit)`` inside ``space`` (center physical, ``(dim,)``; ``cov_unit`` on
    ``space``'s unit scale, ``(dim, dim)``); the covariance is symmetrised and its eigenvalues
    floored at 1e-12 so a near-singular Laplace covariance still gives a valid region."""
    c = 0.5 * (cov_unit + cov_unit.T)
    ev, V = np.linalg.eigh(c)
    c = (V * np.maximum(ev, 1e-12)) @ V.T
    return LocalBox.gaussian(space, np.clip(center, space.lower, space.upper),
                             torch.tensor(c), half)


def region_faces(region: LocalBox, t: torch.Tensor, edge: float = 0.02,
                 share: float = 0.005) -> list[int]:
    """Directions ``k`` of ``region`` whose faces the draws ``t (n, dim)`` (physical) reach:
    more than ``share`` of them within ``edge`` of ``u_k = 0`` or ``1``."""
    u = region.to_unit(t.to(torch.float64))
    near = (u < edge) | (u > 1.0 - edge)
    return [k for k in range(region.dim) if float(near[:, k].double().mean()) > share]


def region_design(region: LocalBox, n: int, seed: int) -> torch.Tensor:
    """``(n, dim)`` FE runs (physical) spread over ``region`` and inside its prior box.

    A Latin hypercube on the parallelepiped, with the points outside the prior box dropped
    (clipping them instead would move them many sd along the thin directions, out of the
    region the GP serves); the hypercube is enlarged until ``n`` remain, and ``n`` are taken
    at random (seeded) when more do.
    """
    outer = region.outer
    m = n
    for _ in range(12):
        u = torch.as_tensor(qmc.LatinHypercube(d=region.dim, seed=seed).random(m))
        x = region.from_unit(u)
        v = outer.to_unit(x)
        inside = ((v >= 0.0) & (v <= 1.0)).all(1)
        if int(inside.sum()) >= n:
            x = x[inside]
            keep = np.sort(np.random.default_rng(seed).choice(len(x), n, replace=False))
            lo = torch.tensor(outer.lower, dtype=x.dtype)
            hi = torch.tensor(outer.upper, dtype=x.dtype)
            return torch.minimum(torch.maximum(x[keep], lo), hi)  # rounding at log bounds
        m = int(np.ceil(1.5 * m * n / max(int(inside.sum()), 1)))
    raise RuntimeError(f"the local region holds too little of the prior box to place {n} "
                       f"runs in it (centre {region.center}): widen --local-sd")


def _box_text(box: Box) -> str:
    """``"s0 5-11.8, QR 7476-1.3e+04, ..."``: a box's bounds for the log."""
    return ", ".join(f"{n} {a:.4g}-{b:.4g}"
                     for n, a, b in zip(box.names, box.lower, box.upper, strict=True))


def marginal_region(region: LocalBox, n: int) -> LocalBox:
    """The first ``n`` coordinates' region: the marginal of ``region``'s Gaussian."""
    B = torch.tensor(region.basis, dtype=torch.float64)
    cov = (B @ B.T)[:n, :n]
    outer = Box(region.names[:n], region.outer.lower[:n], region.outer.upper[:n],
                region.outer.log_scale[:n], region.outer.units[:n])
    ctr = region.outer.from_unit(torch.tensor(region.center, dtype=torch.float64))[:n]
    return LocalBox.gaussian(outer, ctr.tolist(), cov, 1.0)


def calibrate_specimen(setup: Setup, meas: Measurements, out: str | Path, n_runs: int = 50,
                       seed: int = 0, store_root: str | Path = "runs/store",
                       batch_size: int = 64, nuts: dict[str, Any] | None = None,
                       progress: bool = True, kernel: str = "gaussian", ard: bool = True,
                       mean: str = "constant", output: str = "pca", exact: int = 0,
                       record: dict[str, Any] | None = None, refine: int = 0,
                       refine_rounds: int = 1, inputs: str = "raw", inputs_T_C: float = 125.0,
                       inputs_rate: float = 1e-5, local: bool = False,
                       local_sd: float = 3.5, exact_rounds: int = 3,
                       exact_profile: int = 9, profile_ci: bool = False
                       ) -> SpecimenCalibration:
    """Calibrate ``setup.space`` (default s0, QR, xi, m) against ``meas``.

    Args:
        setup: typed problem, parameter box and defaults (see :mod:`solderpyro.configure`).
        meas: measurements; times and points must be model outputs (A, B, grid labels).
        out: run directory (created). n_runs: LHS size (the seed: 50).
        store_root: the run store shared by calibrations of the same problem.
        nuts: options of :func:`~solderpyro.calibration.mcmc.run_nuts`.
        kernel, ard, mean: the GP surrogate's settings (see :class:`GPSurrogate`).
        output: ``"pca"`` (GPs on principal components of the observed outputs: surrogate
            errors correlated across outputs, as the FE's are) or ``"batched"`` (one GP per
            output; a single observed output always uses it).
        exact: if > 0, sample the FE-exact posterior (:func:`fe_exact`, no surrogate in the
            likelihood): ``exact_rounds`` rounds of adaptive importance sampling with
            ``exact`` FE runs each, from a proposal built on the surrogate posterior, the FE's
            best fit and an ``exact_profile``-point chi-square profile along the ridge (0: no
            profile). Writes ``exact_posterior.csv`` (FE-exact vs surrogate quantiles) and
            ``exact_samples.npz``; when the weights are reliable (Pareto k-hat <= 0.7, ESS >=
            50), ``summary.csv``, ``draws.npz`` and the predictive are the FE-exact posterior's
            and the surrogate's summary moves to ``summary_surrogate.csv``. A parameter whose
            FE-exact interval spans >= :data:`WEAK_SHARE` of its box is reported with the
            measurement that would narrow it (:func:`identifiability`).
        profile_ci: with ``exact``, 95 % profile-likelihood confidence intervals of every
            calibrated parameter through the FE (:func:`solderpyro.exact.profile_intervals`,
            started from the FE-exact samples, with the noise sd the data state, else the
            posterior median's; every FE run kept in the store): written to
            ``profile_ci.csv`` (with the posterior's interval beside) and run.json.
        record: how the run was asked for (e.g. ``{"overrides": [...]}``), kept in
            ``run.json`` so that ``solderpyro diagnose`` can rebuild the model.
        refine: FE runs added per refinement round: half a Latin hypercube around the FE's
            own best fit (:func:`fe_anchor`: Levenberg-Marquardt through the FE, +- 4 Laplace
            sd), half over the region the posterior occupies (its 0.5-99.5 % range widened by
            half its width); inside the prior box; the surrogate is refitted on all runs and
            NUTS rerun. 0: none.
        refine_rounds: how many such rounds.
        local: with ``refine``, each round samples a local region instead of the whole box:
            the +-``local_sd`` sd parallelepiped of a Gaussian around the FE's best fit
            (multi-start Levenberg-Marquardt through the FE, Laplace covariance; later rounds:
            the previous posterior's median and covariance, its sd widened 1.5x if it
            reached the region's faces), aligned with the posterior's principal directions. All
            ``refine`` runs go there (a Latin hypercube on the parallelepiped), a GP on the
            runs in and near it (whitened inputs) replaces the global one, and the prior is
            truncated to it. For many observations (full-field data), where a global GP's
            error of a few hundredths of a um costs thousands of nats and its code variance
            in far corners soaks up misfit; the FE check shows whether the region holds a
            fit, and a warning names directions whose faces the last posterior reaches.
        local_sd: the region's half-width in sd.
        inputs: ``"raw"`` (the GP sees the box's unit cube) or ``"flow_stress"`` (s0 and QR
            replaced by the log flow stresses at ``inputs_T_C`` degC and ``inputs_rate`` 1/s,
            :class:`~solderpyro.surrogate.features.FlowStressInputs`; 4.7x smaller held-out
            error at 50 runs on the reference case, docs/calibration.md).

    Returns:
        :class:`SpecimenCalibration`; writes summary.csv, posterior.nc, figures, report.md.
    """
    if local and refine < 1:
        raise ValueError("calibrate_specimen: local=True needs refine > 0 (the FE runs placed "
                         "in the local region)")
    if not local_sd > 0:
        raise ValueError(f"calibrate_specimen: local_sd must be > 0, got {local_sd}")
    if profile_ci and exact <= 0:
        raise ValueError("calibrate_specimen: profile_ci=True needs exact > 0 (the profiles "
                         "start from the FE-exact posterior's samples)")
    if exact < 0 or exact == 1 or exact_rounds < 1 or exact_profile < 0 or exact_profile == 1:
        raise ValueError(f"calibrate_specimen: need exact = 0 or >= 2, exact_rounds >= 1 and "
                         f"exact_profile = 0 or >= 2, got exact={exact}, exact_rounds="
                         f"{exact_rounds}, exact_profile={exact_profile}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    timing: dict[str, float] = {}  # seconds per stage, into run.json and the log
    clock = [time.perf_counter()]

    def stage(name: str) -> None:
        now = time.perf_counter()
        timing[name] = round(timing.get(name, 0.0) + now - clock[0], 2)
        log.info("stage %s: %.1f s", name, now - clock[0])
        clock[0] = now

    if len(meas) == 0:
        raise ValueError("the measurement file has no rows")
    field = any(p not in setup.problem.points for p in meas.points())
    times = tuple(float(t) for t in meas.times())
    fx, fx_fe, fx_obs = split_effects(setup, times)
    solver = SpecimenSolver(setup.problem, reference_grid() if field else None,
                            dtype=setup.dtype, device=setup.device, effects=fx_fe or ())
    store = RunStore(store_root)
    h = store.register(setup.problem, times, field, setup.dtype, effects=fx_fe or ())
    gp_box = calibration_box(setup, fx_fe)  # what the FE runs and the surrogate vary
    space = calibration_box(setup, fx)  # ... plus observation-side effects (no FE needed)
    theta = lhs(gp_box, n_runs, seed)  # (n_runs, n_fe)
    liu = anand_tensor({}, base=LIU2008, dtype=torch.float64)[None]
    if fx_fe is not None:  # the literature run with every effect off
        liu = torch.cat([liu, torch.tensor([fx_fe.off], dtype=torch.float64)], 1)
    params = torch.cat([fe_params(setup, theta), liu])  # the literature run rides along
    log.info("DOE: %d LHS runs over %s + the Liu 2008 constants", n_runs, ", ".join(space.names))
    if fx is not None:
        log.info("effects on: %s (parameters %s)", ", ".join(fx.keys), ", ".join(fx.names))
    doe = run_doe(solver, store, h, params, times, batch_size, progress)
    stage("doe")
    ti, oi = observation_index(meas, doe.times, doe.names)
    y_sim = doe.V[:, ti, oi]  # (n_runs + 1, n_obs)
    y_liu = y_sim[-1]
    ok = doe.ok[:n_runs]
    if int(ok.sum()) < max(5, gp_box.dim + 2):
        raise RuntimeError(f"only {int(ok.sum())} of {n_runs} FE runs converged: "
                           f"{sorted(set(r for r in doe.reasons if r))[:3]}")
    y_obs = torch.tensor(np.array(meas.value_um), dtype=torch.float64)
    if output not in ("pca", "batched"):
        raise ValueError(f"calibrate_specimen output must be 'pca' or 'batched', got {output!r}")
    output = output if y_obs.shape[0] > 1 else "batched"
    log.info("surrogate: %s GP on %d runs, %d observed outputs", output, int(ok.sum()),
             y_obs.shape[0])
    from solderpyro.surrogate.features import input_map

    feats = input_map(inputs, gp_box, setup.space.defaults, inputs_T_C, inputs_rate)
    if feats is not None:
        log.info("surrogate: %s", feats.describe())
    gopts: dict[str, Any] = dict(output=output, kernel=kernel, ard=ard, mean=mean, inputs=feats)
    gp = GPSurrogate(gp_box, **gopts)
    gp.fit(theta[ok], y_sim[:n_runs][ok])
    loo = gp.loo()
    stage("surrogate")
    problems = gp.check(loo)
    sig = meas.sigma_um[np.isfinite(meas.sigma_um)]
    yr = float(y_obs.max() - y_obs.min())
    if sig.size == len(meas) and sig.size:  # the file states the noise: use it
        pr = Priors(sigma_known=float(np.median(sig)))
        log.info("noise: sigma_um from the data (%.3g um), known to ~10 %%", pr.sigma_known)
    else:
        pr = Priors(sigma_max=max(10 * float(sig.max()) if sig.size else 0.0, 0.5 * yr, 1e-3))
    # chains start at likelihood-resampled prior draws: the specimen posterior can have minor
    # modes (the demo's data: one at m = 0.49) that a chain started at random never leaves
    nk: dict[str, Any] = dict(chains=4, warmup=500, draws=1000, seed=seed, progress=progress,
                              init="sir")
    nk.update(nuts or {})
    log.info("NUTS: %d chains x %d draws (modular KOH, code uncertainty from the GP)",
             nk["chains"], nk["draws"])
    # additive observation effects, applied after the surrogate (and after the FE in fe_anchor)
    obs_off = None if fx_obs is None else observation_offset(
        fx_obs, setup.problem, doe.names, len(doe.times), ti, oi)

    def emulate(gp: GPSurrogate) -> Any:
        if obs_off is None:
            return GPEmulator(gp)
        return ObservedEmulator(GPEmulator(gp), gp_box.dim, obs_off)

    post, inp = calibrate_emulator(emulate(gp), y_obs, space, priors=pr, **nk)
    stage("posterior")
    X, Y, okk = theta, y_sim[:n_runs], ok
    fe_fit: dict[str, Any] | None = None
    region: LocalBox | None = None
    local_info: dict[str, Any] = {}
    for rnd in range(refine_rounds if refine > 0 else 0):
        tf = post.flat("t")
        sig = pr.sigma_known or float(post.flat("sigma").median())
        if local and region is not None:  # later local rounds: the last posterior's shape
            faces = region_faces(region, tf)
            u = space.to_unit(tf.to(torch.float64)).numpy()
            cov = np.cov(u.T).reshape(space.dim, space.dim) * (1.5**2 if faces else 1.0)
            region = local_region(space, tf.median(0).values.numpy(), cov, local_sd)
            log.info("refine round %d: local region from the last posterior (faces reached "
                     "along %s)", rnd + 1, faces or "none")
        else:
            pick = np.linspace(0, len(tf) - 1, 3).round().astype(int)
            fe_fit = fe_anchor(solver, setup, times, ti, oi, y_obs, sig, space, gp_box.dim,
                               tf.median(0).values, X[okk], Y[okk], obs_offset=obs_off,
                               iters=8 if local else 5,
                               extra=tf[pick].numpy() if local else None,
                               n_best_runs=4 if local else 1)
            log.info("refine round %d: FE chi2 at the posterior median %.1f, the FE's best "
                     "fit %.1f (n = %d)", rnd + 1, fe_fit["chi2_start"], fe_fit["chi2"],
                     len(y_obs))
            if len(fe_fit["minima"]) > 1:
                log.info("refine round %d: the FE's chi2 has %d distinct minima from the "
                         "starts: %s", rnd + 1, len(fe_fit["minima"]),
                         ", ".join(f"{c:.1f}" for c, _ in fe_fit["minima"]))
            if local:
                region = local_region(space, fe_fit["x"], fe_fit["cov_unit"], local_sd)
        if local:
            assert region is not None
            reg_fe = marginal_region(region, gp_box.dim)
            th_new = region_design(reg_fe, refine, seed + 1 + rnd)
            log.info("refine round %d: %d FE runs in the +-%g sd region around %s (bounding "
                     "box %s)", rnd + 1, refine, local_sd, ", ".join(
                         f"{n}={v:.4g}" for n, v in zip(space.names, region.outer.from_unit(
                             torch.tensor(region.center)).tolist(), strict=True)),
                     _box_text(reg_fe))
        else:
            assert fe_fit is not None
            th_new = torch.cat([
                lhs(fe_fit["box"], refine // 2, seed + 1 + rnd),
                lhs(_posterior_region(tf[:, :gp_box.dim], gp_box), refine - refine // 2,
                    seed + 101 + rnd)])
            log.info("refine round %d: %d FE runs around the FE's best fit (%s) and %d where "
                     "the posterior lies", rnd + 1, refine // 2, _box_text(fe_fit["box"]),
                     refine - refine // 2)
        d2 = run_doe(solver, store, h, fe_params(setup, th_new), times, batch_size, progress)
        X, Y = torch.cat([X, th_new]), torch.cat([Y, d2.V[:, ti, oi]])
        okk = torch.cat([okk, d2.ok])
        if local:
            assert region is not None
            # the runs in and near the region (a margin of a quarter of its width)
            ur = reg_fe.to_unit(X)
            near = okk & ((ur > -0.25) & (ur < 1.25)).all(1)
            gp = GPSurrogate(reg_fe, **{**gopts, "inputs": None})
            gp.fit(X[near], Y[near])
            log.info("refine round %d: local GP on %d runs (whitened inputs)", rnd + 1,
                     int(near.sum()))
            fit_space: Box = region
        else:
            gp = GPSurrogate(gp_box, **gopts)
            gp.fit(X[okk], Y[okk])
            fit_space = space
        loo = gp.loo()
        problems = gp.check(loo)
        # the same box: start from the last posterior's positions and mass matrix
        post, inp = calibrate_emulator(emulate(gp), y_obs, fit_space, priors=pr,
                                       **(nk if local else {**nk, "warm": post.warm}))
        stage("refine")
    if region is not None:
        faces = region_faces(region, post.flat("t"))
        local_info = {"local_region": {
            "center": region.outer.from_unit(torch.tensor(region.center)).tolist(),
            "half_width_sd": local_sd, "basis_unit": [list(b) for b in region.basis],
            "bounding_lower": list(region.lower), "bounding_upper": list(region.upper),
            "faces_reached": [int(k) for k in faces]}}
        if fe_fit is not None:
            local_info["fe_minima"] = fe_fit["minima"]
        if faces:
            msg = (f"the posterior reaches the faces of the local region along {len(faces)} "
                   f"of its {region.dim} directions ({faces}): the prior truncation there "
                   f"may cut posterior mass; add a --refine-rounds round (the next region "
                   f"widens along them) or raise --local-sd")
            log.warning(msg)
            problems = [*problems, msg]
    # the FE at a few posterior draws: does the exact model fit where the surrogate says so?
    sig_fe = pr.sigma_known or float(post.flat("sigma").median())
    draws = post.flat("t").detach().cpu().numpy()
    pick = np.linspace(0, len(draws) - 1, min(FE_CHECK_DRAWS, len(draws))).round().astype(int)

    def fe_fun(rows: np.ndarray) -> np.ndarray:  # every run kept in the run store
        return fe_observed(solver, setup, times, ti, oi, rows, gp_box.dim, obs_off, store, h,
                           batch_size)

    V_chk = fe_fun(draws[pick])
    chk = fe_check(V_chk, y_obs, sig_fe)
    stage("fe_check")
    log.info("FE check: best RMS residual of the FE over %d posterior draws %.4g um (%.2f "
             "noise sd)", chk["draws"], chk["rms_um"], chk["rms_over_sigma"])
    if not chk["ok"]:
        msg = (f"the FE itself misfits at every one of {chk['draws']} posterior draws: best "
               f"RMS residual {chk['rms_um']:.3g} um = {chk['rms_over_sigma']:.1f} noise sd "
               f"(chi2 {chk['chi2']:.0f} on {chk['n']} values): the posterior sits where the "
               f"surrogate, not the FE, fits; do not trust its intervals ("
               + ("more rounds, or a wider --local-sd" if local and refine else
                  "for full-field data: --refine 40 --local --refine-rounds 2; else more "
                  "runs or --refine") + "; --exact samples the FE's own posterior)")
        log.warning(msg)
        problems = [*problems, msg]
    rows = [r for r in post.summary()]
    order = list(setup.space.names) + ["sigma"] + list(space.names[setup.space.n_theta:])
    rows.sort(key=lambda r: order.index(r["parameter"]) if r["parameter"] in order else 99)
    post.save(out / "posterior.nc")
    bands = predict_observation_model(post, inp, None, seed=seed)
    from solderpyro import report

    def write_all(rows: list[dict], bands: Any, problems: list[str], ex: Any = None,
                  ex_info: dict[str, Any] | None = None, ex_rows: list[dict] | None = None
                  ) -> None:
        """summary.csv, draws.npz, run.json and the report (the FE-exact posterior's where
        ``ex`` is reliable); written before the FE-exact step and again after it."""
        saved = (ex.theta, ex.sigma) if ex is not None and ex.reliable else None
        write_summary(rows, out / "summary.csv", SUMMARY)
        save_run(out, meas, space, fx.keys if fx is not None else (), post, bands, y_obs,
                 y_liu, pr,
                 {**(record or {}), "n_runs": n_runs, "seed": seed, "store": str(store_root),
                  "kernel": kernel, "ard": ard, "mean": mean, "surrogate_output": output,
                  "surrogate_inputs": inputs, **({"inputs_T_C": inputs_T_C,
                                                   "inputs_rate": inputs_rate} if feats else {}),
                  "loo_rmse_rel": float(loo.rmse_rel), "loo_coverage95": float(loo.coverage95),
                  "fe_check": chk, **local_info, "timing_s": timing,
                  "posterior": "fe-exact" if saved is not None else "surrogate",
                  **({"exact": ex_info} if ex_info else {}),
                  **({"fe_best_fit": {"x": fe_fit["x"].tolist(), "chi2": fe_fit["chi2"],
                                      "chi2_at_posterior_median": fe_fit["chi2_start"]}}
                     if fe_fit is not None else {})}, draws=saved)
        notes = [f"FE check: the FE at {chk['draws']} posterior draws (one batched solve), "
                 f"best RMS residual {chk['rms_um']:.3g} um = {chk['rms_over_sigma']:.2f} "
                 f"noise sd (chi2 {chk['chi2']:.0f} on {chk['n']} values)"]
        if saved is not None and ex_info:
            notes.insert(0, f"**posterior: FE-exact** (adaptive importance sampling with the FE "
                            f"in the likelihood, {ex_info['fe_runs']} FE runs, ESS "
                            f"{ex_info['ess']:.0f}, Pareto k-hat {ex_info['khat']:.2f}); the "
                            f"surrogate's is in summary_surrogate.csv")
        ident = (ex_info or {}).get("identifiability") or {}
        if saved is not None and ident.get("weak"):
            notes.append("weakly identified by these data (95 % interval over >= "
                         f"{WEAK_SHARE:.0%} of the prior box): "
                         + ", ".join(v["parameter"] for v in ident["weak"])
                         + "; see 'Identifiability' below for the measurement that would "
                         "narrow them")
        if region is not None:
            assert local_info
            notes.append(
                f"local region (--local): the prior truncated to the +-{local_sd:g} sd "
                f"parallelepiped of a Gaussian around " + ", ".join(
                    f"{n} = {v:.4g}" for n, v in zip(space.names,
                                                     local_info["local_region"]["center"],
                                                     strict=True))
                + "; the surrogate is a GP on the runs in and near it")
        if fe_fit is not None and len(fe_fit["minima"]) > 1:
            notes.append("the FE's chi-square has several minima from the Levenberg-Marquardt "
                         "starts: " + ", ".join(f"{c:.1f}" for c, _ in fe_fit["minima"][:5])
                         + " (the best anchors the refinement)")
        report.write(out, meas, rows, post, loo, problems, bands, y_liu, doe, ti, oi, nk,
                     ex_rows, notes,
                     exact=(ex, ex_info, draws, space) if ex is not None else None)

    write_all(rows, bands, problems)  # the surrogate's results are safe before the FE-exact step
    if exact > 0:
        log.info("exact: the FE-exact posterior, %d rounds of %d FE runs after a best fit%s",
                 exact_rounds, exact, f" and a {exact_profile}-point profile"
                 if exact_profile >= 2 else "")
        c2 = np.nansum((V_chk - y_obs.numpy()) ** 2, 1)
        c2[~np.isfinite(V_chk).all(1)] = np.inf
        starts = draws[pick][np.argsort(c2)[:2]]
        if fe_fit is not None:
            starts = np.vstack([starts, fe_fit["x"][None]])
        from solderpyro.coords import sampling_coords

        coords = sampling_coords(space, setup.space.defaults, "auto", inputs_T_C, inputs_rate)
        try:
            ex, ex_info = fe_exact(fe_fun, coords, y_obs, pr, draws, starts, exact,
                                   exact_rounds, exact_profile, seed, len(draws))
        except RuntimeError as err:  # keep the surrogate's results (and the stored runs)
            log.warning("the FE-exact posterior failed: %s", err)
            write_all(rows, bands, [*problems, f"the FE-exact posterior failed: {err}"])
        else:
            ex_rows = exact_rows(ex, rows)
            np.savez(out / "exact_samples.npz", w=ex.result.u, theta=ex.samples,
                     log_target=ex.result.log_target,
                     log_q=ex.result.log_q, round=ex.result.round,
                     weights=ex.result.weights(), names=np.array(space.names))
            write_summary(ex_rows, out / "exact_posterior.csv", tuple(ex_rows[0]))
            if ex.reliable:
                write_summary(rows, out / "summary_surrogate.csv", SUMMARY)
                by = {r["parameter"]: r for r in ex.rows}
                rows = [{**by[r["parameter"]], "r_hat": float("nan"),
                         "ess_bulk": ex_info["ess"], "ess_tail": ex_info["ess"]} for r in rows]
                try:  # which parameters lie along a ridge, and what would narrow them
                    ex_info["identifiability"] = identifiability(
                        setup, fx.keys if fx is not None else (), space, rows, ex, meas,
                        float(pr.sigma_known or np.median(ex.sigma)))
                except Exception as err:  # advisory: never lose the run's files over it
                    log.warning("identifiability not computed", exc_info=True)
                    ex_info["identifiability"] = {"weak": [], "advice": "identifiability not "
                                                  f"computed: {err!r}"}
                log.info("identifiability: %s", ex_info["identifiability"]["advice"])
                gen = torch.Generator().manual_seed(seed)
                Vt, st = torch.as_tensor(ex.V), torch.as_tensor(ex.sigma)
                bands = Bands(Vt, Vt + st[:, None] * torch.randn(
                    Vt.shape, generator=gen, dtype=Vt.dtype), st)
                log.info("exact: reliable (ESS %.0f, k-hat %.2f): summary.csv, draws.npz and "
                         "the predictive are the FE-exact posterior's", ex_info["ess"],
                         ex_info["khat"])
            else:
                msg = (f"the FE-exact posterior is not reliable (ESS {ex_info['ess']:.0f}, "
                       f"Pareto k-hat {ex_info['khat']:.2f}; needs k-hat <= 0.7 and ESS >= "
                       f"50): summary.csv stays the surrogate's; more --exact-rounds or a "
                       f"larger --exact")
                log.warning(msg)
                problems = [*problems, msg]
            if profile_ci:
                write_all(rows, bands, problems, ex, ex_info, ex_rows)  # safe before the profiles
                # the noise sd the data state (as the FE check), else the posterior's
                sig_p = float(pr.sigma_known or np.median(ex.sigma))
                log.info("profile CI: 95 %% profile-likelihood intervals of %d parameters "
                         "through the FE (sigma %.4g um)", space.dim, sig_p)
                from solderpyro.exact import profile_intervals

                try:
                    pci = profile_intervals(fe_fun, space, y_obs.numpy(), sig_p, ex.samples,
                                            np.asarray(ex.result.extra["ssr"], float))
                except (RuntimeError, ValueError) as err:
                    log.warning("the profile-likelihood intervals failed: %s", err)
                    problems = [*problems, f"the profile-likelihood intervals failed: {err}"]
                else:
                    ex_info["profile_ci"] = [p.as_dict() for p in pci]
                    ex_info["profile_ci_sigma_um"] = sig_p
                    by = {r["parameter"]: r for r in rows}
                    pci_rows = [{"parameter": p.parameter, "lower": p.lower, "upper": p.upper,
                                 "at_lower_bound": str(p.at_lower_bound).lower(),
                                 "at_upper_bound": str(p.at_upper_bound).lower(),
                                 "truncated": str(p.truncated).lower(),
                                 "posterior_q2.5": by[p.parameter]["q2.5"],
                                 "posterior_q97.5": by[p.parameter]["q97.5"]} for p in pci]
                    write_summary(pci_rows, out / "profile_ci.csv", tuple(pci_rows[0]))
                    for p in pci:
                        log.info("profile CI: %s in [%.4g, %.4g]%s", p.parameter, p.lower,
                                 p.upper, " (reaches the box's bound)"
                                 if p.at_lower_bound or p.at_upper_bound else "")
            write_all(rows, bands, problems, ex, ex_info, ex_rows)
    print(format_summary(rows))
    stage("report")
    info = json.loads((out / "run.json").read_text())
    info["timing_s"] = timing
    (out / "run.json").write_text(json.dumps(info, indent=2, default=str) + "\n")
    return SpecimenCalibration(out, post, rows, loo, int(ok.sum()), int((~ok).sum()))
