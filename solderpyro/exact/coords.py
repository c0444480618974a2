"""Coordinates to sample a posterior in: the prior box's unit cube, or flow stresses.

The FE-exact posterior (:mod:`solderpyro.exact.posterior`) is sampled with Gaussian-mixture
proposals, which work as well as the posterior is close to Gaussian in the coordinates they live
in. On the specimen's data the Anand constants trade off along curved ridges: s0, Q/R and xi move
together so that the solder's flow stress at the cycle's rates stays what the data say. In the
coordinates of :class:`~solderpyro.surrogate.features.FlowStressInputs` (s0 and Q/R replaced
by the log flow stresses at s0 and at saturation at a reference temperature and rate) much of
that curvature is gone: measured on the stress-free hidden-effect field data, samples of the
best fit's Laplace Gaussian had a median chi-square 44 above the minimum on the unit cube and 9
in flow-stress coordinates (a quadratic surface gives 4.4).

Both coordinate systems map physical parameters ``x (n, d)`` to ``w (n, d)`` and back, say
where ``w`` is inside the prior box, and give ``log |det dw/du|`` (``u`` the box's unit cube,
where the prior is flat), so that a density on ``w`` is ``p(u) / |det dw/du|``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import torch

from solderpyro.params import Box


class UnitCoords:
    """``w = u``, the box's own unit cube (logarithmic where flagged).

    Attributes:
        space: the box; dim: its dimension; pass_through: indices ``k`` with ``w_k = u_k``
            (all of them here): the coordinates a profile may hold fixed.
    """

    name = "unit"

    def __init__(self, space: Box) -> None:
        self.space = space
        self.dim = space.dim
        self.pass_through: tuple[int, ...] = tuple(range(space.dim))

    def to_w(self, x: np.ndarray) -> np.ndarray:
        """``(n, d)`` physical -> ``(n, d)`` sampling coordinates."""
        return self.space.to_unit(torch.as_tensor(np.asarray(x, float))).numpy()

    def from_w(self, w: np.ndarray) -> np.ndarray:
        """``(n, d)`` sampling coordinates -> ``(n, d)`` physical (NaN rows: no preimage)."""
        return self.space.from_unit(torch.as_tensor(np.asarray(w, float))).numpy()

    def inside(self, w: np.ndarray) -> np.ndarray:
        """``(n,)`` whether ``w (n, d)`` maps into the prior box."""
        x = self.from_w(np.atleast_2d(w))
        lo, hi = np.array(self.space.lower), np.array(self.space.upper)
        return np.isfinite(x).all(1) & ((x >= lo) & (x <= hi)).all(1)

    def log_det(self, x: np.ndarray) -> np.ndarray:
        """``(n,)`` ``log |det dw/du|`` at physical ``x (n, d)`` (0 here)."""
        return np.zeros(np.atleast_2d(x).shape[0])

    def jac(self, x: np.ndarray) -> np.ndarray:
        """``(d, d)`` ``dw/du`` at one physical point ``x (d,)`` (the identity here)."""
        return np.eye(self.dim)


class FlowStressCoords(UnitCoords):
    """``w``: the box's unit cube with s0 and Q/R replaced by the log flow stresses of
    :class:`~solderpyro.surrogate.features.FlowStressInputs` (at s0 and at saturation, at
    ``T_ref_C`` and ``rate_ref``).

    For fixed xi, m (and A, s_hat, n) the map is a bijection: ``log sigma_sat`` increases
    with Q/R (the inverse solves for it by bisection), then ``log sigma_0`` with s0. Its
    Jacobian ``dw/du`` is triangular in (s0, Q/R), so ``log |det dw/du| = log |dw_s0/du_s0| +
    log |dw_QR/du_QR|``.

    Args:
        space: the box; must hold s0, QR, xi and m. fixed: A, s_hat, n where not in the box.
        T_ref_C, rate_ref: the reference state (degC, 1/s).
    """

    name = "flow_stress"

    def __init__(self, space: Box, fixed: Mapping[str, float], T_ref_C: float = 125.0,
                 rate_ref: float = 1e-5) -> None:
        from solderpyro.surrogate.features import FlowStressInputs

        super().__init__(space)
        self.fs = FlowStressInputs(space, fixed, T_ref_C, rate_ref)
        self.i_s0, self.i_qr = space.names.index("s0"), space.names.index("QR")
        self.pass_through = tuple(k for k in range(space.dim) if k not in (self.i_s0,
                                                                            self.i_qr))

    def to_w(self, x: np.ndarray) -> np.ndarray:
        return self.fs(torch.as_tensor(np.atleast_2d(np.asarray(x, float)))).numpy()

    def _z(self, x: torch.Tensor) -> torch.Tensor:
        fs = self.fs
        a = fs.param(x, "A")
        log_a = torch.log(a) if isinstance(a, torch.Tensor) else math.log(a)
        return math.log(fs.rate_ref) - log_a + x[..., self.i_qr] / fs.T_ref_K

    def from_w(self, w: np.ndarray) -> np.ndarray:
        from solderpyro.surrogate.features import log_asinh_exp

        W = torch.as_tensor(np.atleast_2d(np.asarray(w, float)))
        sp, fs = self.space, self.fs
        x = sp.from_unit(W)  # right for every pass-through column
        xi, m = x[:, fs.idx["xi"]], x[:, fs.idx["m"]]
        s_hat, n = fs.param(x, "s_hat"), fs.param(x, "n")
        log_sh = torch.log(s_hat) if isinstance(s_hat, torch.Tensor) else math.log(s_hat)

        def g(z: torch.Tensor) -> torch.Tensor:  # log sigma_sat(z), increasing in z
            return log_sh + n * z + log_asinh_exp(m * z) - torch.log(xi)

        lo = torch.full_like(xi, -400.0)
        hi = torch.full_like(xi, 400.0)
        target = W[:, self.i_qr]
        for _ in range(110):  # bisection: 800 / 2^110, well below float64 resolution
            mid = 0.5 * (lo + hi)
            up = g(mid) > target
            hi, lo = torch.where(up, mid, hi), torch.where(up, lo, mid)
        z = 0.5 * (lo + hi)
        a = fs.param(x, "A")
        log_a = torch.log(a) if isinstance(a, torch.Tensor) else math.log(a)
        qr = (z - math.log(fs.rate_ref) + log_a) * fs.T_ref_K
        s0 = torch.exp(W[:, self.i_s0] - log_asinh_exp(m * z) + torch.log(xi))
        x = x.clone()
        x[:, self.i_s0], x[:, self.i_qr] = s0, qr
        bad = ~torch.isfinite(x).all(1) | (z <= -399.0) | (z >= 399.0)
        x[bad] = float("nan")
        return x.numpy()

    def log_det(self, x: np.ndarray) -> np.ndarray:
        from solderpyro.surrogate.features import log_asinh_exp

        X = torch.as_tensor(np.atleast_2d(np.asarray(x, float)))
        sp, fs = self.space, self.fs
        m = X[:, fs.idx["m"]]
        n = fs.param(X, "n")
        v = (m * self._z(X)).detach().requires_grad_(True)
        dpsi = torch.autograd.grad(log_asinh_exp(v).sum(), v)[0]  # d log asinh(e^v) / dv

        def du(k: int) -> torch.Tensor:  # d x_k / d u_k
            lo, hi = sp.lower[k], sp.upper[k]
            return X[:, k] * math.log(hi / lo) if sp.log_scale[k] else \
                torch.full_like(X[:, k], hi - lo)

        d_s0 = du(self.i_s0) / X[:, self.i_s0]
        d_qr = (n + m * dpsi) / fs.T_ref_K * du(self.i_qr)
        return (torch.log(d_s0.abs()) + torch.log(d_qr.abs())).detach().numpy()

    def jac(self, x: np.ndarray) -> np.ndarray:
        u = self.space.to_unit(torch.as_tensor(np.asarray(x, float)))

        def f(uu: torch.Tensor) -> torch.Tensor:
            return self.fs(self.space.from_unit(uu))

        return torch.autograd.functional.jacobian(f, u).numpy()


def sampling_coords(space: Box, fixed: Mapping[str, float] | None = None, kind: str = "auto",
                    T_ref_C: float = 125.0, rate_ref: float = 1e-5) -> UnitCoords:
    """The coordinates to sample ``space`` in.

    Args:
        kind: ``"unit"``, ``"flow_stress"`` or ``"auto"`` (flow stresses when the box holds s0,
            QR, xi and m and ``fixed`` gives the other Anand constants, else the unit cube).
        fixed: the Anand constants not in the box (A, s_hat, n), e.g. ``setup.space.defaults``.
    """
    if kind not in ("unit", "flow_stress", "auto"):
        raise ValueError(f"sampling_coords: kind must be 'unit', 'flow_stress' or 'auto', got "
                         f"{kind!r}")
    ok = all(n in space.names for n in ("s0", "QR", "xi", "m")) and fixed is not None and all(
        k in space.names or k in fixed for k in ("A", "s_hat", "n"))
    if kind == "flow_stress" or (kind == "auto" and ok):
        return FlowStressCoords(space, fixed or {}, T_ref_C, rate_ref)
    return UnitCoords(space)
