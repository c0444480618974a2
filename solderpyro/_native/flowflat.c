/* The whole log density and gradient of the full-field posterior NUTS samples, in one call:
 * solderpyro.calibration.flat.FlatModel.logp_and_grad for the model pca_flat builds with the
 * soft-walled flow-stress coordinates (calibration/flowcoords.py, SoftFlowCoords) and no
 * observation offsets: the sites' transforms and log-Jacobians, the flow coordinates' forward
 * map, the GP input map (reduced.GPInputMap with surrogate.features.FlowStressInputs, A, s_hat
 * and n fixed), the reduced likelihood (reduced.c) and every chain rule back. The same
 * formulas in the same order as the Python, which stays the reference and the fallback
 * (tests/unit/calibration/test_reduced.py checks the two agree). Why: with the reduced likelihood in C,
 * the Python around it was 55 of the 94 us of a gradient (BENCHMARKS.md, "Per-gradient and
 * per-round costs of the calibration").
 *
 * dims: p (calibrated parameters = GP inputs), sigma_positive (1: LogNormal(mu, sd) on log
 *       sigma; 0: uniform on [lo, lo + w], logit), i_s0, i_qr, i_xi, i_m (positions in theta)
 * par:  [0] mu or lo, [1] sd or w (the sigma site); [2] T_ref (K), [3] log(rate_ref / A),
 *       [4] log s_hat, [5] n, [6] frac, [7] za, [8] zb, [9] ls0a, [10] ls0b,
 *       [11..14] p0, [15..18] pw, [19..22] log flags of (s0, QR, xi, m) (flow coordinates);
 *       then per GP input (p each): lo_t, w_t, log_t (the calibration box), lo_g, w_g, log_g
 *       (the GP box), in_lo, in_span (the input map's range)
 * rdims, rptr, rsc: the reduced kernel's (reduced.c)
 * q:    (p + 1) the flat vector; out: lp, gradient (p + 1); work: the reduced kernel's work
 *       plus 16 + 8 p doubles (sp_flowflat_work_size)
 * Returns 0 (a non-finite density is returned as -inf or NaN, as the Python does).
 */
#include <math.h>
#include <string.h>

long sp_reduced_work_size(const long *dims);
int sp_reduced_loglik(const long *dims, void *const *ptr, const double *sc, const double *u,
                      double sigma, double *out, double *work);

#define HALF_LOG_2PI 0.91893853320467274

long sp_flowflat_work_size(const long *rdims, long p) {
    return sp_reduced_work_size(rdims) + 2 + p + 2 * rdims[0] + 16 + 8 * p + p * p;
}

static double logsig(double a) { return a >= 0 ? -log1p(exp(-a)) : a - log1p(exp(a)); }

static double softplus(double a) { return a > 0 ? a + log1p(exp(-a)) : log1p(exp(a)); }

/* flowcoords.soft: (y, ld, dy/dq, dy/da, dy/db, dy/de, dld/dq, dld/da, dld/db, dld/de) */
static void soft(double q, double a, double b, double e, double *o) {
    double A = (q - a) / e, B = (q - b) / e;
    double lsA = logsig(A), lsB = logsig(B), l1A = logsig(-A), l1B = logsig(-B), ld;
    if (A + B < 0) ld = lsA + log1p(-exp(lsB - lsA));
    else ld = l1B + log1p(-exp(l1A - l1B));
    double sA = exp(lsA), sB = exp(lsB), spA = softplus(A), spB = softplus(B);
    double kA = exp(lsA + l1A - ld), kB = exp(lsB + l1B - ld);
    o[0] = a + e * (spA - spB);
    o[1] = ld;
    o[2] = exp(ld);
    o[3] = 1.0 - sA;
    o[4] = sB;
    o[5] = spA - spB - A * sA + B * sB;
    o[6] = (kA - kB) / e;
    o[7] = -kA / e;
    o[8] = kB / e;
    o[9] = (B * kB - A * kA) / e;
}

/* flowcoords._h: log asinh(e^w) and its first two derivatives */
static void hfun(double w, double *h, double *h1, double *h2) {
    double ash, sa_r;
    if (w > 0) {
        double r = sqrt(1.0 + exp(-2.0 * w));
        ash = w + log1p(r);
        *h1 = 1.0 / (ash * r);
        sa_r = ash / r;
    } else if (w > -30.0) {
        double s = exp(w), rr;
        ash = asinh(s);
        rr = sqrt(1.0 + s * s);
        *h1 = s / (ash * rr);
        sa_r = s * ash / rr;
    } else {
        double s2 = exp(2.0 * w);
        *h = w - s2 / 6.0;
        *h1 = 1.0 - s2 / 3.0;
        *h2 = -2.0 * s2 / 3.0;
        return;
    }
    *h = log(ash);
    *h2 = *h1 * (1.0 - *h1 * (1.0 + sa_r));
}

typedef struct {
    double T, lr, lsh, n, F, za, zb, ls0a, ls0b, p0[4], pw[4];
    int lg[4];
} Flow;

/* G(z, m) = n z + h(m z): G, dG/dz, dG/dm, h', h'' */
static void Gfun(const Flow *f, double z, double m, double *o) {
    double h, h1, h2;
    hfun(m * z, &h, &h1, &h2);
    o[0] = f->n * z + h;
    o[1] = f->n + m * h1;
    o[2] = z * h1;
    o[3] = h1;
    o[4] = h2;
}

static double solve_z(const Flow *f, double target, double m) {
    double lo = f->za, hi = f->zb, z = 0.5 * (lo + hi), g[5];
    for (int it = 0; it < 100; ++it) {
        Gfun(f, z, m, g);
        double fv = g[0] - target;
        if (fv > 0) hi = z;
        else lo = z;
        double zn = z - fv / g[1];
        if (!(lo <= zn && zn <= hi)) zn = 0.5 * (lo + hi);
        if (fabs(zn - z) <= 1e-14 * (1.0 + fabs(z))) return zn;
        z = zn;
    }
    return z;
}

static void xfun(const Flow *f, int k, double t, double *x, double *dx) {
    double v = f->p0[k] + f->pw[k] * t;
    if (f->lg[k]) {
        *x = exp(v);
        *dx = *x * f->pw[k];
    } else {
        *x = v;
        *dx = f->pw[k];
    }
}

static void tfun(const Flow *f, int k, double x, double *t, double *lt, double *dlt) {
    if (f->lg[k]) {
        *t = (log(x) - f->p0[k]) / f->pw[k];
        *lt = -log(x * f->pw[k]);
        *dlt = -1.0 / x;
    } else {
        *t = (x - f->p0[k]) / f->pw[k];
        *lt = -log(f->pw[k]);
        *dlt = 0.0;
    }
}

static double clip01(double t) { return t < 0.0 ? 0.0 : (t > 1.0 ? 1.0 : t); }

int sp_flowflat(const long *dims, const double *par, const long *rdims, void *const *rptr,
                const double *rsc, const double *q, double *out, double *work) {
    long p = dims[0];
    int sig_pos = (int)dims[1];
    int ix[4] = {(int)dims[2], (int)dims[3], (int)dims[4], (int)dims[5]};
    const double *lo_t = par + 23, *w_t = lo_t + p, *log_t = w_t + p, *lo_g = log_t + p,
                 *w_g = lo_g + p, *log_g = w_g + p, *in_lo = log_g + p, *in_span = in_lo + p;
    long K = rdims[0];
    double *rw = work, *rout = rw + sp_reduced_work_size(rdims);
    double *t = rout + 2 + p + 2 * K, *dxdt = t + p, *x = dxdt + p, *f = x + p, *u = f + p,
           *gt = u + p, *gx = gt + p, *gq = gx + p, *J = gq + p + 16;  /* J: (p, p) */
    Flow fl = {par[2], par[3], par[4], par[5], par[6], par[7], par[8], par[9], par[10],
               {par[11], par[12], par[13], par[14]}, {par[15], par[16], par[17], par[18]},
               {(int)par[19], (int)par[20], (int)par[21], (int)par[22]}};
    int is_flow[64] = {0};
    for (int k = 0; k < 4; ++k) is_flow[ix[k]] = 1;

    /* the sites: unit-interval theta coordinates (logit) other than the flow ones, sigma */
    double lj = 0.0, grad[65], dx[65];
    for (long i = 0; i < p; ++i) {
        if (is_flow[i]) continue;
        double s = 1.0 / (1.0 + exp(-q[i])), a = fabs(q[i]);
        t[i] = s;
        dx[i] = s * (1.0 - s);
        grad[i] = 1.0 - 2.0 * s;
        lj += -a - 2.0 * log1p(exp(-a));
    }
    double sigma;
    if (sig_pos) {
        double z = (q[p] - par[0]) / par[1];
        sigma = exp(q[p]);
        dx[p] = sigma;
        lj += -0.5 * z * z - (log(par[1]) + HALF_LOG_2PI);
        grad[p] = -z / par[1];
    } else {
        double s = 1.0 / (1.0 + exp(-q[p])), a = fabs(q[p]);
        sigma = par[0] + par[1] * s;
        dx[p] = par[1] * s * (1.0 - s);
        grad[p] = 1.0 - 2.0 * s;
        lj += -a - 2.0 * log1p(exp(-a));
    }

    /* the flow coordinates (SoftFlowCoords.forward) */
    double F = fl.F, sx[10], sm[10], s2[10], s1[10], g5[5], Ga[5], Gb[5];
    soft(q[ix[2]], 0.0, 1.0, F, sx);
    soft(q[ix[3]], 0.0, 1.0, F, sm);
    double xi, dxi, m, dm;
    xfun(&fl, 2, sx[0], &xi, &dxi);
    xfun(&fl, 3, sm[0], &m, &dm);
    double base = fl.lsh - log(xi);
    Gfun(&fl, fl.za, m, Ga);
    Gfun(&fl, fl.zb, m, Gb);
    soft(q[ix[1]], base + Ga[0], base + Gb[0], F * (Gb[0] - Ga[0]), s2);
    double z = solve_z(&fl, s2[0] - base, m);
    Gfun(&fl, z, m, g5);
    double Gz = g5[1], Gm = g5[2], h1 = g5[3], h2 = g5[4];
    double qr = (z - fl.lr) * fl.T, t_qr, lt_qr, dlt_qr;
    tfun(&fl, 1, qr, &t_qr, &lt_qr, &dlt_qr);
    double common = g5[0] - fl.n * z - log(xi);
    soft(q[ix[0]], fl.ls0a + common, fl.ls0b + common, F * (fl.ls0b - fl.ls0a), s1);
    double s0 = exp(s1[0] - common), t_s0, lt_s0, dlt_s0;
    tfun(&fl, 0, s0, &t_s0, &lt_s0, &dlt_s0);
    lj += sx[1] + sm[1] + s2[1] + log(fl.T) - log(Gz) + lt_qr + s1[1] + log(s0) + lt_s0;
    t[ix[0]] = clip01(t_s0);
    t[ix[1]] = clip01(t_qr);
    t[ix[2]] = clip01(sx[0]);
    t[ix[3]] = clip01(sm[0]);

    if (!(sigma * sigma > 0.0)) {  /* sigma (or its square) underflowed: zero density */
        out[0] = -INFINITY;
        for (long i = 0; i <= p; ++i) out[1 + i] = 0.0;
        return 0;
    }

    /* the GP inputs (GPInputMap with FlowStressInputs.value_and_jacobian) */
    for (long l = 0; l < p; ++l) {
        double v = lo_t[l] + t[l] * w_t[l];
        x[l] = log_t[l] != 0.0 ? exp(v) : v;
        dxdt[l] = (log_t[l] != 0.0 ? x[l] : 1.0) * w_t[l];
    }
    memset(J, 0, sizeof(double) * p * p);
    for (long l = 0; l < p; ++l) {
        double zx = log_g[l] != 0.0 ? log(x[l]) : x[l];
        f[l] = (zx - lo_g[l]) / w_g[l];
        J[l * p + l] = (log_g[l] != 0.0 ? 1.0 / x[l] : 1.0) / w_g[l];
    }
    {
        double xs0 = x[ix[0]], xqr = x[ix[1]], xxi = x[ix[2]], xm = x[ix[3]];
        double zz = fl.lr + xqr / fl.T, w = xm * zz;
        double ash = w > -30.0 ? asinh(exp(w < 700.0 ? w : 700.0)) : exp(w);
        double cm = log(ash) - log(xxi), hp;
        if (w >= 0.0) hp = 1.0 / (ash * sqrt(1.0 + exp(-2.0 * w)));
        else hp = (w < -30.0 ? 1.0 : exp(w) / ash) / sqrt(1.0 + exp(2.0 * w));
        double *rs0 = J + ix[0] * p, *rqr = J + ix[1] * p;
        for (long l = 0; l < p; ++l) { rs0[l] = 0.0; rqr[l] = 0.0; }
        double dz_qr = 1.0 / fl.T;
        /* dcommon: hp m dz (QR only), + hp z at m, - 1/xi at xi */
        rs0[ix[1]] = hp * xm * dz_qr;
        rs0[ix[3]] += hp * zz;
        rs0[ix[2]] += -1.0 / xxi;
        for (long l = 0; l < p; ++l) rqr[l] = rs0[l];
        rqr[ix[1]] += fl.n * dz_qr;
        rs0[ix[0]] += 1.0 / xs0;
        f[ix[0]] = log(xs0) + cm;
        f[ix[1]] = fl.lsh + fl.n * zz + cm;
    }
    for (long l = 0; l < p; ++l) u[l] = (f[l] - in_lo[l]) / in_span[l];

    /* the reduced likelihood, its gradient back to the theta coordinates */
    if (sp_reduced_loglik(rdims, rptr, rsc, u, sigma, rout, rw) != 0) {
        out[0] = -INFINITY;
        for (long i = 0; i <= p; ++i) out[1 + i] = 0.0;
        return 0;
    }
    double ll = rout[0], gs = rout[1 + p];
    for (long j = 0; j < p; ++j) {
        double s = 0.0;
        for (long l = 0; l < p; ++l) s += rout[1 + l] * J[l * p + j] / in_span[l];
        gt[j] = s * dxdt[j];
    }

    /* the flat gradient: the logit sites, sigma, then the flow coordinates' reverse pass */
    for (long i = 0; i < p; ++i)
        if (!is_flow[i]) gq[i] = grad[i] + gt[i] * dx[i];
    gq[p] = grad[p] + gs * dx[p];
    {
        double g0 = gt[ix[0]], g1 = gt[ix[1]], g2 = gt[ix[2]], g3 = gt[ix[3]];
        double b_s0 = g0 * exp(lt_s0) + 1.0 / s0 + dlt_s0;
        double b_y1 = b_s0 * s0, b_common = -b_s0 * s0;
        gq[ix[0]] = b_y1 * s1[2] + s1[6];
        double b_a1 = b_y1 * s1[3] + s1[7], b_b1 = b_y1 * s1[4] + s1[8];
        b_common += b_a1 + b_b1;
        double b_z = b_common * m * h1, b_m = b_common * z * h1, b_xi = -b_common / xi;
        double b_qr = g1 * exp(lt_qr) + dlt_qr;
        b_z += b_qr * fl.T;
        b_z += -(m * m * h2) / Gz;
        b_m += -(h1 + m * z * h2) / Gz;
        double b_y2 = b_z / Gz;
        b_m += -b_z * Gm / Gz;
        b_xi += b_z / (xi * Gz);
        gq[ix[1]] = b_y2 * s2[2] + s2[6];
        double b_a2 = b_y2 * s2[3] + s2[7], b_b2 = b_y2 * s2[4] + s2[8];
        double b_e2 = b_y2 * s2[5] + s2[9];
        b_xi += -(b_a2 + b_b2) / xi;
        b_m += b_a2 * Ga[2] + b_b2 * Gb[2] + b_e2 * F * (Gb[2] - Ga[2]);
        double b_txi = g2 + b_xi * dxi, b_tm = g3 + b_m * dm;
        gq[ix[2]] = b_txi * sx[2] + sx[6];
        gq[ix[3]] = b_tm * sm[2] + sm[6];
    }
    out[0] = ll + lj;
    for (long i = 0; i <= p; ++i) out[1 + i] = gq[i];
    return 0;
}
