"""The full-joint KOH log-likelihood for a product design, in Kronecker form.

When every computer-model run at a parameter set reports the same input points (an FE run
reports the same points and times; SEPIA's ball drop reads each drag run at the same heights),
the runs form a product design: ``m_t`` parameter sets times ``m_x`` input points, ``m = m_t
m_x``. The Gaussian kernel of :func:`~.koh.joint_model` is a product over inputs, so on such a
design its simulation block is a Kronecker product, and the whole joint covariance

    S = [[A, B], [B^T, D]],   A = sc2 (R_t (x) R_x + nugget I)               (m, m)
                              B = sc2 r_t(t) (x) R_xo                          (m, n)
                              D = sc2 (R_oo + nugget I) + s2 I                 (n, n)

(``r_t(t)`` the correlation of the runs' parameter sets with the candidate t, ``R_xo`` of the
input grid with the observation inputs) is inverted through the eigendecompositions of the two
small factors, ``R_t = Q_t diag(l_t) Q_t^T`` and ``R_x = Q_x diag(l_x) Q_x^T``: with ``Q = Q_t
(x) Q_x`` and ``E = l_t l_x^T + nugget``, ``A^-1 = Q (sc2 E)^-1 Q^T``, and the ``n x n`` Schur
complement ``C = D - B^T A^-1 B = D - sc2 W^T diag(h) W`` (``W = Q_x^T R_xo``, ``h_b = sum_a
(Q_t^T r_t)_a^2 / E_ab``) carries the observations. ``log|S| = m log sc2 + sum log E +
log|C|``. The gradient ``d ll / d x = 1/2 (a^T dS a + s1^T dS s1 / G - tr(S^-1 dS))`` (``a =
P z``, ``s1 = S^-1 1``, ``G = 1^T S^-1 1``, as :func:`~.fastkoh.joint_flat`) is taken term by
term: every ``dS`` is a Kronecker block, a rank-structured border or the small D, and every
trace reduces to sums over the eigenbasis.

Cost per gradient: two symmetric eigendecompositions (``m_t``, ``m_x``) and products of
``m_t x m_x`` arrays with the ``n`` observation columns, ``O(m_t^3 + m_x^3 + n m (m_t +
m_x))``, against the dense ``(m + n)^3`` Cholesky and inverse. It is the same likelihood:
equal to the dense one to rounding (tests/unit/calibration/test_kronjoint.py, 1e-8 relative).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.linalg import lapack

if TYPE_CHECKING:
    from solderpyro.calibration.koh import JointInputs

#: below this many runs the dense Cholesky is as cheap: one gradient, one thread, 1 shared
#: correlation, 5 observations: 100 runs 0.14 ms dense / 0.20 ms here, 144 runs 0.27 / 0.21,
#: 400 runs 2.4 / 0.29 (python benchmarks/kron_gradient.py; the crossover is ~120
#: runs)
MIN_RUNS = 128


@dataclass(frozen=True)
class ProductDesign:
    """A simulation design that is every parameter set crossed with every input point.

    Attributes:
        order: ``(m,)`` the run indices in grid order (parameter set major: run ``order[a m_x
            + b]`` is parameter set ``a`` at input point ``b``).
        x: ``(m_x, n_x)`` the input points; t: ``(m_t, p)`` the parameter sets (unit cube).
    """

    order: np.ndarray
    x: np.ndarray
    t: np.ndarray


def product_design(u_sim: np.ndarray, n_x: int) -> ProductDesign | None:
    """The product structure of ``u_sim (m, n_x + p)`` (unit-cube runs, inputs first), or None
    when some parameter set misses some input point, repeats one, or either factor has a
    single level (nothing to gain)."""
    if n_x < 1 or u_sim.shape[1] <= n_x:
        return None
    x, ix = np.unique(u_sim[:, :n_x], axis=0, return_inverse=True)
    t, it = np.unique(u_sim[:, n_x:], axis=0, return_inverse=True)
    mx, mt = x.shape[0], t.shape[0]
    if mx < 2 or mt < 2 or mx * mt != u_sim.shape[0]:
        return None
    key = it.reshape(-1) * mx + ix.reshape(-1)
    if np.bincount(key, minlength=mx * mt).max() != 1:
        return None
    return ProductDesign(np.argsort(key), x, t)


def _sqdist(a: np.ndarray, b: np.ndarray, ard: bool) -> np.ndarray:
    """Per-dimension squared distances ``(k, len(a), len(b))`` (k = 1, summed, when not ARD)."""
    d = np.moveaxis((a[:, None, :] - b[None, :, :]) ** 2, -1, 0)
    return np.ascontiguousarray(d if ard else d.sum(0, keepdims=True))


def kron_joint(inp: JointInputs, force: bool = False) -> KronJoint | None:
    """The Kronecker likelihood of :func:`~.koh.joint_model`'s inputs where it applies (the
    Gaussian kernel, a constant mean, no discrepancy, a product design of at least
    :data:`MIN_RUNS` runs, or any size with ``force``), else None."""
    if inp.kernel != "gaussian" or inp.mean != "constant" or inp.discrepancy:
        return None
    u_sim = inp.u_sim.detach().cpu().numpy().astype(float)
    u_xo = inp.u_xobs.detach().cpu().numpy().astype(float)
    design = product_design(u_sim, u_xo.shape[1])
    if design is None or not (force or u_sim.shape[0] >= MIN_RUNS):
        return None
    return KronJoint(design, u_xo, inp.z.detach().cpu().numpy().astype(float), inp.ard,
                     inp.nugget, inp.y_scale)


class KronJoint:
    """The log-likelihood of :func:`~.koh.joint_model` (Gaussian kernel, constant mean with
    beta integrated out, no discrepancy) on a product design, with its gradient.

    Args:
        design: :func:`product_design` of the runs; u_xobs: ``(n, n_x)`` observation inputs on
            the unit cube; z: ``(m + n,)`` standardized outputs, runs in their original order
            then observations; ard: one correlation parameter per input (else one shared);
            nugget: as :class:`~.koh.JointInputs`; y_scale: the output standardization.

    The flat vector ``x = (t_unit (p,), sigma, sigma_c, corr (n_corr,))`` (sigma, sigma_c in
    output units) is that of :func:`~.fastkoh.joint_flat`.
    """

    def __init__(self, design: ProductDesign, u_xobs: np.ndarray, z: np.ndarray, ard: bool,
                 nugget: float, y_scale: float) -> None:
        gx, gt = design.x, design.t
        self.mx, self.nx = gx.shape
        self.mt, self.p = gt.shape
        self.m, self.n = self.mx * self.mt, u_xobs.shape[0]
        self.gt, self.ard, self.nugget = gt, ard, nugget
        self.ys2 = y_scale * y_scale
        m = self.m
        self.zs = z[:m][design.order].reshape(self.mt, self.mx)
        self.zo = z[m:].copy()
        self.v_s = np.stack([self.zs, np.ones((self.mt, self.mx))])  # (2, mt, mx): z and 1
        self.v_o = np.stack([self.zo, np.ones(self.n)])  # (2, n)
        self.dx, self.dxo = _sqdist(gx, gx, ard), _sqdist(gx, u_xobs, ard)
        self.doo, self.dt = _sqdist(u_xobs, u_xobs, ard), _sqdist(gt, gt, ard)
        self.eye_n = np.eye(self.n)

    def _solve(self, x: np.ndarray) -> dict | None:
        """Factor S at ``x`` and solve it for [z, 1]; None where S is not positive definite."""
        p, nx = self.p, self.nx
        t, sigma, sigma_c, corr = x[:p], x[p], x[p + 1], x[p + 2:]
        cx, ct = (corr[:nx], corr[nx:]) if self.ard else (corr[:1], corr[:1])
        sc2 = sigma_c * sigma_c / self.ys2
        s2 = sigma * sigma / self.ys2
        rx = np.exp(-np.tensordot(cx, self.dx, 1))  # (mx, mx)
        rxo = np.exp(-np.tensordot(cx, self.dxo, 1))  # (mx, n)
        roo = np.exp(-np.tensordot(cx, self.doo, 1))  # (n, n)
        rtt = np.exp(-np.tensordot(ct, self.dt, 1))  # (mt, mt)
        dtv = self.gt - t[None, :]  # (mt, p)
        dt2 = dtv * dtv
        rt = np.exp(-(dt2 @ ct if self.ard else ct[0] * dt2.sum(1)))  # (mt,)
        if not (np.isfinite(rtt).all() and np.isfinite(rx).all()):
            return None
        lt, qt = np.linalg.eigh(rtt)
        lx, qx = np.linalg.eigh(rx)
        e = lt[:, None] * lx[None, :] + self.nugget  # (mt, mx)
        if not (e.min() > 0.0 and sc2 > 0.0):
            return None
        vt = qt.T @ rt  # (mt,)
        wx = qx.T @ rxo  # (mx, n)
        ie = 1.0 / e
        h = (vt * vt) @ ie  # (mx,)
        c = sc2 * (roo + self.nugget * self.eye_n) + s2 * self.eye_n - sc2 * (wx.T * h) @ wx
        lc, info = lapack.dpotrf(c, lower=1)
        if info != 0:
            return None
        ci, info = lapack.dpotri(lc, lower=1)
        ci = np.tril(ci) + np.tril(ci, -1).T  # C^-1 (n, n)
        logdet = self.m * math.log(sc2) + float(np.log(e).sum()) + 2.0 * float(
            np.log(lc.diagonal()).sum())
        # S^-1 [z, 1] by blocks, the simulation part in the eigenbasis (Q^T v)
        vw = qt.T @ self.v_s @ qx  # (2, mt, mx)
        y0 = vw * (ie / sc2)
        bty = sc2 * (vt @ y0) @ wx  # (2, n): B^T A^-1 v_s
        q = (bty - self.v_o) @ ci  # (2, n)
        yw = y0 + vt[None, :, None] * (q @ wx.T)[:, None, :] * ie  # (2, mt, mx)
        ys = qt @ yw @ qx.T  # (2, mt, mx): S^-1 [z, 1], simulation rows, grid order
        yo = -q
        gg = float(ys[1].sum() + yo[1].sum())  # G = 1^T S^-1 1
        s1z = float(ys[0].sum() + yo[0].sum())  # 1^T S^-1 z
        return dict(sc2=sc2, s2=s2, ct=ct, rx=rx, rxo=rxo, roo=roo, rtt=rtt, dtv=dtv, dt2=dt2,
                    rt=rt, lt=lt, qt=qt, lx=lx, qx=qx, ie=ie, vt=vt, wx=wx, ci=ci,
                    logdet=logdet, yw=yw, ys=ys, yo=yo, gg=gg, s1z=s1z)

    def beta(self, x: np.ndarray) -> tuple[float, float]:
        """beta | rest for the constant mean: ``(beta_hat, var)`` in standardized units (as
        :func:`~.koh.joint_loglik` returns them)."""
        f = self._solve(x)
        if f is None:
            raise np.linalg.LinAlgError("the joint covariance is not positive definite")
        return f["s1z"] / f["gg"], 1.0 / f["gg"]

    def __call__(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        """``x (d,)`` -> ``(ll, d ll / dx (d,))``: the same function as the dense one in
        :func:`~.fastkoh.joint_flat` (-inf where S is not positive definite)."""
        f = self._solve(x)
        if f is None:
            return -math.inf, np.zeros_like(x)
        p, nx = self.p, self.nx
        sigma, sigma_c = x[p], x[p + 1]
        sc2, s2, ct, gg = f["sc2"], f["s2"], f["ct"], f["gg"]
        rx, rxo, roo, rtt, rt = f["rx"], f["rxo"], f["roo"], f["rtt"], f["rt"]
        lt, qt, lx, qx, ie, vt, wx, ci = (f[k] for k in ("lt", "qt", "lx", "qx", "ie", "vt",
                                                          "wx", "ci"))
        yw, ys, yo = f["yw"], f["ys"], f["yo"]
        r = f["s1z"] / gg
        a_w, a_s, a_o = yw[0] - r * yw[1], ys[0] - r * ys[1], yo[0] - r * yo[1]  # P z
        za = float((self.zs * a_s).sum() + self.zo @ a_o)
        ll = -0.5 * f["logdet"] - 0.5 * math.log(gg) - 0.5 * za
        # d ll = 1/2 (a^T dS a + s1^T dS s1 / G - tr(S^-1 dS)), term by term
        wts = np.array([1.0, 1.0 / gg])
        vec_w = np.stack([a_w, yw[1]])  # (2, mt, mx) eigenbasis
        vec_s = np.stack([a_s, ys[1]])  # (2, mt, mx) grid
        vec_o = np.stack([a_o, yo[1]])  # (2, n)
        wc = wx @ ci  # (mx, n): Y = U C^-1 in the eigenbasis is vt (x) wc_j / E
        u_w = vt[None, :, None] * wx.T[:, None, :] * ie  # (n, mt, mx): U = A^-1 B
        y_w = vt[None, :, None] * wc.T[:, None, :] * ie  # (n, mt, mx)

        def d_a(mt_w: np.ndarray, mx_w: np.ndarray) -> float:
            """dA = sc2 Q (mt_w (x) mx_w) Q^T (eigenbasis factors; 1-D = diagonal)."""
            def app(v: np.ndarray) -> np.ndarray:
                v = mt_w[:, None] * v if mt_w.ndim == 1 else mt_w @ v
                return v * mx_w if mx_w.ndim == 1 else v @ mx_w
            dmt = mt_w if mt_w.ndim == 1 else mt_w.diagonal()
            dmx = mx_w if mx_w.ndim == 1 else mx_w.diagonal()
            quad = sc2 * float(wts @ (vec_w * app(vec_w)).sum((1, 2)))
            tr = float(dmt @ ie @ dmx) + sc2 * float((u_w * app(y_w)).sum())
            return quad - tr

        def d_b(dmt: np.ndarray, dmxo: np.ndarray) -> float:
            """dB = sc2 dmt (x) dmxo (grid basis: dmt (mt,), dmxo (mx, n)); S^-1's
            simulation-observation block is -U C^-1."""
            quad = 2.0 * sc2 * float(wts @ np.einsum("a,kab,bj,kj->k", dmt, vec_s, dmxo, vec_o))
            tr = -2.0 * sc2 * float((vt * (qt.T @ dmt)) @ ie @ (wc * (qx.T @ dmxo)).sum(1))
            return quad - tr

        def d_d(dd: np.ndarray) -> float:
            """dD (n, n); S^-1's observation block is C^-1."""
            quad = float(wts @ np.einsum("ki,ij,kj->k", vec_o, dd, vec_o))
            return quad - float((ci * dd).sum())

        g = np.empty_like(x)
        tr_ci = float(ci.trace())
        # s2: dS = diag(0_m, 1_n)
        g[p] = 0.5 * (float(wts @ (vec_o * vec_o).sum(1)) - tr_ci) * 2.0 * sigma / self.ys2
        # sc2: dS = (S - s2 diag(0_m, 1_n)) / sc2, with a^T S a = z^T a and s1^T S s1 = G
        ao2, so2 = float(a_o @ a_o), float(yo[1] @ yo[1])
        d_sc2 = 0.5 * ((za - s2 * ao2) + (gg - s2 * so2) / gg
                       - (self.m + self.n - s2 * tr_ci)) / sc2
        g[p + 1] = d_sc2 * 2.0 * sigma_c / self.ys2
        # correlation parameters: d exp(-c D) / dc = -D exp(-c D)
        ncx = nx if self.ard else 1
        gc = np.zeros(x.shape[0] - p - 2)
        for k in range(ncx):
            drx = qx.T @ (-self.dx[k] * rx) @ qx
            gc[k] += 0.5 * (d_a(lt, drx) + d_b(rt, -self.dxo[k] * rxo)
                            + d_d(-sc2 * self.doo[k] * roo))
        for k in range(self.dt.shape[0]):
            drt = qt.T @ (-self.dt[k] * rtt) @ qt
            d2k = f["dt2"][:, k] if self.ard else f["dt2"].sum(1)
            gc[ncx + k if self.ard else 0] += 0.5 * (d_a(drt, lx) + d_b(-d2k * rt, rxo))
        g[p + 2:] = gc
        # t: only r_t(t) moves, d r_t / dt_k = 2 c_k (t_sim - t_k) r_t
        for k in range(p):
            ck = ct[k] if self.ard else ct[0]
            g[k] = 0.5 * d_b(2.0 * ck * f["dtv"][:, k] * rt, rxo)
        return ll, g
