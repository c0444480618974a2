"""The FE-exact posterior: adaptive importance sampling with the FE itself in the likelihood.

A surrogate posterior is only as good as the surrogate where the posterior lies. With full-field
data (2240 values) a GP error of a few thousandths of a um moves the chi-square by ~10 nats,
and when the FE's own chi-square is flat along a ridge (a stress-free temperature or a back
stress traded against s0, Q/R and xi) that is enough to put the surrogate posterior on the
wrong piece of the ridge, with intervals that miss the truth although the model fits. This
module samples the posterior of the FE itself, with no surrogate in the likelihood:

1. **Sampling coordinates** (:mod:`solderpyro.exact.coords`) in which the posterior is close to
   Gaussian: flow stresses instead of s0 and Q/R where the box allows it.
2. **A proposal that covers the posterior** (:func:`initial_proposal`), a mixture of
   - the surrogate posterior's draws (a Gaussian mixture fitted to them, widened),
   - the FE's best fit with its Laplace covariance (widened), and
   - the **profile of the FE's chi-square along the ridge** (:func:`fe_profile`): the
     coordinate that the weakest Laplace direction moves most is fixed at a grid of values
     (extended while the chi-square stays low) and the others refitted by one batched
     Levenberg-Marquardt; a spline through the fits carries components that follow the
     ridge (:func:`ridge_mixture`), weighted by their Laplace mass.
3. **AMIS rounds** (:func:`solderpyro.exact.amis.amis`) with the exact likelihood, the
   noise sd integrated out under the calibration's own prior
   (:func:`~solderpyro.exact.amis.log_marginal_sigma`). ``fun`` evaluates the FE (one
   batched solve per round; the specimen calibration routes it through the run store).
4. **Reliability**: the Kish ESS and the Pareto k-hat of the weights
   (:attr:`~solderpyro.exact.amis.AMISResult.reliable`).

Everything here is generic over ``fun: rows (b, dim) -> (b, n_obs)`` (physical parameters in,
model outputs in um out, NaN rows where the model failed) and a box with a flat prior on its
unit cube (logarithmic where flagged), as in the KOH calibration.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from solderpyro.calibration.intervals import (
    likelihood_hull,
    weighted_quantiles,
    with_intervals,
    with_monte_carlo_error,
)
from solderpyro.exact.amis import (
    AmisOptions,
    AMISResult,
    TMixture,
    amis,
    log_marginal_sigma,
    weighted_em,
)
from solderpyro.exact.coords import UnitCoords
from solderpyro.params import Box

Fun = Callable[[np.ndarray], np.ndarray]


@dataclass
class Profile:
    """The FE's chi-square profiled along one sampling coordinate.

    Attributes:
        coord: index of the profiled coordinate (one the coordinates pass through unchanged
            from the unit cube, so that holding it fixed holds a parameter fixed).
        c: ``(G,)`` its grid values (ascending).
        x: ``(G, dim)`` the fits, physical units; w: ``(G, dim)`` the same in sampling
            coordinates.
        chi2: ``(G,)`` their chi-square (inf where the model failed).
        cov: ``(G, dim - 1, dim - 1)`` Laplace covariance of the other sampling coordinates
            given the profiled one (NaN where no Jacobian was available).
    """

    coord: int
    c: np.ndarray
    x: np.ndarray
    w: np.ndarray
    chi2: np.ndarray
    cov: np.ndarray


def laplace_cov_w(J_u: np.ndarray, coords: UnitCoords, x: np.ndarray, sigma: float,
                  free: np.ndarray | None = None) -> np.ndarray:
    """Laplace covariance in sampling coordinates from a Jacobian on the unit scale.

    ``df/dw_k = sum_l df/du_l (dw/du)^-1_lk``; with ``free`` (the fitted parameters, the
    others held) only the free columns of ``J_u`` exist and ``dw/du`` is taken on them
    (a held coordinate must pass through, so its ``u`` does not move with the free ``w``).

    Args:
        J_u: ``(n_obs, len(free))`` df/du, um; x: ``(dim,)`` the point (physical); sigma: um.
    Returns:
        ``(len(free), len(free))`` ``(J_w' J_w / sigma^2 + 4 I)^-1`` (the ``4 I`` bounds a
        direction the data do not constrain).
    """
    d = coords.dim
    fr = np.arange(d) if free is None else np.asarray(free)
    D = coords.jac(np.asarray(x, float))[np.ix_(fr, fr)]
    J_w = J_u @ np.linalg.inv(D)
    return np.linalg.inv(J_w.T @ J_w / sigma**2 + 4.0 * np.eye(len(fr)))


def profile_coordinate(cov: np.ndarray, candidates: tuple[int, ...] | None = None) -> int:
    """The coordinate the weakest direction of a ``(dim, dim)`` covariance moves most:
    ``argmax |v_k|`` of its leading eigenvector over ``candidates`` (default all)."""
    ev, V = np.linalg.eigh(0.5 * (cov + cov.T))
    cand = list(range(len(cov))) if candidates is None else list(candidates)
    return int(cand[int(np.argmax(np.abs(V[cand, -1])))])


@dataclass(frozen=True)
class ProfileOptions:
    """The tuning of :func:`fe_profile`.

    Attributes:
        n_grid: the first grid's points (at least 2).
        iters: Levenberg-Marquardt iterations per fit (2 batched calls each).
        n_sd: the first grid's half-width, Laplace sd of the profiled coordinate.
        extend_chi2: an end of the profile within this chi-square of its minimum is extended.
        max_extend: the most extensions.
    """

    n_grid: int = 9
    iters: int = 5
    n_sd: float = 4.0
    extend_chi2: float = 20.0
    max_extend: int = 4


def fe_profile(fun: Fun, coords: UnitCoords, x_best: np.ndarray, cov_w: np.ndarray,
               y: np.ndarray, sigma: float, options: ProfileOptions = ProfileOptions(),
               coord: int | None = None) -> Profile:
    """Profile the chi-square along the weakest direction's coordinate.

    The grid first spans ``+-options.n_sd`` Laplace sd of that coordinate around the best fit
    (inside the box); each grid point starts from the Laplace conditional mean of the others,
    and one batched Levenberg-Marquardt (:func:`solderpyro.exact.fit.lm_fit`) refits them all.
    A ridge can reach much farther than the Laplace sd says (a curved ridge, a flat one), so
    while an end of the profile is within ``options.extend_chi2`` of its minimum and not at
    the box's bound, two more points are added beyond it (each step 1.5x the last spacing),
    started by extrapolating the ridge, and refitted in one more batched fit (at most
    ``options.max_extend`` times).

    Args:
        fun: ``rows (b, dim) -> (b, n_obs)`` model outputs, um.
        coords: sampling coordinates (:mod:`solderpyro.exact.coords`) of the box.
        x_best: ``(dim,)`` the best fit, physical; cov_w: ``(dim, dim)`` its Laplace
            covariance in sampling coordinates (:func:`laplace_cov_w`).
        y: ``(n_obs,)`` data, um; sigma: noise sd, um.
        options: grid, fits and extensions (:class:`ProfileOptions`).
        coord: the coordinate to profile (default :func:`profile_coordinate` among the
            pass-through ones).
    Returns:
        :class:`Profile`, sorted by the profiled value.
    """
    from solderpyro.exact.fit import LMOptions, lm_fit

    n_grid, iters, n_sd = options.n_grid, options.iters, options.n_sd
    extend_chi2, max_extend = options.extend_chi2, options.max_extend
    space, d = coords.space, coords.dim
    if n_grid < 2:
        raise ValueError(f"fe_profile: n_grid must be >= 2, got {n_grid}")
    j = profile_coordinate(cov_w, coords.pass_through) if coord is None else int(coord)
    if j not in coords.pass_through:
        raise ValueError(f"fe_profile: coordinate {j} is not one the {coords.name} "
                         f"coordinates hold fixed by holding a parameter")
    w_best = coords.to_w(np.asarray(x_best, float)[None])[0]
    sd = float(np.sqrt(cov_w[j, j]))
    c = np.linspace(max(0.0, w_best[j] - n_sd * sd), min(1.0, w_best[j] + n_sd * sd), n_grid)
    slope = cov_w[:, j] / cov_w[j, j]
    rest = np.delete(np.arange(d), j)
    lo, hi = np.array(space.lower), np.array(space.upper)

    def start(W: np.ndarray) -> np.ndarray:
        """Physical starts for sampling-coordinate points (clipped into the box)."""
        X = coords.from_w(W)
        fallback = np.repeat(np.asarray(x_best, float)[None], len(W), 0)
        fallback[:, j] = space.from_unit(torch.as_tensor(W[:, j:j + 1].repeat(d, 1))
                                         ).numpy()[:, j]
        X = np.where(np.isfinite(X).all(1, keepdims=True), X, fallback)
        return np.clip(X, lo, hi)

    def refit(X0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        fits = lm_fit(fun, X0, lo, hi, y, sigma, free=[rest] * len(X0),
                      options=LMOptions(iters=iters))
        covs = np.full((len(X0), d - 1, d - 1), np.nan)
        for g, ft in enumerate(fits):
            J = ft.jacobian_unit(lo, hi, space.log_scale)
            if J is not None:
                covs[g] = laplace_cov_w(J, coords, ft.x, sigma, rest)
        x = np.stack([ft.x for ft in fits])
        x[:, j] = X0[:, j]  # exactly on the grid (the fit never moves a held parameter)
        return x, np.array([ft.chi2 for ft in fits]), covs

    W0 = w_best[None] + (c - w_best[j])[:, None] * slope[None]
    W0[:, j] = c
    x, chi2, covs = refit(start(W0))
    for _ in range(max_extend):
        o = np.argsort(c)
        c, x, chi2, covs = c[o], x[o], chi2[o], covs[o]
        ok = np.isfinite(chi2)
        if ok.sum() < 2:
            break
        c2min = float(chi2[ok].min())
        W = coords.to_w(x)
        new: list[np.ndarray] = []
        for end, nb in ((0, 1), (len(c) - 1, len(c) - 2)):
            at_bound = c[end] <= 0.0 or c[end] >= 1.0
            if at_bound or not chi2[end] - c2min < extend_chi2:
                continue
            step = c[end] - c[nb]  # outward
            tang = (W[end] - W[nb]) / step
            for k in (1.5, 1.5 + 1.5**2):
                cn = float(np.clip(c[end] + k * step, 0.0, 1.0))
                if np.all(np.abs(c - cn) > 1e-9) and all(abs(v[j] - cn) > 1e-9 for v in new):
                    wn = W[end] + tang * (cn - c[end])
                    wn[j] = cn
                    new.append(wn)
        if not new:
            break
        xn, c2n, cvn = refit(start(np.array(new)))
        c = np.concatenate([c, np.array([v[j] for v in new])])
        x, chi2, covs = np.concatenate([x, xn]), np.concatenate([chi2, c2n]), \
            np.concatenate([covs, cvn])
    o = np.argsort(c)
    return Profile(j, c[o], x[o], coords.to_w(x[o]), chi2[o], covs[o])


def ridge_mixture(profile: Profile, dim: int, inflate: float = 1.2, df: float = 8.0,
                  temper: float = 0.5, uniform_share: float = 0.2, refine: int = 4
                  ) -> TMixture | None:
    """A proposal along the profiled ridge: Student-t components strung along it.

    A ridge that the data pin to a thin curve leaves any straight segment within a fraction of
    its length (on the hidden-effect field data, 1 Laplace sd along the weakest axis of the
    best fit costs chi2 +150 instead of +1). So the profile's fits are joined by a cubic spline
    in the profiled coordinate, and ``refine`` components per profile interval are centred on
    it: each has an sd along the profiled coordinate of 0.6 of their spacing, the others'
    conditional Laplace covariance (interpolated between the profile points, widened by
    ``inflate``) sheared along the spline's tangent. Weights: the Laplace mass of each piece,
    ``exp(-chi2/2) sqrt(det cov) * width`` with chi2 and log det interpolated, tempered
    (``**temper``) and mixed with a uniform share.

    Args:
        profile: from :func:`fe_profile`; dim: the number of sampling coordinates.
    Returns:
        a :class:`TMixture` in the profile's sampling coordinates, or None when fewer than two
        grid points have a finite fit.
    """
    from scipy.interpolate import CubicSpline, interp1d

    ok = np.isfinite(profile.chi2) & np.isfinite(profile.cov).all((1, 2))
    if ok.sum() < 2:
        return None
    c, j = profile.c[ok], profile.coord
    W = profile.w[ok]
    rest = np.delete(np.arange(dim), j)
    cov = profile.cov[ok]
    logdet = np.array([np.linalg.slogdet(cv)[1] for cv in cov])
    cf = np.unique(np.concatenate([np.linspace(c[g], c[g + 1], refine + 1)
                                   for g in range(len(c) - 1)]))
    if len(c) >= 3:
        path = CubicSpline(c, W[:, rest])
        centre, tang = path(cf), path(cf, 1)
    else:
        centre = interp1d(c, W[:, rest], axis=0)(cf)
        tang = np.repeat(((W[1, rest] - W[0, rest]) / (c[1] - c[0]))[None], len(cf), 0)
    chi2 = np.interp(cf, c, profile.chi2[ok])
    ld = np.interp(cf, c, logdet)
    cv = interp1d(c, cov, axis=0)(cf)  # convex combinations of SPD matrices stay SPD
    gaps = np.diff(cf)
    near = np.minimum(np.r_[np.inf, gaps], np.r_[gaps, np.inf])
    cell = 0.5 * (np.r_[gaps[0], gaps] + np.r_[gaps, gaps[-1]])
    means = np.empty((len(cf), dim))
    means[:, j], means[:, rest] = cf, centre
    covs = np.zeros((len(cf), dim, dim))
    for g in range(len(cf)):
        h2 = (0.6 * near[g]) ** 2
        t = tang[g]
        covs[g, j, j] = h2
        covs[g, rest, j] = covs[g, j, rest] = h2 * t
        covs[g][np.ix_(rest, rest)] = inflate**2 * cv[g] + h2 * np.outer(t, t)
        covs[g] += 1e-12 * np.eye(dim)
    lw = temper * (-0.5 * chi2 + 0.5 * ld + np.log(cell))
    w = np.exp(lw - lw.max())
    w = (1.0 - uniform_share) * w / w.sum() + uniform_share / len(w)
    return TMixture(w, means, covs, np.full(len(w), df))


def initial_proposal(coords: UnitCoords, draws: np.ndarray | None = None,
                     fe_best: tuple[np.ndarray, np.ndarray] | None = None,
                     profile: Profile | None = None, seed: int = 0, inflate: float = 1.5,
                     df: float = 5.0) -> TMixture:
    """The first AMIS proposal in sampling coordinates, from what is known of the posterior.

    Args:
        coords: the sampling coordinates.
        draws: ``(n, dim)`` surrogate posterior draws, physical (a 3-component Gaussian mixture
            is fitted to them and widened by ``inflate``).
        fe_best: ``(x (dim,) physical, cov_w (dim, dim))``: the FE's best fit and its Laplace
            covariance in sampling coordinates (widened by ``inflate``).
        profile: :func:`fe_profile` along the ridge (:func:`ridge_mixture`).
    Returns:
        the mixture of the parts given: draws 0.3, best fit 0.2, ridge 0.5 (renormalized).
    """
    parts: list[tuple[float, TMixture]] = []
    if draws is not None and len(draws) > 2 * coords.dim:
        w = coords.to_w(draws)
        w = w[np.isfinite(w).all(1)]
        fit = weighted_em(w, np.ones(len(w)), min(3, len(w) // (2 * coords.dim)),
                          np.random.default_rng(seed))
        parts.append((0.3, TMixture(fit.weights, fit.means, fit.covs * inflate**2,
                                    np.full(len(fit.weights), df))))
    if fe_best is not None:
        parts.append((0.2, TMixture.single(coords.to_w(np.asarray(fe_best[0])[None])[0],
                                           inflate**2 * fe_best[1], df)))
    if profile is not None:
        rm = ridge_mixture(profile, coords.dim)
        if rm is not None:
            parts.append((0.5, rm))
    if not parts:
        raise ValueError("initial_proposal: give posterior draws, an FE best fit or a profile")
    return TMixture.combine(parts)


@dataclass
class ExactPosterior:
    """The FE-exact posterior from :func:`exact_posterior`.

    Attributes:
        names: parameter names (then ``sigma``).
        result: the AMIS samples and weights (sampling coordinates).
        samples: ``(N, dim)`` the same samples in physical units (weights ``result.weights()``).
        theta: ``(n_draws, dim)`` draws resampled by the weights, physical units.
        sigma: ``(n_draws,)`` noise sd drawn from its conditional posterior, um.
        V: ``(n_draws, n_obs)`` the model's outputs at those draws, um.
        rows: summary rows (parameter, q2.5, median, mean, q97.5) from the weighted samples.
        profile: the ridge profile used in the proposal, or None.
    """

    names: tuple[str, ...]
    result: AMISResult
    samples: np.ndarray
    theta: np.ndarray
    sigma: np.ndarray
    V: np.ndarray
    rows: list[dict]
    profile: Profile | None = None

    @property
    def reliable(self) -> bool:
        """Whether the AMIS weights pass their checks (Kish ESS and Pareto k-hat;
        :attr:`~solderpyro.exact.amis.AMISResult.reliable`)."""
        return self.result.reliable


@dataclass(frozen=True)
class ExactSampling:
    """The run of :func:`exact_posterior`.

    Attributes:
        n: samples per AMIS round (one ``fun`` call each); rounds: AMIS rounds.
        extra_rounds: up to this many more while the weights are not reliable
            (:attr:`AmisOptions.extra_rounds <solderpyro.exact.amis.AmisOptions>`).
        seed: random seed (AMIS and the resampling).
        n_draws: resampled draws returned (systematic resampling of the weights).
        on_round: called with the :class:`~solderpyro.exact.amis.AMISResult` so far after
            every round (e.g. to log progress), or None.
    """

    n: int
    rounds: int
    seed: int = 0
    n_draws: int = 1000
    on_round: Callable[[AMISResult], None] | None = None
    extra_rounds: int = 0


def exact_posterior(fun: Fun, coords: UnitCoords, y: np.ndarray, q0: TMixture,
                    options: ExactSampling, sigma_known: float | None = None,
                    sigma_max: float | None = None, profile: Profile | None = None
                    ) -> ExactPosterior:
    """Sample the posterior of ``coords.space`` and the noise sd with ``fun`` in the likelihood.

    ``p(theta, sigma | y) ∝ prod_i N(y_i; fun(theta)_i, sigma^2) p(sigma)``, flat on the box's
    unit cube; sigma's prior is the calibration's (``LogNormal(log sigma_known, 0.1)`` or
    ``Uniform(0, sigma_max)``) and is integrated out for the weights. AMIS runs in the sampling
    coordinates ``w``, where the target is ``p(u(w)) / |det dw/du|``.

    Args:
        fun: ``rows (b, dim) -> (b, n_obs)`` um, NaN rows where the model failed.
        coords: sampling coordinates of the box. y: ``(n_obs,)`` data, um.
        q0: first proposal (sampling coordinates).
        options: samples, rounds, seed, draws and progress hook (:class:`ExactSampling`).
        sigma_known, sigma_max: sigma's prior, um (see above; one of them must be given).
        profile: the ridge profile used in ``q0``, kept in the result (or None).
    Returns:
        :class:`ExactPosterior`.
    Raises:
        RuntimeError: when the model failed at every sample.
    """
    n, rounds, seed, n_draws = options.n, options.rounds, options.seed, options.n_draws
    y = np.asarray(y, float)
    n_obs = y.shape[0]

    def log_target(w: np.ndarray) -> tuple[np.ndarray, dict]:
        X = coords.from_w(w)
        V = np.asarray(fun(X), float)
        ssr = ((V - y[None]) ** 2).sum(1)
        ll, _ = log_marginal_sigma(ssr, n_obs, sigma_known, sigma_max)
        return ll - coords.log_det(X), {"V": V, "ssr": ssr}

    res = amis(log_target, q0, n, rounds,
               AmisOptions(seed=seed, extra_rounds=options.extra_rounds),
               in_support=coords.inside, on_round=options.on_round)
    if not np.isfinite(res.log_w).any():
        raise RuntimeError(f"exact_posterior: the model failed at all {len(res.u)} samples")
    w = res.weights()
    rng = np.random.default_rng(seed + 7)
    pos = (rng.random() + np.arange(n_draws)) / n_draws  # systematic resampling
    idx = np.minimum(np.searchsorted(np.cumsum(w), pos), len(w) - 1)
    ll, draw_sigma = log_marginal_sigma(res.extra["ssr"], n_obs, sigma_known, sigma_max)
    sig = draw_sigma(idx, rng)
    X = coords.from_w(res.u)
    rows = []
    for k, nm in enumerate(coords.space.names):
        q = weighted_quantiles(X[:, k], w, (0.025, 0.5, 0.975))
        rows.append({"parameter": nm, "q2.5": q[0], "median": q[1],
                     "mean": float(w @ X[:, k]), "q97.5": q[2]})
    qs = np.quantile(sig, [0.025, 0.5, 0.975])
    rows.append({"parameter": "sigma", "q2.5": float(qs[0]), "median": float(qs[1]),
                 "mean": float(sig.mean()), "q97.5": float(qs[2])})
    rows = with_intervals(rows, X, coords.space, weights=w)
    # the ends rest on the few effective samples in each tail: moved out by their MC error
    rows = with_monte_carlo_error(rows, X, w, coords.space)
    # every sample the FE's likelihood does not reject stays inside the reported intervals
    inside = np.isfinite(res.log_w) & np.isfinite(ll)
    rows = likelihood_hull(rows, X[inside], ll[inside], coords.space)
    return ExactPosterior(tuple(coords.space.names) + ("sigma",), res, X, X[idx], sig,
                          res.extra["V"][idx], rows, profile)


#: chi-square quantile of a 95 % profile-likelihood interval (one degree of freedom, Wilks)
PROFILE_CHI2_95 = 3.841458820694124


@dataclass
class ProfileInterval:
    """A profile-likelihood confidence interval of one parameter through the model itself.

    Attributes:
        parameter: its name; k: its column in the box.
        lower, upper: the interval, physical units: where the profile chi-square
            ``min_{others} chi2`` crosses its minimum plus ``delta`` (3.84 for 95 %).
        at_lower_bound, at_upper_bound: the profile stays below the threshold up to the box's
            bound, so the data do not bound the parameter there (practical non-identifiability,
            Raue et al. 2009); the interval then ends at the bound.
        grid: ``(G,)`` profiled values, physical, ascending; chi2: ``(G,)`` the profile there
            (inf where the model failed); x: ``(G, dim)`` the refitted parameter sets.
        chi2_min: the smallest chi-square seen (the profile's reference), delta: the threshold.
        truncated: an end is still below the threshold at the last profiled value inside the
            box (the extensions ran out): the interval reaches at least that far.
    """

    parameter: str
    k: int
    lower: float
    upper: float
    at_lower_bound: bool
    at_upper_bound: bool
    grid: np.ndarray
    chi2: np.ndarray
    x: np.ndarray
    chi2_min: float
    delta: float
    truncated: bool = False

    def as_dict(self) -> dict:
        """JSON-ready (the run record's ``exact``)."""
        return {"parameter": self.parameter, "lower": self.lower, "upper": self.upper,
                "at_lower_bound": self.at_lower_bound, "at_upper_bound": self.at_upper_bound,
                "grid": self.grid.tolist(), "chi2": self.chi2.tolist(),
                "chi2_min": self.chi2_min, "delta": self.delta, "truncated": self.truncated}


def _crossing(g: np.ndarray, d: np.ndarray, i_in: int, i_out: int) -> float:
    """Where the profile excess ``d`` crosses 0 between grid points ``i_in`` (below) and
    ``i_out`` (above): a parabola through three neighbouring points when they exist (exact
    for a quadratic profile), else a straight line."""
    lo_i, hi_i = sorted((i_in, i_out))
    trio = [j for j in (lo_i - 1, lo_i, hi_i, hi_i + 1) if 0 <= j < len(g)
            and np.isfinite(d[j])]
    if len(trio) >= 3:
        # the three points closest to the bracket, the bracket's two included
        extra = [j for j in trio if j not in (lo_i, hi_i)]
        pick = sorted([lo_i, hi_i, min(extra, key=lambda j: min(abs(j - lo_i), abs(j - hi_i)))])
        g0, sc = float(np.mean(g[pick])), float(np.ptp(g[pick])) or 1.0  # well conditioned
        c = np.polyfit((g[pick] - g0) / sc, d[pick], 2)
        roots = np.roots(c)
        roots = g0 + sc * roots[np.isreal(roots)].real
        roots = roots[(roots >= g[lo_i] - 1e-12) & (roots <= g[hi_i] + 1e-12)]
        if len(roots):
            return float(roots[np.argmin(np.abs(roots - g[i_out]))])
    t = d[i_in] / (d[i_in] - d[i_out])
    return float(g[i_in] + t * (g[i_out] - g[i_in]))


@dataclass(frozen=True)
class IntervalOptions:
    """The tuning of :func:`profile_intervals`.

    Attributes:
        n_grid: grid points per parameter (at least 3).
        iters: Levenberg-Marquardt iterations per fit.
        delta: the chi-square threshold above the minimum (3.84: 95 %, one degree of freedom).
        max_extend: the most extensions of a profile whose end is still below the threshold.
    """

    n_grid: int = 9
    iters: int = 6
    delta: float = PROFILE_CHI2_95
    max_extend: int = 2


def profile_intervals(fun: Fun, space, y: np.ndarray, sigma: float, samples: np.ndarray,
                      ssr: np.ndarray, params: list[int] | None = None,
                      options: IntervalOptions = IntervalOptions()) -> list[ProfileInterval]:
    """Profile-likelihood confidence intervals through the model, started from posterior
    samples.

    For each parameter ``k`` its value is held at a grid and the others are refitted by one
    batched Levenberg-Marquardt for all parameters and grid points together
    (:func:`solderpyro.exact.fit.lm_fit`); the interval is where ``chi2_k(value) - chi2_min <=
    delta`` (``options.delta``; Wilks: the profile likelihood ratio at the true value is
    asymptotically chi2(1), so ``delta = 3.84`` gives 95 % coverage whatever the prior box and
    however wide the ridge of the other parameters, unlike a flat-prior posterior's interval).
    The grid spans the unit-scale range of the samples within ``delta + 10`` of the best one,
    widened by 15 %; each grid point starts from the best-fitting sample near it (so the fits
    follow the branch of the ridge the posterior found there); while an end of the profile is
    still below the threshold and not at the box's bound, two more points are added beyond it
    (``options.max_extend`` times).

    Args:
        fun: ``rows (b, dim) -> (b, n_obs)`` model outputs, um (NaN rows where it failed).
        space: the box (:class:`~solderpyro.params.Box`); y: ``(n_obs,)`` data, um; sigma:
            noise sd, um.
        samples: ``(N, dim)`` posterior samples, physical (e.g. the AMIS samples), and ssr
            ``(N,)`` their sums of squared residuals, um^2 (inf/NaN where the model failed).
        params: columns to profile (default all).
        options: grid, fits, threshold and extensions (:class:`IntervalOptions`).
    Returns:
        one :class:`ProfileInterval` per profiled parameter, in ``params`` order.
    Raises:
        ValueError: bad sizes, ``sigma <= 0``, ``n_grid < 3`` or no finite sample.
    """
    from solderpyro.exact.fit import LMOptions, lm_fit

    n_grid, iters, delta = options.n_grid, options.iters, options.delta
    samples = np.atleast_2d(np.asarray(samples, float))
    ssr = np.asarray(ssr, float)
    d = space.dim
    if samples.shape[1] != d or len(ssr) != len(samples):
        raise ValueError(f"profile_intervals: samples {samples.shape} and ssr {ssr.shape} do not "
                         f"match a box of dimension {d}")
    if not sigma > 0 or n_grid < 3:
        raise ValueError(f"profile_intervals: need sigma > 0 and n_grid >= 3, got sigma={sigma}, "
                         f"n_grid={n_grid}")
    ok = np.isfinite(ssr) & np.isfinite(samples).all(1)
    if not ok.any():
        raise ValueError("profile_intervals: no sample with a finite fit")
    sm = _ProfileSamples(space, samples[ok], ssr[ok] / sigma**2)
    c_s, U = sm.c_s, sm.U
    ks = list(range(d)) if params is None else [int(k) for k in params]
    near = c_s <= c_s.min() + delta + 10.0
    grids: dict[int, np.ndarray] = {}
    X0s, owners = [], []
    for k in ks:
        a, b = U[near, k].min(), U[near, k].max()
        pad = max(0.15 * (b - a), 0.025)
        ug = np.linspace(max(0.0, a - pad), min(1.0, b + pad), n_grid)
        grids[k] = ug
        X0s.append(sm.starts(k, ug, 0.5 * (ug[1] - ug[0])))
        owners += [k] * n_grid
    X0 = np.vstack(X0s)
    fits = lm_fit(fun, X0, sm.lo, sm.hi, y, sigma,
                  free=[np.delete(np.arange(d), k) for k in owners], options=LMOptions(iters=iters))
    res: dict[int, list[tuple[float, float, np.ndarray]]] = {k: [] for k in ks}
    for k, ug_k, ft in zip(owners, np.concatenate([grids[k] for k in ks]), fits, strict=True):
        res[k].append((float(ug_k), ft.chi2, ft.x))
    for _ in range(options.max_extend):
        c_min = min(c_s.min(), min(c for k in ks for _, c, _ in res[k]))
        new, new_own = _extensions(sm, res, float(c_min), delta)
        if not new:
            break
        fits = lm_fit(fun, np.array(new), sm.lo, sm.hi, y, sigma,
                      free=[np.delete(np.arange(d), k) for k, _ in new_own],
                      options=LMOptions(iters=iters))
        for (k, un), ft in zip(new_own, fits, strict=True):
            res[k].append((un, ft.chi2, ft.x))
    c_min = float(min(c_s.min(), min(c for k in ks for _, c, _ in res[k])))
    return [_interval(sm, k, res[k], c_min, delta) for k in ks]


class _ProfileSamples:
    """The posterior samples a profile starts from: ``samples`` ``(N, dim)`` physical, their
    chi-squares ``c_s`` ``(N,)`` (finite), and their unit-box coordinates ``U``."""

    def __init__(self, space: Any, samples: np.ndarray, c_s: np.ndarray) -> None:
        self.space, self.samples, self.c_s = space, samples, c_s
        self.lo, self.hi = np.array(space.lower, float), np.array(space.upper, float)
        self.U = space.to_unit(torch.as_tensor(samples)).numpy()

    def to_phys(self, k: int, u: np.ndarray) -> np.ndarray:
        """``(m,)`` physical values of column ``k`` at unit values ``u`` ``(m,)``."""
        full = np.repeat(self.U[np.argmin(self.c_s)][None], len(u), 0)
        full[:, k] = u
        return self.space.from_unit(torch.as_tensor(full)).numpy()[:, k]

    def starts(self, k: int, ug: np.ndarray, spacing: float) -> np.ndarray:
        """``(len(ug), dim)`` starts of the fits at unit values ``ug`` of column ``k``: the
        best-fitting sample within ``spacing`` (unit scale) of each, else the nearest."""
        U, c_s = self.U, self.c_s
        X0 = np.empty((len(ug), U.shape[1]))
        xg = self.to_phys(k, ug)
        for i, u in enumerate(ug):
            dist = np.abs(U[:, k] - u)
            cand = np.nonzero(dist <= spacing)[0]
            j = int(cand[np.argmin(c_s[cand])]) if len(cand) else int(np.argmin(dist))
            X0[i] = self.samples[j]
            X0[i, k] = xg[i]
        return np.clip(X0, self.lo, self.hi)


def _extensions(sm: _ProfileSamples, res: dict[int, list[tuple[float, float, np.ndarray]]],
                c_min: float, delta: float
                ) -> tuple[list[np.ndarray], list[tuple[int, float]]]:
    """Two more points beyond each end of a profile in ``res`` (per column: (unit value,
    chi2, fit) points) still below ``c_min + delta`` and not at the box's bound. Returns
    their starts (physical) and (column, unit value)."""
    new: list[np.ndarray] = []
    new_own: list[tuple[int, float]] = []
    for k, pts_k in res.items():
        pts = sorted(pts_k, key=lambda t: t[0])
        ug = np.array([p[0] for p in pts])
        below = np.nonzero(np.array([p[1] for p in pts]) - c_min <= delta)[0]
        if not len(below):
            continue
        step = ug[1] - ug[0]
        for end, sgn in ((int(below[0]), -1.0), (int(below[-1]), 1.0)):
            if end not in (0, len(ug) - 1) or ug[end] in (0.0, 1.0):
                continue  # bracketed, or already at the box's bound
            for m in (1.5, 1.5 + 1.5**2):
                un = float(np.clip(ug[end] + sgn * m * step, 0.0, 1.0))
                if np.any(np.abs(ug - un) < 1e-12) or (k, un) in new_own:
                    continue  # clipped onto a value already profiled
                x0 = pts[end][2].copy()
                x0[k] = sm.to_phys(k, np.array([un]))[0]
                new.append(np.clip(x0, sm.lo, sm.hi))
                new_own.append((k, un))
    return new, new_own


def _interval(sm: _ProfileSamples, k: int, pts_k: list[tuple[float, float, np.ndarray]],
              c_min: float, delta: float) -> ProfileInterval:
    """Column ``k``'s interval from its profile points (unit value, chi2, fit): where
    ``chi2 - c_min <= delta``, linearly interpolated at the crossings."""
    pts = sorted(pts_k, key=lambda t: t[0])
    ug = np.array([p[0] for p in pts])
    c2 = np.array([p[1] if np.isfinite(p[1]) else np.inf for p in pts])
    xs = np.stack([p[2] for p in pts])
    g = sm.to_phys(k, ug)
    exc = c2 - c_min - delta
    inside = np.nonzero(exc <= 0)[0]
    if not len(inside):  # the profile never comes down to the threshold: its best point
        i = int(np.argmin(c2))
        lower = upper = float(g[i])
        at_lo = at_hi = trunc = False
    else:
        i0, i1 = int(inside[0]), int(inside[-1])
        at_lo = i0 == 0 and ug[0] <= 0.0
        at_hi = i1 == len(ug) - 1 and ug[-1] >= 1.0
        lower = float(g[0]) if i0 == 0 else _crossing(g, exc, i0, i0 - 1)
        upper = float(g[-1]) if i1 == len(g) - 1 else _crossing(g, exc, i1, i1 + 1)
        trunc = (i0 == 0 and not at_lo) or (i1 == len(ug) - 1 and not at_hi)
    return ProfileInterval(sm.space.names[k], k, lower, upper, bool(at_lo), bool(at_hi),
                           g, c2, xs, c_min, delta, bool(trunc))


def laplace_cov_unit(fit: Any, space: Box, sigma: float) -> np.ndarray:
    """Laplace covariance ``(space.dim, space.dim)`` of an :class:`~solderpyro.exact.fit.LMFit` on
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
