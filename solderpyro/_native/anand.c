/* Fused, no-autograd Anand update at Gauss points (CPU, float64).
 *
 * The same algorithm, point by point, as the torch path of
 * solderpyro/materials/integrate.py (return_map_3d without autograd): elastic trial, the joint
 * Newton on (zeta, s) from a warm start (_return_map_joint), the bracketed fallback with the
 * nested s-solve (_return_map, _solve_s) where the joint Newton fails, the factored consistent
 * tangent (_tangent3d) and the stress / state update. Every point is independent, so the torch
 * path's lock-step iteration (converged points frozen) gives the same iterates as this loop;
 * only the rounding of the elementary functions differs.
 *
 * Broadcasting: a scalar field f (T, dt, eps_th, E, nu, C_k) is read as f[i / div_f] for point
 * i; the parameter rows as prm[9 * (i / div_p) + k]. Mandel 4-vectors (xx, yy, zz, sqrt2*xy).
 */
#include <math.h>
#include <stddef.h>
#include <stdlib.h>
#include <string.h>

#include "pool.h"

#define ZETA_MAX 700.0
#define LN2 0.6931471805599453
#define TINY6 (2.2250738585072014e-308 * 1e6)

static inline double clamp_max(double v, double hi) { return v > hi ? hi : v; }
static inline double clamp_min(double v, double lo) { return v < lo ? lo : v; }
static inline double dmin(double a, double b) { return (a != a) ? a : ((b != b) ? b : (a < b ? a : b)); }
static inline double dmax(double a, double b) { return (a != a) ? a : ((b != b) ? b : (a > b ? a : b)); }

static inline double sigmoid(double z) { return 1.0 / (1.0 + exp(-z)); }

/* log(sigmoid(z)), stable */
static inline double logsigmoid(double z) { return (z < 0.0 ? z : 0.0) - log1p(exp(-fabs(z))); }

/* log(sinh(exp(ly))) */
static inline double log_sinh_of_log(double ly) {
    double y = exp(clamp_max(ly, 700.0));
    if (ly < -18.0) return ly + y * y / 6.0;
    return y + log(-expm1(-2.0 * y)) - LN2;
}

/* y*coth(y), y = exp(ly) */
static inline double y_coth(double ly) {
    double y = exp(clamp_max(ly, 700.0));
    if (ly < -9.0) return 1.0 + y * y / 3.0;
    return y / tanh(y);
}

typedef struct {
    double QR, A, xi, m, h0, s_hat, n, a;
} Anand;

/* hardening residual H and its partials (anand.hardening_residual) */
static inline void hardening(double s, double s_n, double L, double logZ, const Anand *P,
                             double *H, double *dH_ds, double *dH_dL) {
    double s_star = P->s_hat * exp(P->n * logZ);
    double r = 1.0 - s / s_star;
    double ar = fabs(r);
    if (ar < 1e-300) ar = 1e-300;
    double sg = (r > 0.0) ? 1.0 : ((r < 0.0) ? -1.0 : (r == 0.0 ? 0.0 : r));
    double ara = pow(ar, P->a);
    double phi = ara * sg;
    double dphi_dr = P->a * pow(ar, P->a - 1.0);
    double dep = exp(L);
    *H = s - s_n - P->h0 * dep * phi;
    *dH_ds = 1.0 + P->h0 * dep * dphi_dr / s_star;
    *dH_dL = -P->h0 * dep * (phi + dphi_dr * P->n * s / s_star);
}

/* Constants of one point's joint Newton: base = log(q_tr/(3Gk)), lxq = log(xi*q_tr), and their
 * exponentials eb = q_tr/(3Gk), xq = xi*q_tr. */
typedef struct {
    double base, lxq, eb, xq, c, s_n;
} Pt;

/* flow / hardening residuals and the 2x2 Jacobian in (zeta, s) (_partials_raw), with the
 * elementary functions shared: sigmoid(+-zeta) and their logs from one exp(-|zeta|),
 * dep = eb*sigmoid(-zeta), y = exp(ly) = xq*sigmoid(zeta)/s, tanh(y) from expm1(-2y), and
 * ar^(a-1) = ar^a/ar. */
static inline void partials(const Pt *q, double zeta, double s, const Anand *P, double *R,
                            double *H, double J[4], double *yc, double *dH_ds, double *dH_dL) {
    double e = exp(-fabs(zeta));
    double t = log1p(e);
    double opz = 1.0 + e, sg, sgm, lsg, lsgm;
    if (zeta >= 0.0) {
        sg = 1.0 / opz; sgm = e / opz; lsg = -t; lsgm = -zeta - t;
    } else {
        sg = e / opz; sgm = 1.0 / opz; lsg = zeta - t; lsgm = -t;
    }
    double L = q->base + lsgm;
    /* hardening_residual(s, s_n, L, L - c) */
    double s_star = P->s_hat * exp(P->n * (L - q->c));
    double r = 1.0 - s / s_star;
    double ar = fabs(r);
    if (ar < 1e-300) ar = 1e-300;
    double sgn = (r > 0.0) ? 1.0 : ((r < 0.0) ? -1.0 : (r == 0.0 ? 0.0 : r));
    double ara = pow(ar, P->a);
    double phi = ara * sgn;
    double dphi_dr = P->a * (ara / ar);
    double dep = q->eb * sgm;
    *H = s - q->s_n - P->h0 * dep * phi;
    *dH_ds = 1.0 + P->h0 * dep * dphi_dr / s_star;
    *dH_dL = -P->h0 * dep * (phi + dphi_dr * P->n * s / s_star);
    /* flow residual in log form */
    double ly = q->lxq + lsg - log(s);
    double y = ly < 700.0 ? q->xq * sg / s : exp(700.0);
    double lsl, ycv;
    if (ly < -18.0) {
        lsl = ly + y * y / 6.0;
        ycv = 1.0 + y * y / 3.0;
    } else {
        double em = expm1(-2.0 * y);
        lsl = y + log(-em) - LN2;
        ycv = ly < -9.0 ? 1.0 + y * y / 3.0 : y * (2.0 + em) / (-em);
    }
    if (!(ly == ly)) lsl = ycv = ly; /* NaN in, NaN out */
    *R = L - q->c - lsl / P->m;
    *yc = ycv;
    J[0] = -sg - ycv * sgm / P->m;
    J[1] = ycv / (P->m * s);
    J[2] = -*dH_dL * sg;
    J[3] = *dH_ds;
}

/* bracketed Newton for s at fixed L (_solve_s) */
static double solve_s(double L, double c, double s_n, double s_guess, const Anand *P,
                      double *dH_ds, double *dH_dL) {
    double logZ = L - c;
    double s_star = P->s_hat * exp(P->n * logZ);
    double lo = dmin(s_n, s_star), hi = dmax(s_n, s_star);
    double s = dmin(dmax(s_guess, lo), hi);
    double H;
    for (int it = 0; it < 60; ++it) {
        hardening(s, s_n, L, logZ, P, &H, dH_ds, dH_dL);
        if (fabs(H) <= 1e-13 * fabs(s_n) + 1e-300) break;
        if (H < 0) lo = s;
        if (H > 0) hi = s;
        double s_new = s - H / *dH_ds;
        int bad = !((s_new > lo) && (s_new < hi)) || !isfinite(s_new);
        s = bad ? 0.5 * (lo + hi) : s_new;
    }
    hardening(s, s_n, L, logZ, P, &H, dH_ds, dH_dL);
    return s;
}

/* predictor (_initial_zeta) */
static inline double initial_zeta(double log_qtr, double s_n, const Anand *P, double c,
                                  double Gk) {
    double ly = log(P->xi) + log_qtr - log(s_n);
    double d = clamp_max(c + log_sinh_of_log(ly) / P->m - log_qtr + log(3.0 * Gk), -1e-3);
    return -d + log(-expm1(d));
}

/* bracketed Newton on zeta with s(zeta) solved exactly inside (_return_map) */
static void return_map(double log_qtr, double s_n, const Anand *P, double c, double Gk,
                       double zeta0, double *zeta_out, double *s_out) {
    double base = log_qtr - log(3.0 * Gk);
    double lo = -ZETA_MAX, hi = ZETA_MAX;
    double zeta = dmin(dmax(zeta0, -ZETA_MAX + 1), ZETA_MAX - 1);
    double s = s_n, dH_ds, dH_dL;
    double lxi = log(P->xi);
    for (int it = 0; it < 100; ++it) {
        double L = base + logsigmoid(-zeta);
        s = solve_s(L, c, s_n, s, P, &dH_ds, &dH_dL);
        double ly = lxi + log_qtr + logsigmoid(zeta) - log(s);
        double R = L - c - log_sinh_of_log(ly) / P->m;
        if ((fabs(R) < 1e-11) || (hi - lo < 1e-13)) break;
        if (R > 0) lo = zeta;
        if (R < 0) hi = zeta;
        double yc = y_coth(ly);
        double sg = sigmoid(zeta), sgm = sigmoid(-zeta);
        double ds_dz = dH_dL * sg / dH_ds;
        double dR = -sg - yc * sgm / P->m + yc / (P->m * s) * ds_dz;
        double z_new = zeta - R / dR;
        int bad = !((z_new > lo) && (z_new < hi)) || !isfinite(z_new);
        zeta = bad ? 0.5 * (lo + hi) : z_new;
    }
    *zeta_out = zeta;
    *s_out = s;
}

typedef struct {
    const double *eps, *epsp_n, *s_n, *X_n, *prm, *T, *dt, *eth, *E, *nu, *Ck, *guess;
    long d_p, d_T, d_dt, d_eth, d_E, d_nu, d_Ck;
    double *sigma, *epsp, *s_out, *X_out, *dep, *x, *K, *g2, *coef, *nb;
    int tangent;
} Args;

/* One point's data between the phases of the update. */
typedef struct {
    Anand P;
    Pt q;
    double K, G, Gk, Ck, pres, nrm, log_qtr, xi_tr[4];
    int kin;
    double zeta, s;                  /* start, then solution of the joint Newton */
    double yc, dH_ds, dH_dL;         /* tangent ingredients at the solution */
    int done;
} Point;

/* Quantities that depend on the broadcast fields only (a member's constants, temperature...),
 * kept while consecutive points read the same rows. */
typedef struct {
    long key[7];
    int valid;
    Anand P;
    double eth, K, G, Gk, Ck, c, l3g, lxi;
} Group;

static void group(const Args *a, long i, Group *g) {
    long key[7] = {i / a->d_p, i / a->d_T, i / a->d_dt, i / a->d_eth, i / a->d_E, i / a->d_nu,
                   a->Ck ? i / a->d_Ck : 0};
    if (g->valid && memcmp(key, g->key, sizeof key) == 0) return;
    memcpy(g->key, key, sizeof key);
    g->valid = 1;
    const double *pr = a->prm + 9 * key[0];
    Anand P = {pr[1], pr[2], pr[3], pr[4], pr[5], pr[6], pr[7], pr[8]};
    double T = a->T[key[1]], dt = a->dt[key[2]], E = a->E[key[4]], nu = a->nu[key[5]];
    g->P = P;
    g->eth = a->eth[key[3]];
    g->Ck = a->Ck ? a->Ck[key[6]] : 0.0;
    g->K = E / (3.0 * (1.0 - 2.0 * nu));
    g->G = E / (2.0 * (1.0 + nu));
    g->Gk = a->Ck ? g->G + g->Ck / 3.0 : g->G;
    g->c = log(dt * P.A) - P.QR / T;
    g->l3g = log(3.0 * g->Gk);
    g->lxi = log(P.xi);
}

/* elastic trial, constants of the local Newton and its start (_Trial, _initial_zeta) */
static void setup(const Args *a, long i, Point *d, Group *g) {
    group(a, i, g);
    double eth = g->eth, c = g->c;
    d->P = g->P;
    d->kin = a->Ck != NULL;
    d->Ck = g->Ck;
    d->K = g->K;
    d->G = g->G;
    d->Gk = g->Gk;
    double s_n = a->s_n[i];
    const double *ep = a->eps + 4 * i, *pn = a->epsp_n + 4 * i;
    double ee[4] = {ep[0] - pn[0] - eth, ep[1] - pn[1] - eth, ep[2] - pn[2] - eth,
                    ep[3] - pn[3] - eth * 0.0};
    double tr = ee[0] + ee[1] + ee[2];
    d->pres = d->K * tr;
    for (int k = 0; k < 4; ++k) {
        double mk = k < 3 ? 1.0 : 0.0;
        d->xi_tr[k] = 2.0 * d->G * (ee[k] - tr * mk / 3.0);
        if (a->X_n) d->xi_tr[k] -= a->X_n[4 * i + k];
    }
    const double *x = d->xi_tr;
    double ss = x[0] * x[0] + x[1] * x[1] + x[2] * x[2] + x[3] * x[3] + TINY6;
    d->nrm = sqrt(ss);
    d->log_qtr = 0.5 * log(1.5 * ss);
    if (a->guess) {
        d->zeta = a->guess[2 * i];
        d->s = a->guess[2 * i + 1];
    } else {
        d->zeta = initial_zeta(d->log_qtr, s_n, &d->P, c, d->Gk);
        d->s = s_n;
    }
    double q_tr = sqrt(1.5 * ss);
    Pt q = {d->log_qtr - g->l3g, g->lxi + d->log_qtr, q_tr / (3.0 * d->Gk), d->P.xi * q_tr, c,
            s_n};
    d->q = q;
}

/* joint Newton on (zeta, s) from the start (_return_map_joint) */
static void joint(Point *d) {
    double zeta = d->zeta, s = d->s, s_n = d->q.s_n;
    double R, H, J[4], yc = 0.0, dH_ds = 0.0, dH_dL = 0.0;
    int done = 0;
    for (int it = 0; it <= 12; ++it) {
        partials(&d->q, zeta, s, &d->P, &R, &H, J, &yc, &dH_ds, &dH_dL);
        done = (fabs(R) < 1e-11) && (fabs(H) <= 1e-13 * s_n);
        if (it == 12) {
            done = done && isfinite(zeta);
            break;
        }
        if (done) break;
        double det = J[0] * J[3] - J[1] * J[2];
        double dz = -(J[3] * R - J[1] * H) / det;
        double ds = -(J[0] * H - J[2] * R) / det;
        zeta = zeta + (dz < -10.0 ? -10.0 : (dz > 10.0 ? 10.0 : dz));
        s = clamp_min(s + ds, 1e-3 * s_n);
    }
    d->zeta = zeta;
    d->s = s;
    d->yc = yc;
    d->dH_ds = dH_ds;
    d->dH_dL = dH_dL;
    d->done = done;
}

/* fallback where the joint Newton failed, tangent (_tangent3d), stress and state */
static void finish(const Args *a, long i, Point *d) {
    const Anand *P = &d->P;
    double zeta = d->zeta, s = d->s;
    double G = d->G, Gk = d->Gk, Ck = d->Ck;
    if (!d->done) { /* robust nested, bracketed solve */
        double z0 = initial_zeta(d->log_qtr, d->q.s_n, P, d->q.c, Gk);
        return_map(d->log_qtr, d->q.s_n, P, d->q.c, Gk, z0, &zeta, &s);
        if (a->tangent) {
            double R, H, J[4];
            partials(&d->q, zeta, s, P, &R, &H, J, &d->yc, &d->dH_ds, &d->dH_dL);
        }
    }
    a->x[2 * i] = zeta;
    a->x[2 * i + 1] = s;
    a->s_out[i] = s;
    double ez = exp(-fabs(zeta)), opz = 1.0 + ez;
    double sg = zeta >= 0.0 ? 1.0 / opz : ez / opz, sgm = zeta >= 0.0 ? ez / opz : 1.0 / opz;
    if (!(zeta == zeta)) sg = sgm = zeta;
    if (a->tangent) { /* _tangent3d */
        double yc = d->yc, dH_ds = d->dH_ds;
        double emz = zeta >= 0.0 ? ez : (zeta > -700.0 ? 1.0 / ez : exp(700.0));
        if (!(zeta == zeta)) emz = zeta;
        double w = yc * emz / P->m;
        double Fs_dHdL = yc / (P->m * s) * d->dH_dL;
        double bracket = sgm - w * dH_ds / ((1.0 + w) * dH_ds - Fs_dHdL);
        a->K[i] = d->K;
        if (!d->kin) {
            a->g2[i] = 2.0 * G * sg;
            a->coef[i] = 2.0 * G * bracket;
        } else {
            a->g2[i] = 2.0 * G * (sg + sgm * (Ck / 3.0) / Gk);
            a->coef[i] = 2.0 * G * (G / Gk) * bracket;
        }
        for (int k = 0; k < 4; ++k) a->nb[4 * i + k] = d->xi_tr[k] / d->nrm;
    }
    const double *pn = a->epsp_n + 4 * i;
    double f = sgm / (2.0 * Gk);
    for (int k = 0; k < 4; ++k) {
        double mk = k < 3 ? 1.0 : 0.0;
        double dp = f * d->xi_tr[k];
        a->epsp[4 * i + k] = pn[k] + dp;
        double sig = d->pres * mk + sg * d->xi_tr[k];
        if (a->X_out) {
            double X;
            if (d->kin) {
                double dX = (2.0 / 3.0) * Ck * dp;
                X = a->X_n ? a->X_n[4 * i + k] + dX : dX;
            } else {
                X = a->X_n[4 * i + k];
            }
            a->X_out[4 * i + k] = X;
            sig = sig + X;
        }
        a->sigma[4 * i + k] = sig;
    }
    a->dep[i] = d->q.eb * sgm;
}

#include "anand_simd.h"

/* points [i0, i1) */
static void range(const Args *a, long i0, long i1, int simd) {
    Point d[4];
    Group g;
    g.valid = 0;
    long i = i0;
#ifdef SP_SIMD4
    if (simd) {
        Group g4[4];
        g4[3].valid = 0;
        for (; i + 4 <= i1; i += 4) {
            g4[0] = g4[3];
            point4(a, i, g4);
        }
        g = g4[3];
    }
#endif
    (void)simd;
    for (; i < i1; ++i) {
        setup(a, i, &d[0], &g);
        joint(&d[0]);
        finish(a, i, &d[0]);
    }
}

typedef struct {
    const Args *a;
    long n, chunk;
    int simd;
} Job;

static void run_range(void *ctx, long c) {
    const Job *j = (const Job *)ctx;
    long i0 = c * j->chunk, i1 = i0 + j->chunk < j->n ? i0 + j->chunk : j->n;
    range(j->a, i0, i1, j->simd);
}

/* Entry point; see solderpyro/_native/__init__.py (anand_update) for the arguments. simd: use
 * the 4-lane joint Newton where compiled in (else the scalar one; the same iterates). */
int sp_anand_update(long n, const double *eps, const double *epsp_n, const double *s_n,
                    const double *X_n, const double *prm, const double *T, const double *dt,
                    const double *eth, const double *E, const double *nu, const double *Ck,
                    const long *div, const double *guess, int tangent, double *sigma,
                    double *epsp, double *s_out, double *X_out, double *dep, double *x,
                    double *K, double *g2, double *coef, double *nb, int nthreads, int simd) {
    Args a = {eps, epsp_n, s_n, X_n, prm, T, dt, eth, E, nu, Ck, guess,
              div[0], div[1], div[2], div[3], div[4], div[5], div[6],
              sigma, epsp, s_out, X_out, dep, x, K, g2, coef, nb, tangent};
    Job job = {&a, n, 256, simd};
    sp_parallel((n + job.chunk - 1) / job.chunk, nthreads, run_range, &job);
    return 0;
}

/* Whether the 4-lane path is compiled in. */
int sp_simd_width(void) {
#ifdef SP_SIMD4
    return 4;
#else
    return 1;
#endif
}

/* ------------------------------------------------------------------------------------------
 * Fused evaluation of the solder layer (SpecimenSolver._eval without a band): strains from the
 * retained displacements, the Anand update, the plane-stress condensation of the in-plane
 * stress on eps_zz (Tangent3D.col_zz) and the internal forces assembled on the retained dofs.
 * Points are ordered (b, n_e, n_qp); edof (n_e, 8) points a fixed dof at dof 0 with zero B
 * columns, as in the solver.
 */
static const int IP3[3] = {0, 1, 3};

/* in-plane strains B u_e at the points of element je = j*ne + e (of member j) */
static inline void strain_elem(long je, long ne, long nq, long n_r, const double *u,
                               const int *edof, const double *B, double *ev /* (nq, 3) */) {
    long e = je % ne, j = je / ne;
    const double *uj = u + n_r * j;
    const int *ed = edof + 8 * e;
    double ue[8];
    for (int a = 0; a < 8; ++a) ue[a] = uj[ed[a]];
    for (long q = 0; q < nq; ++q)
        for (int k = 0; k < 3; ++k) {
            const double *b = B + 24 * (e * nq + q) + 8 * k;
            ev[3 * q + k] = ((b[0] * ue[0] + b[1] * ue[1]) + (b[2] * ue[2] + b[3] * ue[3])) +
                            ((b[4] * ue[4] + b[5] * ue[5]) + (b[6] * ue[6] + b[7] * ue[7]));
        }
}

/* full strains (with eps_zz) of the points [i0, i1), whole elements */
static void strains(long i0, long i1, long ne, long nq, long n_r, const double *u,
                    const double *ezz, const int *edof, const double *B, double *eps) {
    double ev[3 * 64];
    for (long je = i0 / nq; je < i1 / nq; ++je) {
        strain_elem(je, ne, nq, n_r, u, edof, B, ev);
        for (long q = 0; q < nq; ++q) {
            long i = je * nq + q;
            eps[4 * i] = ev[3 * q];
            eps[4 * i + 1] = ev[3 * q + 1];
            eps[4 * i + 2] = ezz ? ezz[i] : 0.0;
            eps[4 * i + 3] = ev[3 * q + 2];
        }
    }
}

typedef struct {
    const Args *a;
    long n, chunk;
    int simd;
    long ne, nq, n_r;
    const double *u, *ezz;
    const int *edof;
    const double *B, *Bw;
    int pstress;
    const double *sig;
    double *szz, *sig_ip;
    const double *K, *g2, *coef, *nb;
    double *fe;
} EvalJob;

/* strains, Anand update, condensation and element forces of the points of chunk c (whole
 * elements) */
static void run_eval(void *ctx, long c) {
    const EvalJob *j = (const EvalJob *)ctx;
    long nq = j->nq, ne = j->ne;
    long i0 = c * j->chunk, i1 = i0 + j->chunk < j->n ? i0 + j->chunk : j->n;
    strains(i0, i1, ne, nq, j->n_r, j->u, j->ezz, j->edof, j->B, (double *)j->a->eps);
    range(j->a, i0, i1, j->simd);
    const double *K = j->K, *g2 = j->g2, *coef = j->coef;
    for (long i = i0; i < i1; ++i) {
        const double *sg = j->sig + 4 * i;
        j->szz[i] = sg[2];
        if (j->pstress) { /* sig_ip - C[ip, zz] / C[zz, zz] * sigma_zz */
            const double *nbi = j->nb + 4 * i;
            double cz[4];
            for (int k = 0; k < 4; ++k) {
                double mk = k < 3 ? 1.0 : 0.0;
                cz[k] = K[i] * mk + g2[i] * ((k == 2 ? 1.0 : 0.0) - mk / 3.0) +
                        coef[i] * nbi[k] * nbi[2];
            }
            for (int k = 0; k < 3; ++k)
                j->sig_ip[3 * i + k] = sg[IP3[k]] - cz[IP3[k]] / cz[2] * sg[2];
        } else {
            for (int k = 0; k < 3; ++k) j->sig_ip[3 * i + k] = sg[IP3[k]];
        }
    }
    for (long je = i0 / nq; je < i1 / nq; ++je) { /* element forces sum_q Bw^T sigma */
        const double *Bwe = j->Bw + 24 * nq * (je % ne), *se = j->sig_ip + 3 * nq * je;
        double f[8] = {0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0};
        for (long q = 0; q < nq; ++q)
            for (int k = 0; k < 3; ++k) {
                double sv = se[3 * q + k];
                const double *bw = Bwe + 24 * q + 8 * k;
                for (int aa = 0; aa < 8; ++aa) f[aa] += bw[aa] * sv;
            }
        memcpy(j->fe + 8 * je, f, sizeof f);
    }
}

int sp_solder_eval(const long *dims, const double *u, const double *ezz, const int *edof,
                   const int *dofD, const double *SDD,
                   const double *B, const double *Bw, const double *epsp_n, const double *s_n,
                   const double *X_n, const double *prm, const double *T, const double *dt,
                   const double *eth, const double *E, const double *nu, const double *Ck,
                   const long *div, const double *guess, int pstress, double *sig_ip,
                   double *szz, double *epsp, double *s_out, double *X_out, double *dep,
                   double *x, double *K, double *g2, double *coef, double *nb, double *fint,
                   int nthreads, int simd) {
    long b = dims[0], ne = dims[1], nq = dims[2], n_r = dims[3], nD = dims[4];
    long n = b * ne * nq;
    if (nq > 64) return -2;
    double *eps = (double *)malloc(sizeof(double) * 4 * (n + 1));
    double *sig = (double *)malloc(sizeof(double) * 4 * (n + 1));
    double *fe = (double *)malloc(sizeof(double) * 8 * (b * ne + 1));
    if (!eps || !sig || !fe) {
        free(eps); free(sig); free(fe);
        return -1;
    }
    Args a = {eps, epsp_n, s_n, X_n, prm, T, dt, eth, E, nu, Ck, guess,
              div[0], div[1], div[2], div[3], div[4], div[5], div[6],
              sig, epsp, s_out, X_out, dep, x, K, g2, coef, nb, 1};
    EvalJob job = {&a, n, 64 * nq, simd, ne, nq, n_r, u, ezz, edof, B, Bw, pstress, sig, szz,
                   sig_ip, K, g2, coef, nb, fe};
    sp_parallel((n + job.chunk - 1) / job.chunk, nthreads, run_eval, &job);
    memset(fint, 0, sizeof(double) * b * n_r);
    double *sd = (double *)malloc(sizeof(double) * (nD + 1));
    for (long j = 0; j < b; ++j) {
        double *fj = fint + n_r * j;
        const double *uj = u + n_r * j;
        if (sd) { /* S u: S is zero outside the border dofs dofD; S_DD symmetric: row axpys */
            memset(sd, 0, sizeof(double) * nD);
            for (long q = 0; q < nD; ++q) {
                const double *Sq = SDD + nD * q;
                double uq = uj[dofD[q]];
                for (long p = 0; p < nD; ++p) sd[p] += Sq[p] * uq;
            }
            for (long p = 0; p < nD; ++p) fj[dofD[p]] = sd[p];
        }
        for (long e = 0; e < ne; ++e)
            for (int aa = 0; aa < 8; ++aa) fj[edof[8 * e + aa]] += fe[8 * (j * ne + e) + aa];
    }
    if (!sd) {
        free(eps); free(sig); free(fe);
        return -1;
    }
    free(sd);
    free(eps);
    free(sig);
    free(fe);
    return 0;
}

/* Newton update of eps_zz accompanying du (SpecimenSolver._dezz, plane stress):
 * dz = -(szz + C[zz, ip] . B du) / C[zz, zz], C from the factored tangent (Tangent3D.row_zz). */
void sp_dezz(const long *dims, const double *du, const double *szz, const int *edof,
             const double *B, const double *K, const double *g2, const double *coef,
             const double *nb, double *dz) {
    long b = dims[0], ne = dims[1], nq = dims[2], n_r = dims[3];
    long n = b * ne * nq;
    if (nq > 64) return;
    double ev[3 * 64];
    for (long i = 0; i < n; ++i) {
        if (i % nq == 0) strain_elem(i / nq, ne, nq, n_r, du, edof, B, ev);
        const double *e3 = ev + 3 * (i % nq);
        const double *nbi = nb + 4 * i;
        double rz[4];
        for (int k = 0; k < 4; ++k) {
            double mk = k < 3 ? 1.0 : 0.0;
            rz[k] = K[i] * mk + g2[i] * ((k == 2 ? 1.0 : 0.0) - mk / 3.0) +
                    coef[i] * nbi[2] * nbi[k];
        }
        double sdot = rz[0] * e3[0] + rz[1] * e3[1] + rz[3] * e3[2];
        dz[i] = -(szz[i] + sdot) / rz[2];
    }
}
