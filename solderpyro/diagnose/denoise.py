"""Denoising a residual field: the structure of a misfit above the measurement noise.

A full-field residual (um, on the 31 x 18 grid at each measured time) is noise of sd ``sigma``
(0.05 um) plus, when the model misses an effect, a smooth pattern that can be several times
smaller than the noise (0.01-0.03 um). Each map is smoothed by Gaussian-process regression:

    r(x, y) = f(x, y) + e,   f ~ GP(0, a^2 k_5/2(dx / l_x, dy / l_y)),   e ~ N(0, sigma^2),

with the measurement's own noise sd ``sigma`` fixed (it is known) and the amplitude ``a`` and
length scales ``l_x``, ``l_y`` (mm) chosen by the marginal likelihood of every time's map
together (one set for all maps: the same physics makes them). The denoised residual is the
posterior mean of ``f`` and its band is +-2 posterior sd. Whether there is a smooth part at
all is decided first, by the likelihood ratio of the fitted GP against ``a = 0`` (pure noise):
``LR = 2 (log L(a, l) - log L(0))``, referred to chi2 on 3 dof (conservative: ``a = 0`` lies
on the boundary, where the null distribution is stochastically smaller). Below the level
:data:`ALPHA` the denoised map is zero with a zero band, "no structure above the noise": a
pointwise band alone would let pure noise leave it at a few per cent of the values (a slow
drift of a map's noise mean). A pattern above the noise leaves the band
(:attr:`Smooth.share_above_band`). Why a GP and not a
projection on the candidates' signatures: the denoised map must show a misfit no candidate
explains as well (an unknown effect), and must not be shaped by the candidates it is compared
with (docs/diagnosis.md).

Units: um for residuals, mm for coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize
from scipy.stats import chi2 as _chi2

#: bounds of the length scales, mm: one grid spacing (1 mm in x, 0.5 mm in y) up to the
#: specimen's size (30 mm x 8.5 mm)
LX_BOUNDS = (1.0, 60.0)
LY_BOUNDS = (0.5, 17.0)
#: level of the likelihood-ratio test of "any smooth part"
ALPHA = 0.01


@dataclass
class Smooth:
    """A denoised residual, row for row with the residual it came from.

    Attributes:
        mean: ``(n,)`` posterior mean of the smooth part, um.
        sd: ``(n,)`` its posterior sd, um (the band is ``mean +- 2 sd``).
        amplitude: fitted amplitude ``a`` of the smooth part, um.
        lengthscale: ``(2,)`` fitted ``(l_x, l_y)``, mm.
        sigma: the noise sd used, um.
        lr: likelihood ratio statistic of the smooth part against pure noise (NaN when the
            hyperparameters were given); p_value: its chi2(3) tail; ``mean`` and ``sd`` are
            zero when ``p_value >= ALPHA``.
    """

    mean: np.ndarray
    sd: np.ndarray
    amplitude: float
    lengthscale: np.ndarray
    sigma: float
    lr: float = float("nan")
    p_value: float = float("nan")

    @property
    def z(self) -> np.ndarray:
        """``(n,)`` ``mean / sd``: beyond +-2 the smooth part leaves its band."""
        return self.mean / np.maximum(self.sd, 1e-300)

    @property
    def share_above_band(self) -> float:
        """Share of the values whose band (``mean +- 2 sd``) excludes zero."""
        return float(np.mean(np.abs(self.z) > 2.0))

    def summary(self) -> dict[str, float | list[float] | str]:
        """What diagnosis.json records of the smoothing."""
        return {"method": "Gaussian-process regression per map (Matern 5/2, ARD), noise sd "
                          "fixed, amplitude and length scales by marginal likelihood",
                "amplitude_um": float(self.amplitude),
                "lengthscale_mm": [float(v) for v in self.lengthscale],
                "noise_um": float(self.sigma), "rms_um": float(np.sqrt(np.mean(self.mean**2))),
                "share_above_band": self.share_above_band, "lr": float(self.lr),
                "p_value": float(self.p_value)}


def _sqdist(xy: np.ndarray) -> np.ndarray:
    """``(2, n, n)`` squared differences in x and in y of points ``xy (n, 2)``, mm^2."""
    return ((xy[:, None, :] - xy[None, :, :]) ** 2).transpose(2, 0, 1)


def _matern52(d2: np.ndarray, ls: np.ndarray) -> np.ndarray:
    """Unit-variance Matern 5/2 correlation ``(n, n)`` from squared differences
    ``d2 (2, n, n)`` (:func:`_sqdist`) and length scales ``ls (2,)``, mm."""
    d = np.sqrt(5.0 * (d2[0] / ls[0] ** 2 + d2[1] / ls[1] ** 2))
    return (1.0 + d + d**2 / 3.0) * np.exp(-d)


def _groups(groups: np.ndarray) -> list[np.ndarray]:
    return [np.flatnonzero(groups == g) for g in np.unique(groups)]


def _nll(p: np.ndarray, d2s: list[np.ndarray], r: np.ndarray, idx: list[np.ndarray],
         sigma: float) -> float:
    """Negative log marginal likelihood of every map, parameters ``log (a, l_x, l_y)``."""
    a2, ls = np.exp(2 * p[0]), np.exp(p[1:])
    tot = 0.0
    for rows, d2 in zip(idx, d2s, strict=True):
        K = a2 * _matern52(d2, ls) + sigma**2 * np.eye(len(rows))
        L = np.linalg.cholesky(K)
        al = np.linalg.solve(L, r[rows])
        tot += 0.5 * al @ al + np.log(np.diag(L)).sum()
    return float(tot)


def denoise(xy: np.ndarray, residual: np.ndarray, groups: np.ndarray, sigma: float,
            fixed: tuple[float, np.ndarray] | None = None) -> Smooth:
    """Denoise residual maps by GP regression (module docstring); BLAS on one thread (its
    matrices are a few hundred wide: threads only contend).

    Args:
        xy: ``(n, 2)`` coordinates of each value, mm.
        residual: ``(n,)`` residual, um.
        groups: ``(n,)`` which map each value belongs to (e.g. the measured time, s); the maps
            share one amplitude and length scales and are smoothed separately.
        sigma: the noise sd, um (> 0).
        fixed: ``(amplitude um, (l_x, l_y) mm)`` to smooth with instead of fitting them (e.g.
            another residual's, so that two maps are seen through the same smoother).
    Returns:
        :class:`Smooth`.
    Raises:
        ValueError: shapes that differ or ``sigma <= 0``.
    """
    xy = np.asarray(xy, float)
    r = np.asarray(residual, float)
    g = np.asarray(groups)
    if xy.shape != (len(r), 2) or g.shape != r.shape:
        raise ValueError(f"denoise: xy must be (n, 2) and groups (n,) with n = {len(r)}, got "
                         f"{xy.shape} and {g.shape}")
    if not sigma > 0:
        raise ValueError(f"denoise: sigma must be > 0 um, got {sigma}")
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - threadpoolctl comes with scikit-learn
        return _denoise(xy, r, g, float(sigma), fixed)
    with threadpool_limits(1):
        return _denoise(xy, r, g, float(sigma), fixed)


def _denoise(xy: np.ndarray, r: np.ndarray, g: np.ndarray, sigma: float,
             fixed: tuple[float, np.ndarray] | None) -> Smooth:
    """:func:`denoise` after its checks."""
    idx = _groups(g)
    d2s = [_sqdist(xy[rows]) for rows in idx]
    lr = p = float("nan")
    if fixed is not None:
        a, ls = float(fixed[0]), np.asarray(fixed[1], float)
    else:
        a, ls = _fit(xy, r, idx, sigma)
        nll = _nll(np.log([a, *ls]), d2s, r, idx, sigma)
        nll0 = float(0.5 * (r**2).sum() / sigma**2 + len(r) * np.log(sigma))
        lr = max(2.0 * (nll0 - nll), 0.0)
        p = float(_chi2.sf(lr, 3))
    mean, sd = np.zeros_like(r), np.zeros_like(r)
    if p >= ALPHA:  # no smooth part detectable above the noise
        return Smooth(mean, sd, a, ls, float(sigma), lr, p)
    for rows, d2 in zip(idx, d2s, strict=True):
        Kf = a**2 * _matern52(d2, ls)
        L = np.linalg.cholesky(Kf + sigma**2 * np.eye(len(rows)))
        A = np.linalg.solve(L, Kf)  # (n_t, n_t): L^-1 K
        mean[rows] = A.T @ np.linalg.solve(L, r[rows])
        sd[rows] = np.sqrt(np.maximum(a**2 - (A**2).sum(0), 0.0))
    return Smooth(mean, sd, a, ls, float(sigma), lr, p)


def _fit(xy: np.ndarray, r: np.ndarray, idx: list[np.ndarray], sigma: float
         ) -> tuple[float, np.ndarray]:
    """Amplitude (um) and length scales ``(2,)`` (mm) by the marginal likelihood of every
    other value of each map (a checkerboard of the 31 x 18 grid: 8 times cheaper, the
    hyperparameters of a smooth field hardly change)."""
    idx = [rows[::2] for rows in idx]
    d2s = [_sqdist(xy[rows]) for rows in idx]
    a0 = np.sqrt(max(float(np.var(r)) - sigma**2, 0.01 * sigma**2))
    bounds = [(np.log(1e-4 * sigma), np.log(100 * sigma + 10 * np.abs(r).max())),
              tuple(np.log(LX_BOUNDS)), tuple(np.log(LY_BOUNDS))]
    best = None
    for lx, ly in ((3.0, 1.5), (10.0, 4.0)):  # a short and a long start
        res = minimize(_nll, np.log([a0, lx, ly]), args=(d2s, r, idx, sigma),
                       method="L-BFGS-B", bounds=bounds, options={"ftol": 1e-7})
        if best is None or res.fun < best.fun:
            best = res
    assert best is not None
    return float(np.exp(best.x[0])), np.exp(best.x[1:])


def shape_correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation of two patterns ``(n,)`` over all values (shape, not size); 0 when
    either is constant."""
    a = np.asarray(a, float) - np.mean(a)
    b = np.asarray(b, float) - np.mean(b)
    den = float(np.linalg.norm(a) * np.linalg.norm(b))
    return float(a @ b / den) if den > 0 else 0.0
