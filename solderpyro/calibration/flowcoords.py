"""The coordinates NUTS samples the Anand constants in when the surrogate sees flow stresses.

Why (measured, BENCHMARKS.md, "Per-gradient and per-round costs of the calibration",
``benchmarks/posterior_geometry.py``): on full-field data the posterior of (s0, Q/R, xi, m) is a
thin curved ridge along which the solder's flow stress at the cycle's rates stays what the data say.
In the logit of the box's unit cube (the transform Pyro and NumPyro use for a bounded prior) its
Hessian, whitened by the posterior covariance, has eigenvalues up to 1e4-5e4: NUTS needs step sizes
near 0.01 and hundreds of gradients per draw, and no constant mass matrix fits. In the surrogate's
own inputs (the log flow stresses of :class:`~solderpyro.surrogate.features.FlowStressInputs`, xi
and m on the unit scale) the same Hessian is 12-52: nearly Gaussian. But those inputs fill a curved
region, not a box, and hard walls at its faces made NUTS diverge (25-63 divergent transitions per
chain where the posterior touches the Q/R face).

:class:`SoftFlowCoords` keeps the flow-stress inputs and makes the walls soft. A triangular
bijection from ``q (4,)`` in R^4 onto the open box, in this order:

- ``t_xi = soft(q_xi; 0, 1)``, ``t_m = soft(q_m; 0, 1)`` (unit-cube values of xi and m);
- ``y_sat = soft(q_sat; a_sat, b_sat)``: the log saturation flow stress, between its values at
  the Q/R bounds for this xi, m; Q/R solves ``y_sat(Q/R) = y_sat`` (monotone, Newton);
- ``y_0 = soft(q_0; a_0, b_0)``: the log initial flow stress, between its values at the s0
  bounds; ``s0 = exp(y_0 - common)``;

with ``soft(q; a, b) = a + e softplus((q - a)/e) - e softplus((q - b)/e)``, ``e = frac (b - a)``:
the identity ``y = q`` more than a few ``e`` inside the interval, and a smooth exponential
approach to each face outside it (``frac = 0.01``: the whitened Hessian on the clean
full-field posterior 11-58, the surrogate inputs' own 12-52; ``frac = 0.05``: 82-314). The
density on ``q`` is the uniform prior's ``p(t)`` times ``|det dt/dq|``, the product of the
diagonal derivatives (the map is triangular). The gradient is analytic (reverse mode by
hand, checked against torch autograd in ``tests/unit/calibration/test_flowcoords.py``): this is
evaluated at every leapfrog step, where torch's per-operation overhead cost 2 ms against the
likelihood's 0.25 ms (measured).

It applies when the calibration box holds s0, QR, xi and m and A, s_hat, n are fixed
(:meth:`SoftFlowCoords.applies`); other parameters keep the logit.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from solderpyro.params import Box

#: The soft walls' width, a fraction of each interval (see the module docstring).
FRAC = 0.01
#: The parameters the transform replaces, in its ``q`` order of use.
NAMES = ("s0", "QR", "xi", "m")


def _logsig(a: float) -> float:
    """log(sigmoid(a)) without overflow."""
    return -math.log1p(math.exp(-a)) if a >= 0 else a - math.log1p(math.exp(a))


def _softplus(a: float) -> float:
    return a + math.log1p(math.exp(-a)) if a > 0 else math.log1p(math.exp(a))


def soft(q: float, a: float, b: float, e: float) -> tuple[float, ...]:
    """The soft-walled map ``R -> (a, b)`` (``b - a >> e > 0``) at ``q``, and its partials.

    Returns:
        ``(y, ld, dy/dq, dy/da, dy/db, dy/de, dld/dq, dld/da, dld/db, dld/de)`` with
        ``ld = log dy/dq``.
    """
    A, B = (q - a) / e, (q - b) / e
    lsA, lsB, l1A, l1B = _logsig(A), _logsig(B), _logsig(-A), _logsig(-B)
    if A + B < 0:  # below the middle: both sigmoids small, D = sA (1 - sB/sA)
        ld = lsA + math.log1p(-math.exp(lsB - lsA))
    else:  # above: D = (1 - sB) (1 - (1 - sA)/(1 - sB))
        ld = l1B + math.log1p(-math.exp(l1A - l1B))
    sA, sB = math.exp(lsA), math.exp(lsB)
    spA, spB = _softplus(A), _softplus(B)
    y = a + e * (spA - spB)
    kA, kB = math.exp(lsA + l1A - ld), math.exp(lsB + l1B - ld)  # s(1-s)/D
    return (y, ld, math.exp(ld), 1.0 - sA, sB, spA - spB - A * sA + B * sB,
            (kA - kB) / e, -kA / e, kB / e, (B * kB - A * kA) / e)


def soft_inverse(y: float, a: float, b: float, e: float) -> float:
    """``q`` with ``soft(q; a, b, e)[0] = y`` for ``a < y < b`` (closed form)."""
    d1, d2 = (y - a) / e, (b - y) / e
    return a + e * (math.log(math.expm1(d1)) - math.log(-math.expm1(-d2)))


def _h(w: float) -> tuple[float, float, float]:
    """``h(w) = log asinh(e^w)`` and its first two derivatives, stable for any real w."""
    if w > 0:
        r = math.sqrt(1.0 + math.exp(-2.0 * w))  # sqrt(1 + e^2w) / e^w
        ash = w + math.log1p(r)  # asinh(e^w)
        h1 = 1.0 / (ash * r)
        sa_r = ash / r  # e^w asinh / sqrt(1 + e^2w)
    elif w > -30.0:
        s = math.exp(w)
        ash, rr = math.asinh(s), math.sqrt(1.0 + s * s)
        h1 = s / (ash * rr)
        sa_r = s * ash / rr
    else:  # asinh(s) = s (1 - s^2/6): h = w - s^2/6, h' = 1 - s^2/3
        s2 = math.exp(2.0 * w)
        return w - s2 / 6.0, 1.0 - s2 / 3.0, -2.0 * s2 / 3.0
    return math.log(ash), h1, h1 * (1.0 - h1 * (1.0 + sa_r))


class _SoftMaps(NamedTuple):
    """The four :func:`soft` maps of :meth:`SoftFlowCoords.forward` (each ``soft``'s tuple of
    value, log slope and partials): xi's, m's, the saturation stress's and the initial
    stress's."""

    xi: tuple[float, ...]
    m: tuple[float, ...]
    sat: tuple[float, ...]
    init: tuple[float, ...]


class _SaturationSolve(NamedTuple):
    """The solve for ``z = lr + (Q/R) / T`` in :meth:`SoftFlowCoords.forward`: ``z``,
    ``G(z, m)``'s partials ``dG/dz``, ``dG/dm``, ``h'(mz)``, ``h''(mz)``, and ``dG/dm`` at
    the interval's ends ``za``, ``zb``."""

    z: float
    Gz: float
    Gm: float
    h1: float
    h2: float
    Gma: float
    Gmb: float


class _PhysicalValues(NamedTuple):
    """The physical values of :meth:`SoftFlowCoords.forward` and their unit maps: xi and m
    with ``dx/dt``; s0 (MPa); the log slopes ``log dt/dx`` of s0 and Q/R and their
    derivatives in x."""

    xi: float
    dxi: float
    m: float
    dm: float
    s0: float
    lt_s0: float
    dlt_s0: float
    lt_qr: float
    dlt_qr: float


class SoftFlowCoords:
    """Soft-walled flow-stress coordinates for NUTS (see the module docstring).

    Args:
        box: the calibration box (unit cube = the theta site); holds s0, QR, xi, m.
        fixed: values of A (1/s), s_hat (MPa) and n (-) (not in the box).
        T_ref_C, rate_ref: the reference state of the surrogate's flow-stress inputs (degC,
            1/s).
        frac: the soft walls' width as a fraction of each interval.

    Attributes:
        idx: ``(4,)`` positions of s0, QR, xi, m in the theta vector.
    Raises:
        ValueError when the transform does not apply (:meth:`applies`).
    """

    name = "flow"  #: the suffix of the coordinates' names in a warm start

    def __init__(self, box: Box, fixed: dict[str, float], T_ref_C: float = 125.0,
                 rate_ref: float = 1e-5, frac: float = FRAC) -> None:
        why = self.applies(box, fixed)
        if why:
            raise ValueError(why)
        if not 0.0 < frac < 0.1:
            raise ValueError(f"SoftFlowCoords frac must be in (0, 0.1), got {frac}")
        self.idx = np.array([box.names.index(n) for n in NAMES])
        self.frac = frac
        self.T = T_ref_C + 273.15
        self.lr = math.log(rate_ref) - math.log(fixed["A"])
        self.lsh, self.n = math.log(fixed["s_hat"]), float(fixed["n"])
        lo = [box.lower[k] for k in self.idx]
        hi = [box.upper[k] for k in self.idx]
        self.log = [bool(box.log_scale[k]) for k in self.idx]
        # unit map per coordinate: t = (phi(x) - p0) / pw, phi = log where flagged
        self.p0 = [math.log(v) if g else v for v, g in zip(lo, self.log, strict=True)]
        self.pw = [(math.log(h) if g else h) - p for h, p, g in
                   zip(hi, self.p0, self.log, strict=True)]
        self.za, self.zb = self.lr + lo[1] / self.T, self.lr + hi[1] / self.T
        self.ls0a, self.ls0b = math.log(lo[0]), math.log(hi[0])

    @staticmethod
    def applies(box: Box, fixed: dict[str, float]) -> str:
        """Why the transform does not apply to ``box`` ('' when it does)."""
        missing = [n for n in NAMES if n not in box.names]
        if missing:
            return f"the box has no {', '.join(missing)}"
        free = [n for n in ("A", "s_hat", "n") if n in box.names or n not in fixed]
        if free:
            return f"{', '.join(free)} not fixed"
        return ""

    def _x(self, k: int, t: float) -> tuple[float, float]:
        """Physical value of coordinate ``k`` at unit value ``t``, and ``dx/dt``."""
        v = self.p0[k] + self.pw[k] * t
        if self.log[k]:
            x = math.exp(v)
            return x, x * self.pw[k]
        return v, self.pw[k]

    def _t(self, k: int, x: float) -> tuple[float, float, float]:
        """Unit value of coordinate ``k`` at physical ``x``, ``log dt/dx`` and its
        derivative in ``x``."""
        if self.log[k]:
            return (math.log(x) - self.p0[k]) / self.pw[k], -math.log(x * self.pw[k]), -1 / x
        return (x - self.p0[k]) / self.pw[k], -math.log(self.pw[k]), 0.0

    def _G(self, z: float, m: float) -> tuple[float, float, float, float, float]:
        """``G(z, m) = n z + h(m z)``, ``dG/dz``, ``dG/dm``, and ``h'(mz)``, ``h''(mz)``."""
        h, h1, h2 = _h(m * z)
        return self.n * z + h, self.n + m * h1, z * h1, h1, h2

    def _solve_z(self, target: float, m: float) -> float:
        """``z`` in ``[za, zb]`` with ``G(z, m) = target`` (G increasing; Newton, bisection
        safeguard)."""
        lo, hi = self.za, self.zb
        z = 0.5 * (lo + hi)
        for _ in range(100):
            g, gz = self._G(z, m)[:2]
            f = g - target
            if f > 0:
                hi = z
            else:
                lo = z
            zn = z - f / gz
            if not lo <= zn <= hi:
                zn = 0.5 * (lo + hi)
            if abs(zn - z) <= 1e-14 * (1.0 + abs(z)):
                return zn
            z = zn
        return z

    def forward(self, q: np.ndarray) -> tuple[np.ndarray, float, Callable[[np.ndarray],
                                                                           np.ndarray]]:
        """``q (4,)`` -> unit-cube values ``t (4,)`` of (s0, QR, xi, m), ``log |det dt/dq|``,
        and ``vjp``: ``vjp(gt (4,)) -> (4,)`` the gradient in ``q`` of ``gt . t +
        log |det dt/dq|`` (``gt``: the log likelihood's gradient in ``t``)."""
        F = self.frac
        # xi, m
        sx = soft(float(q[2]), 0.0, 1.0, F)
        sm = soft(float(q[3]), 0.0, 1.0, F)
        t_xi, t_m = sx[0], sm[0]
        xi, dxi = self._x(2, t_xi)
        m, dm = self._x(3, t_m)
        base = self.lsh - math.log(xi)
        Ga, _, Gma, _, _ = self._G(self.za, m)
        Gb, _, Gmb, _, _ = self._G(self.zb, m)
        a2, b2, e2 = base + Ga, base + Gb, F * (Gb - Ga)
        s2 = soft(float(q[1]), a2, b2, e2)
        y2 = s2[0]
        z = self._solve_z(y2 - base, m)
        G, Gz, Gm, h1, h2 = self._G(z, m)
        qr = (z - self.lr) * self.T
        t_qr, lt_qr, dlt_qr = self._t(1, qr)
        common = G - self.n * z - math.log(xi)  # h(mz) - log xi
        a1, e1 = self.ls0a + common, F * (self.ls0b - self.ls0a)
        b1 = self.ls0b + common
        s1 = soft(float(q[0]), a1, b1, e1)
        s0 = math.exp(s1[0] - common)
        t_s0, lt_s0, dlt_s0 = self._t(0, s0)
        ld = (sx[1] + sm[1] + s2[1] + math.log(self.T) - math.log(Gz) + lt_qr
              + s1[1] + math.log(s0) + lt_s0)
        t = np.clip([t_s0, t_qr, t_xi, t_m], 0.0, 1.0)

        soft_maps = _SoftMaps(sx, sm, s2, s1)
        sat = _SaturationSolve(z, Gz, Gm, h1, h2, Gma, Gmb)
        phys = _PhysicalValues(xi, dxi, m, dm, s0, lt_s0, dlt_s0, lt_qr, dlt_qr)

        def vjp(g: np.ndarray) -> np.ndarray:
            return self._reverse(g, soft_maps, sat, phys)
        return t, ld, vjp

    def _reverse(self, g: np.ndarray, soft_maps: _SoftMaps, sat: _SaturationSolve,
                 phys: _PhysicalValues) -> np.ndarray:
        """The reverse pass of :meth:`forward` from its saved values: adjoints of
        ``g . t + ld``, ``g (4,)`` -> ``(4,)``."""
        F = self.frac
        sx, sm, s2, s1 = soft_maps
        z, Gz, Gm, h1, h2, Gma, Gmb = sat
        xi, dxi, m, dm, s0, lt_s0, dlt_s0, lt_qr, dlt_qr = phys
        b_s0 = g[0] * math.exp(lt_s0) + 1.0 / s0 + dlt_s0
        b_y1 = b_s0 * s0
        b_common = -b_s0 * s0
        gq = np.zeros(4)
        gq[0] = b_y1 * s1[2] + s1[6]
        b_a1 = b_y1 * s1[3] + s1[7]
        b_b1 = b_y1 * s1[4] + s1[8]
        b_common += b_a1 + b_b1
        b_z = b_common * m * h1
        b_m = b_common * z * h1
        b_xi = -b_common / xi
        b_qr = g[1] * math.exp(lt_qr) + dlt_qr
        b_z += b_qr * self.T
        # -log Gz, Gz = n + m h'(mz)
        b_z += -(m * m * h2) / Gz
        b_m += -(h1 + m * z * h2) / Gz
        # z implicit: G(z, m) = y2 - base, base = lsh - log xi
        b_y2 = b_z / Gz
        b_m += -b_z * Gm / Gz
        b_xi += b_z / (xi * Gz)
        gq[1] = b_y2 * s2[2] + s2[6]
        b_a2 = b_y2 * s2[3] + s2[7]
        b_b2 = b_y2 * s2[4] + s2[8]
        b_e2 = b_y2 * s2[5] + s2[9]
        b_xi += -(b_a2 + b_b2) / xi
        b_m += b_a2 * Gma + b_b2 * Gmb + b_e2 * F * (Gmb - Gma)
        b_txi = g[2] + b_xi * dxi
        b_tm = g[3] + b_m * dm
        gq[2] = b_txi * sx[2] + sx[6]
        gq[3] = b_tm * sm[2] + sm[6]
        return gq

    def inverse(self, t: np.ndarray) -> np.ndarray:
        """Unit-cube values ``t (4,)`` of (s0, QR, xi, m), inside the open cube -> ``q (4,)``
        (values at a face are moved 1e-9 inside)."""
        F = self.frac
        t = np.clip(np.asarray(t, dtype=float), 1e-9, 1.0 - 1e-9)
        s0 = self._x(0, float(t[0]))[0]
        qr = self._x(1, float(t[1]))[0]
        xi = self._x(2, float(t[2]))[0]
        m = self._x(3, float(t[3]))[0]
        z = self.lr + qr / self.T
        base = self.lsh - math.log(xi)
        Ga, Gb, Gz = self._G(self.za, m)[0], self._G(self.zb, m)[0], self._G(z, m)[0]
        q_sat = soft_inverse(base + Gz, base + Ga, base + Gb, F * (Gb - Ga))
        common = _h(m * z)[0] - math.log(xi)
        q0 = soft_inverse(math.log(s0) + common, self.ls0a + common, self.ls0b + common,
                          F * (self.ls0b - self.ls0a))
        return np.array([q0, q_sat, soft_inverse(float(t[2]), 0.0, 1.0, F),
                         soft_inverse(float(t[3]), 0.0, 1.0, F)])
