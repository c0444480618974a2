"""The flat unconstrained vector NUTS samples on: its sites (bounds, transforms) and the
model that carries the log density and its gradient. Shared by the analytic densities
(:mod:`.fastkoh`: direct, full joint; :mod:`.reduced`: modular PCA)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from solderpyro.calibration.koh import SITE_SIGMA, Priors

_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)


@dataclass(frozen=True)
class FlatSite:
    """One sampled site in the flat vector.

    Attributes:
        name: the Pyro site name; size: its number of elements; vector: whether the site is a
        vector ``(size,)`` (else a scalar); lo, hi: the bounds of an interval support, or
        ``lo = hi = nan`` for a positive support (log transform); offset: its first index.
    """

    name: str
    size: int
    vector: bool
    lo: float
    hi: float
    offset: int

    @property
    def positive(self) -> bool:
        return math.isnan(self.lo)

    def constrain(self, u: np.ndarray) -> np.ndarray:
        """Unconstrained ``(..., size)`` -> constrained values of the same shape."""
        if self.positive:
            return np.exp(u)
        return self.lo + (self.hi - self.lo) / (1.0 + np.exp(-u))

    def unconstrain(self, x: np.ndarray) -> np.ndarray:
        """Constrained ``(..., size)`` -> unconstrained values of the same shape."""
        if self.positive:
            return np.log(x)
        s = np.clip((x - self.lo) / (self.hi - self.lo), 1e-15, 1.0 - 1e-15)
        return np.log(s) - np.log1p(-s)


class FlatModel:
    """A KOH posterior on a flat unconstrained vector, for :func:`~.nuts.sample_nuts`.

    Attributes:
        sites: the sampled sites in order; dim: the length ``d`` of the flat vector.
        dtype: the torch dtype of the model's tensors (for :meth:`to_samples`).
        reparam: None, or ``(idx, coords)``: the flat indices ``idx (k,)`` of unit-interval
            coordinates that ``coords`` (e.g. :class:`~.flowcoords.SoftFlowCoords`: methods
            ``forward(q (k,)) -> (t (k,), log|det dt/dq|, vjp)`` and ``inverse(t) -> q``)
            maps jointly instead of each by its logit; :attr:`coord_suffix` names them.
        native: None, or the whole :meth:`logp_and_grad` compiled (``q (d,) -> (lp,
            gradient (d,))``; :func:`~.reduced.pca_flat` sets it in flow coordinates where the
            native kernels are built), which :meth:`logp_and_grad` then calls.
    """

    def __init__(self, sites: list[FlatSite], loglik: Any, prior_mu: float, prior_sd: float,
                 dtype: torch.dtype, reparam: tuple[np.ndarray, Any] | None = None) -> None:
        self.sites = sites
        self.reparam = reparam
        #: flat index -> a suffix for the coordinate's name (``":flow"``): a coordinate in
        #: another system than the logit, so a warm start does not take its metric for one
        self.coord_suffix = ({int(i): ":" + getattr(reparam[1], "name", "reparam")
                              for i in reparam[0]} if reparam else {})
        self.dim = sum(s.size for s in sites)
        #: the log-likelihood on the constrained flat vector: ``x (d,) -> (loglik,
        #: d loglik / dx (d,))`` (the priors and transforms are this class's)
        self.loglik = loglik
        self._mu, self._sd = prior_mu, prior_sd  # LogNormal sigma prior (positive sites)
        self.dtype = dtype
        self._lo = np.zeros(self.dim)
        self._w = np.ones(self.dim)
        for st in sites:
            if not st.positive:
                self._lo[st.offset:st.offset + st.size] = st.lo
                self._w[st.offset:st.offset + st.size] = st.hi - st.lo
        # the uniform priors' -log(hi - lo) and the Jacobians' +log(hi - lo) cancel exactly
        pos = [s for s in sites if s.positive]
        self._pos_idx = np.array([s.offset for s in pos], dtype=np.int64)
        self.native: Any = None

    def logp_and_grad(self, q: np.ndarray) -> tuple[float, np.ndarray]:
        """Log posterior density (up to a constant) and its gradient at ``q (d,)``.

        Returns:
            (float, ``(d,)``): the log density of the unconstrained vector (log-Jacobians
            included), exactly Pyro's ``-potential_energy`` up to an additive constant.
        """
        if self.native is not None:
            return self.native(q)
        # interval transform on every coordinate (positive ones are overwritten below)
        with np.errstate(over="ignore"):  # q < -709: s = 0 (x at its lower bound)
            s = 1.0 / (1.0 + np.exp(-q))
        x = self._lo + self._w * s
        dx = self._w * s * (1.0 - s)  # dx/du
        grad = 1.0 - 2.0 * s  # d/du of log s + log(1 - s)
        au = np.abs(q)  # log s + log(1 - s), stable for large |u|
        lj_all = -au - 2.0 * np.log1p(np.exp(-au))
        if self._pos_idx.size:
            pi = self._pos_idx
            lj_all[pi] = 0.0
            x[pi] = np.exp(q[pi])
            dx[pi] = x[pi]
            # LogNormal prior plus the Jacobian u: -(u - mu)^2 / (2 sd^2) + const
            z = (q[pi] - self._mu) / self._sd
            lj_all[pi] = -0.5 * z * z - (math.log(self._sd) + _HALF_LOG_2PI)
            grad[pi] = -z / self._sd
        vjp = None
        if self.reparam is not None:
            ri, rc = self.reparam
            x[ri], ld, vjp = rc.forward(q[ri])  # unit interval sites: x = t
            lj_all[ri] = 0.0
            lj_all[ri[0]] = ld
        lj = float(lj_all.sum())
        ll, gx = self.loglik(x)
        g = grad + gx * dx
        if vjp is not None:
            g[ri] = vjp(gx[ri])
        return ll + lj, g

    def to_samples(self, draws: np.ndarray) -> dict[str, torch.Tensor]:
        """Unconstrained draws ``(chain, draw, d)`` -> ``site -> (chain, draw[, size])`` tensors
        in constrained units (Pyro's layout: scalars without a trailing axis)."""
        out = {}
        if self.reparam is not None:
            ri, rc = self.reparam
            flat = draws.reshape(-1, draws.shape[-1])
            t = np.array([rc.forward(row[ri])[0] for row in flat]).reshape(
                *draws.shape[:-1], len(ri))
        for s in self.sites:
            v = s.constrain(draws[..., s.offset:s.offset + s.size])
            if self.reparam is not None:
                for j, i in enumerate(ri):
                    if s.offset <= i < s.offset + s.size:
                        v[..., i - s.offset] = t[..., j]
            out[s.name] = torch.as_tensor(v if s.vector else v[..., 0], dtype=self.dtype)
        return out

    def to_unconstrained(self, values: dict[str, Any]) -> np.ndarray:
        """``site -> constrained value`` (scalar or ``(size,)``) -> the flat vector ``(d,)``."""
        q = np.empty(self.dim)
        for s in self.sites:
            v = np.asarray(torch.as_tensor(values[s.name]).detach().cpu().double(),
                           dtype=float).reshape(-1)
            if v.shape != (s.size,):
                raise ValueError(f"init value of {s.name} has {v.size} elements, expected "
                                 f"{s.size}")
            q[s.offset:s.offset + s.size] = s.unconstrain(v)
            if self.reparam is not None:
                ri, rc = self.reparam
                if all(s.offset <= i < s.offset + s.size for i in ri):
                    q[ri] = rc.inverse(v[ri - s.offset])
        return q


def reject_unsupported(priors: Priors, extra: dict[str, bool]) -> None:
    """Raise :class:`NotImplementedError` naming every option an analytic log density does
    not cover: the descriptions in ``extra`` whose flag is true, and custom priors
    (``priors.custom``), which none covers. Returns None when all are covered."""
    bad = [k for k, v in extra.items() if v]
    if priors.custom:
        bad.append(f"custom priors on {sorted(priors.custom)}")
    if bad:
        raise NotImplementedError("no analytic log density for " + ", ".join(bad)
                                  + " (Pyro's potential with autograd serves it)")


def sigma_site(priors: Priors, y: np.ndarray, offset: int) -> tuple[FlatSite, float, float]:
    """The sigma site at flat index ``offset`` with the prior :class:`~.koh.Priors` gives it
    for the observations ``y (n,)`` (output units): flat on ``(0, sigma_max)`` (default 2 x
    the range of ``y``), or LogNormal around ``sigma_known``.

    Returns:
        ``(site, mu, sd)``: the :class:`FlatSite` (an interval, or positive for the LogNormal)
        and the LogNormal's ``(mu, sd)`` of log sigma (``(0, 1)``, unused, for the flat prior).
    """
    if priors.sigma_known is not None:
        return (FlatSite(SITE_SIGMA, 1, False, math.nan, math.nan, offset),
                math.log(priors.sigma_known), 0.1)
    y_range = float(y.max() - y.min()) if y.shape[0] > 1 else float(abs(y[0]))
    hi = priors.sigma_max or 2 * max(y_range, 1e-12)
    return FlatSite(SITE_SIGMA, 1, False, 0.0, float(hi), offset), 0.0, 1.0
