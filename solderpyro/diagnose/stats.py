"""Statistics of model misfit: predictive checks and score (Lagrange-multiplier) tests.

Everything here is plain linear algebra on residuals and Jacobians, so it can be checked
against closed forms (tests/unit/diagnose/test_stats.py). Units: residuals in um, weights in
1/um^2; parameters in whatever units their Jacobian columns use.

Score test of an effect with parameters phi (k of them, "off" at phi0) in the model
y = f(theta, phi) + e, e ~ N(0, W^-1): with J_t = df/dtheta (n, p) and J_e = df/dphi (n, k) at
(theta_hat, phi0) and r = y - f, project out what the calibrated parameters can already do,
P = I - J_t (J_t' W J_t)^-1 J_t' W, and take

    U = (P J_e)' W r,  I = (P J_e)' W (P J_e),  S = U' I^+ U  ~  chi2(rank I)  under "off".

S is also the drop of the (linearised) chi-square when the effect is added and all parameters
are refitted, so it reads as "this much of the misfit the effect can explain".
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import stats


@dataclass
class PredictiveCheck:
    """Posterior predictive checks of ``n`` observations.

    Attributes:
        z: ``(n,)`` standardized residuals ``(y - mean) / sd`` of the predictive (noise included).
        pit: ``(n,)`` probability integral transform ``P(y_rep <= y)``.
        t_obs, t_rep: ``(n_draws,)`` discrepancy ``sum((y - mu)^2 / sigma^2)`` of the data and of
            a replicate under each draw.
        p_value: posterior predictive p-value ``P(T_rep >= T_obs)``.
    """

    z: np.ndarray
    pit: np.ndarray
    t_obs: np.ndarray
    t_rep: np.ndarray
    p_value: float


def predictive_check(y: np.ndarray, process: np.ndarray, sigma: np.ndarray,
                     seed: int = 0) -> PredictiveCheck:
    """Posterior predictive checks from draws of the model.

    Args:
        y: ``(n,)`` measurements, um.
        process: ``(n_draws, n)`` draws of the model's prediction (code uncertainty included), um.
        sigma: ``(n_draws,)`` noise standard deviation of each draw, um.
        seed: for the replicated data.
    Returns:
        :class:`PredictiveCheck`.
    """
    y = np.asarray(y, float)
    process = np.asarray(process, float)
    sigma = np.broadcast_to(np.asarray(sigma, float), process.shape[:1])
    if process.ndim != 2 or process.shape[1] != y.shape[0]:
        raise ValueError(f"process must have shape (n_draws, {y.shape[0]}), got {process.shape}")
    if not np.all(sigma > 0):
        raise ValueError("sigma must be > 0")
    rng = np.random.default_rng(seed)
    rep = process + sigma[:, None] * rng.standard_normal(process.shape)
    sd = np.sqrt(process.var(0) + np.mean(sigma**2))
    z = (y - process.mean(0)) / sd
    pit = (rep <= y).mean(0)
    t_obs = (((y - process) / sigma[:, None]) ** 2).sum(1)
    t_rep = (((rep - process) / sigma[:, None]) ** 2).sum(1)
    return PredictiveCheck(z, pit, t_obs, t_rep, float(np.mean(t_rep >= t_obs)))


class _WProj:
    """``P = I - J (J' W J)^+ J' W`` for ``J (n, p)``, ``w (n,)``: removes what J can fit.

    Applied as ``P @ x`` for ``x (n,)`` or ``(n, k)`` in O(n p k), never formed: the dense
    ``(n, n)`` matrix cost seconds per score test on full-field data (n = 2,240)."""

    def __init__(self, J: np.ndarray, w: np.ndarray) -> None:
        self.sw = np.sqrt(w)
        self.q, _ = _orth(self.sw[:, None] * J)

    def __matmul__(self, x: np.ndarray) -> np.ndarray:
        sw = self.sw if x.ndim == 1 else self.sw[:, None]
        return x - (self.q @ (self.q.T @ (sw * x))) / sw


def _wproj(J: np.ndarray, w: np.ndarray) -> _WProj:
    """The weighted projector :class:`_WProj` of ``J (n, p)`` with weights ``w (n,)``."""
    return _WProj(J, w)


def _orth(A: np.ndarray, rtol: float = 1e-8, scale: float | None = None
          ) -> tuple[np.ndarray, int]:
    """Orthonormal basis of the column space of ``A`` and its numerical rank (singular values
    above ``rtol`` times ``scale``, default the largest one)."""
    if A.size == 0:
        return np.zeros((A.shape[0], 0)), 0
    u, s, _ = np.linalg.svd(A, full_matrices=False)
    ref = s.max() if scale is None else scale
    k = int((s > rtol * max(ref, 1e-300)).sum()) if s.size else 0
    return u[:, :k], k


@dataclass
class Misfit:
    """Chi-square misfit of the calibrated model after a linearised refit of its parameters.

    Attributes:
        chi2: ``r' P' W P r``; dof: ``n - rank(J_theta)``; p_value: ``P(chi2_dof >= chi2)``.
        rms: root mean square of the refitted residual, um; rms_noise: the noise sd, um.
        residual: ``(n,)`` the refitted residual ``P r``, um.
    """

    chi2: float
    dof: int
    p_value: float
    rms: float
    rms_noise: float
    residual: np.ndarray


def misfit(r: np.ndarray, J_theta: np.ndarray, w: np.ndarray) -> Misfit:
    """Misfit of residual ``r (n,)`` (um) once the parameters with Jacobian ``J_theta (n, p)``
    are refitted to first order, with weights ``w (n,)`` = 1/variance (1/um^2)."""
    P = _wproj(J_theta, w)
    rt = P @ r
    chi2 = float((w * rt**2).sum())
    dof = max(len(r) - _orth(np.sqrt(w)[:, None] * J_theta)[1], 1)
    return Misfit(chi2, dof, float(stats.chi2.sf(chi2, dof)), float(np.sqrt(np.mean(rt**2))),
                  float(np.sqrt(np.mean(1.0 / w))), rt)


@dataclass
class Score:
    """Score test of one candidate effect (see the module docstring).

    Attributes:
        effect: name; statistic: S; dof: rank of the projected information; p_value;
        evidence: ``-log10 p``, computed in log space (:func:`evidence`);
        identifiable: share ``|P J_e|_W / |J_e|_W`` of the effect's signature that the calibrated
            parameters cannot mimic (0: fully confounded with them, 1: orthogonal);
        delta: ``(k,)`` linearised estimate of the effect's parameters (from "off");
        chi2_after: the misfit chi-square left after adding it;
        pattern: ``(n,)`` the fitted linearised effect ``P J_e delta``, um (compare with the
            refitted residual);
        basis: ``(n, rank)`` W-orthonormal basis of ``sqrt(W) P J_e`` (for confusions).
        lr, lr_value: for one-parameter effects, the largest chi-square drop over a ladder of
            finite magnitudes (likelihood ratio, calibrated parameters refitted) and the
            magnitude that gave it; where it exceeds the score, statistic/p-value use it.
        profile_chi2: chi-square of the FE refitted with the effect on (when done).
    """

    effect: str
    statistic: float
    dof: int
    p_value: float
    evidence: float
    identifiable: float
    delta: np.ndarray
    chi2_after: float
    pattern: np.ndarray
    basis: np.ndarray = field(repr=False)
    lr: float | None = None
    lr_value: float | None = None
    profile_chi2: float | None = None


def score_test(name: str, r: np.ndarray, J_theta: np.ndarray, J_eff: np.ndarray,
               w: np.ndarray) -> Score:
    """Score test of an effect with Jacobian ``J_eff (n, k)`` at "off".

    Args:
        name: the effect's name.
        r: ``(n,)`` residual ``y - f(theta_hat, off)``, um.
        J_theta: ``(n, p)`` Jacobian of the outputs w.r.t. the calibrated parameters.
        J_eff: ``(n, k)`` Jacobian w.r.t. the effect's parameters at "off".
        w: ``(n,)`` weights, 1 / (noise variance), 1/um^2.
    Returns:
        :class:`Score`.
    """
    P = _wproj(J_theta, w)
    sw = np.sqrt(w)
    Je = P @ J_eff
    A = sw[:, None] * Je
    full = float(np.linalg.norm(sw[:, None] * J_eff))
    q, k = _orth(A, rtol=1e-6, scale=full)  # directions the parameters cannot mimic
    rt = P @ r
    u = q.T @ (sw * rt)  # coordinates of the residual in the effect's projected span
    S = float(u @ u)
    if k == 0:
        p, delta, pattern = 1.0, np.zeros(J_eff.shape[1]), np.zeros_like(r)
    else:
        p = float(stats.chi2.sf(S, k))
        delta = np.linalg.lstsq(A, sw * rt, rcond=None)[0]
        pattern = Je @ delta
    ident = float(np.linalg.norm(A) / full) if full > 0 else 0.0
    chi2 = float((w * rt**2).sum())
    ev = evidence(S, k)
    return Score(name, S, k, p, ev, ident, delta, chi2 - S, pattern, q)


def evidence(statistic: float, dof: int) -> float:
    """``-log10 P(chi2_dof >= statistic)``, exact in the far tail (no underflow to 0 at 1e-300:
    strong effects stay ordered by their evidence). 0 for ``dof = 0``."""
    if dof <= 0:
        return 0.0
    ls = float(stats.chi2.logsf(statistic, dof))
    if not np.isfinite(ls):  # far tail: log Q(k/2, x/2) ~ (k/2 - 1) log(x/2) - x/2 - lgamma(k/2)
        from scipy.special import gammaln

        x, a = 0.5 * statistic, 0.5 * dof
        ls = (a - 1.0) * np.log(x) - x - float(gammaln(a))
    return float(-ls / np.log(10.0))


def confusion(a: Score, b: Score) -> float:
    """Largest canonical correlation between two effects' projected signatures (0..1).

    1 means some combination of ``a``'s parameters changes the data exactly as one of ``b``'s
    (after the calibrated parameters have taken their share): the data cannot tell them apart.
    """
    if a.basis.shape[1] == 0 or b.basis.shape[1] == 0:
        return 0.0
    return float(np.linalg.svd(a.basis.T @ b.basis, compute_uv=False).max())
