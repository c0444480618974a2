/* Batched assembly, Cholesky factorization and solve of the FE's retained tangent, exploiting
 * its bordered-band structure (see solderpyro/fem/bordered.py for the plan and the layout).
 *
 * The retained dofs split into "interior" dofs I (untouched by the condensed elastic bars S;
 * ordered to a band of half-width w) and "border" dofs D (where S is dense). With
 *     K = [[A, Bc], [Bc^T, Dd]],  A = L L^T (band),  Sc = Dd - Bc^T A^-1 Bc = M M^T (dense),
 * one member's factor is stored as [L band (nI*(w+1)) | Bc values (nnzB, CSR by interior
 * row) | U (nD*nD, Sc = U^T U, upper, row-major)]. The Schur complement is formed as
 * Dd - Bc^T Z with Z = A^-1 Bc (two band sweeps on the nD columns, then a sparse product).
 * The solve is two band sweeps, a sparse product, two dense triangular sweeps, a sparse
 * product and two band sweeps. Inner loops run along contiguous rows (vectorizable).
 *
 * Element tangents: Ke = sum_q Bw_q^T C_q B_q with the in-plane tangent C_q (3x3) either given
 * (Cip) or formed from the factored 3-D tangent C = K m m^T + g2 (I - m m^T/3) + coef nb nb^T
 * (plane stress: condensed on eps_zz; plane strain: the in-plane block).
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "pool.h"

/* per-thread scratch, grown on demand and kept (one per pool thread) */
static double *scratch(long n) {
    static __thread double *buf = NULL;
    static __thread long cap = 0;
    if (n > cap) {
        free(buf);
        buf = (double *)malloc(sizeof(double) * n);
        cap = buf ? n : 0;
    }
    return buf;
}

typedef struct {
    long n_r, nI, nD, w, nnzB, n_e, n_qp, nbuf;
    const int *emap;     /* (n_e, 8, 8): offset into the member buffer, or -1 */
    const int *brow;     /* (nI + 1,) CSR row pointers of Bc */
    const int *bcol;     /* (nnzB,) border column of each Bc entry */
    const int *perm;     /* (n_r,): position of retained dof j in [I | D] order */
    const double *SD;    /* (nD, nD) condensed bars on the border */
    const double *B;     /* (n_e, n_qp, 3, 8) */
    const double *Bw;    /* (n_e, n_qp, 3, 8) B * w det J */
} Plan;

static const int IPX[3] = {0, 1, 3};

/* in-plane 3x3 tangent at one point from the factored 3-D tangent */
static void cip_from_factored(double K, double g2, double coef, const double *nb, int pstress,
                              double C[9]) {
    double F[4][4];
    for (int i = 0; i < 4; ++i)
        for (int j = 0; j < 4; ++j) {
            double mi = i < 3 ? 1.0 : 0.0, mj = j < 3 ? 1.0 : 0.0;
            double mm = mi * mj;
            double dev = (i == j ? 1.0 : 0.0) - mm / 3.0;
            F[i][j] = K * mm + g2 * dev + coef * nb[i] * nb[j];
        }
    for (int a = 0; a < 3; ++a)
        for (int b = 0; b < 3; ++b) {
            double v = F[IPX[a]][IPX[b]];
            if (pstress) v -= F[2][IPX[a]] * F[2][IPX[b]] / F[2][2];
            C[3 * a + b] = v;
        }
}

/* assemble one member into buf (zeroed band/Bc, Sd = SD) */
static void assemble(const Plan *P, double *buf, const double *Cip, const double *tK,
                     const double *tg2, const double *tcoef, const double *tnb, int pstress,
                     long n_fact, const double *dKe, long e0) {
    long nb = P->nI * (P->w + 1);
    memset(buf, 0, sizeof(double) * (nb + P->nnzB));
    double *Sd = buf + nb + P->nnzB;
    memcpy(Sd, P->SD, sizeof(double) * P->nD * P->nD);
    for (long e = 0; e < P->n_e; ++e) {
        double Ke[64] = {0};
        for (long q = 0; q < P->n_qp; ++q) {
            long pt = e * P->n_qp + q;
            double C[9];
            if (e < n_fact) {
                cip_from_factored(tK[pt], tg2[pt], tcoef[pt], tnb + 4 * pt, pstress, C);
            } else {
                memcpy(C, Cip + 9 * (pt - n_fact * P->n_qp), sizeof C);
            }
            const double *Bq = P->B + 24 * pt, *Bwq = P->Bw + 24 * pt;
            double CB[24];
            for (int i = 0; i < 3; ++i)
                for (int a = 0; a < 8; ++a)
                    CB[8 * i + a] = C[3 * i] * Bq[a] + C[3 * i + 1] * Bq[8 + a] +
                                    C[3 * i + 2] * Bq[16 + a];
            for (int a = 0; a < 8; ++a)
                for (int b = 0; b < 8; ++b)
                    Ke[8 * a + b] += Bwq[a] * CB[b] + Bwq[8 + a] * CB[8 + b] +
                                     Bwq[16 + a] * CB[16 + b];
        }
        if (dKe && e >= e0)
            for (int k = 0; k < 64; ++k) Ke[k] -= dKe[64 * (e - e0) + k];
        const int *em = P->emap + 64 * e;
        for (int k = 0; k < 64; ++k)
            if (em[k] >= 0) buf[em[k]] += Ke[k];
    }
}

/* band Cholesky in place; L[i, j] at i*(w+1) + (j - i + w) */
static int band_chol(double *L, long n, long w) {
    long ld = w + 1;
    for (long i = 0; i < n; ++i) {
        long j0 = i - w < 0 ? 0 : i - w;
        for (long j = j0; j <= i; ++j) {
            long k0 = (j - w < 0 ? 0 : j - w);
            if (k0 < j0) k0 = j0;
            double s = L[i * ld + (j - i + w)];
            for (long k = k0; k < j; ++k) s -= L[i * ld + (k - i + w)] * L[j * ld + (k - j + w)];
            if (j < i) {
                L[i * ld + (j - i + w)] = s / L[j * ld + w];
            } else {
                if (!(s > 0.0)) return (int)i + 1;
                L[i * ld + w] = sqrt(s);
            }
        }
    }
    return 0;
}

static void band_fwd(const double *L, long n, long w, double *x) {
    long ld = w + 1;
    for (long i = 0; i < n; ++i) { /* column-oriented: independent updates, no sum chain */
        double xi = x[i] / L[i * ld + w];
        x[i] = xi;
        long j1 = i + w < n - 1 ? i + w : n - 1;
        for (long j = i + 1; j <= j1; ++j) x[j] -= L[j * ld + (i - j + w)] * xi;
    }
}

static void band_bwd(const double *L, long n, long w, double *x) {
    long ld = w + 1;
    for (long i = n - 1; i >= 0; --i) {
        double xi = x[i] / L[i * ld + w];
        x[i] = xi;
        long j0 = i - w < 0 ? 0 : i - w;
        for (long j = j0; j < i; ++j) x[j] -= L[i * ld + (j - i + w)] * xi;
    }
}

/* dense Cholesky Sc = U^T U in place (row-major n x n, upper triangle used), right-looking:
 * every update is an axpy along a contiguous row */
static int dense_chol(double *M, long n) {
    for (long k = 0; k < n; ++k) {
        double *Mk = M + k * n;
        double d = Mk[k];
        if (!(d > 0.0)) return (int)k + 1;
        d = sqrt(d);
        Mk[k] = d;
        double r = 1.0 / d;
        for (long j = k + 1; j < n; ++j) Mk[j] *= r;
        for (long i = k + 1; i < n; ++i) {
            double a = Mk[i];
            if (a == 0.0) continue;
            double *Mi = M + i * n;
            for (long j = i; j < n; ++j) Mi[j] -= a * Mk[j];
        }
    }
    return 0;
}

/* factor one assembled member buffer; Z: scratch (nI * nD) */
static int factor(const Plan *P, double *buf, double *Z) {
    long nI = P->nI, nD = P->nD, w = P->w, ld = w + 1;
    double *L = buf, *Bv = buf + nI * ld, *M = Bv + P->nnzB;
    int info = band_chol(L, nI, w);
    if (info) return info;
    /* Z = A^-1 Bc, rows of Z contiguous over the nD border columns */
    memset(Z, 0, sizeof(double) * nI * nD);
    for (long i = 0; i < nI; ++i)
        for (int k = P->brow[i]; k < P->brow[i + 1]; ++k) Z[i * nD + P->bcol[k]] = Bv[k];
    for (long i = 0; i < nI; ++i) { /* L Y = Bc */
        double *Zi = Z + i * nD;
        long j0 = i - w < 0 ? 0 : i - w;
        for (long j = j0; j < i; ++j) {
            double l = L[i * ld + (j - i + w)];
            const double *Zj = Z + j * nD;
            for (long c = 0; c < nD; ++c) Zi[c] -= l * Zj[c];
        }
        double d = 1.0 / L[i * ld + w];
        for (long c = 0; c < nD; ++c) Zi[c] *= d;
    }
    for (long i = nI - 1; i >= 0; --i) { /* L^T Z = Y */
        double *Zi = Z + i * nD;
        double d = 1.0 / L[i * ld + w];
        for (long c = 0; c < nD; ++c) Zi[c] *= d;
        long j0 = i - w < 0 ? 0 : i - w;
        for (long j = j0; j < i; ++j) {
            double l = L[i * ld + (j - i + w)];
            double *Zj = Z + j * nD;
            for (long c = 0; c < nD; ++c) Zj[c] -= l * Zi[c];
        }
    }
    /* Sc = Dd - Bc^T Z (upper triangle) */
    for (long r = 0; r < nI; ++r) {
        const double *Zr = Z + r * nD;
        for (int k = P->brow[r]; k < P->brow[r + 1]; ++k) {
            long p = P->bcol[k];
            double v = Bv[k];
            double *Mp = M + p * nD;
            for (long q = p; q < nD; ++q) Mp[q] -= v * Zr[q];
        }
    }
    info = dense_chol(M, nD);
    return info ? (int)(nI + info) : 0;
}

static void solve(const Plan *P, const double *buf, const double *rhs, double *x, double *t) {
    long nI = P->nI, nD = P->nD, w = P->w, ld = w + 1;
    const double *L = buf, *Bv = buf + nI * ld, *M = Bv + P->nnzB;
    double *tI = t, *tD = t + nI, *z = t + nI + nD;
    for (long j = 0; j < P->n_r; ++j) t[P->perm[j]] = rhs[j];
    memcpy(z, tI, sizeof(double) * nI);
    band_fwd(L, nI, w, z);
    band_bwd(L, nI, w, z);
    for (long r = 0; r < nI; ++r)
        for (int k = P->brow[r]; k < P->brow[r + 1]; ++k) tD[P->bcol[k]] -= Bv[k] * z[r];
    for (long r = 0; r < nD; ++r) { /* U^T y = tD, column-oriented */
        const double *Mr = M + r * nD;
        double yr = tD[r] / Mr[r];
        tD[r] = yr;
        for (long k = r + 1; k < nD; ++k) tD[k] -= Mr[k] * yr;
    }
    for (long r = nD - 1; r >= 0; --r) { /* U x = y, four partial sums */
        const double *Mr = M + r * nD;
        double s0 = 0.0, s1 = 0.0, s2 = 0.0, s3 = 0.0;
        long k = r + 1;
        for (; k + 4 <= nD; k += 4) {
            s0 += Mr[k] * tD[k];
            s1 += Mr[k + 1] * tD[k + 1];
            s2 += Mr[k + 2] * tD[k + 2];
            s3 += Mr[k + 3] * tD[k + 3];
        }
        for (; k < nD; ++k) s0 += Mr[k] * tD[k];
        tD[r] = (tD[r] - ((s0 + s1) + (s2 + s3))) / Mr[r];
    }
    for (long r = 0; r < nI; ++r) {
        double sr = tI[r];
        for (int k = P->brow[r]; k < P->brow[r + 1]; ++k) sr -= Bv[k] * tD[P->bcol[k]];
        tI[r] = sr;
    }
    band_fwd(L, nI, w, tI);
    band_bwd(L, nI, w, tI);
    for (long j = 0; j < P->n_r; ++j) x[j] = t[P->perm[j]];
}

typedef struct {
    const Plan *P;
    const long *slot;
    double *cache;
    const double *tK, *tg2, *tcoef, *tnb, *Cip, *dKe;
    long n_fact, e0;
    int pstress;
    int *info;
} FactorJob;

static void run_factor(void *ctx, long j) {
    const FactorJob *f = (const FactorJob *)ctx;
    const Plan *P = f->P;
    long npt_f = f->n_fact * P->n_qp, npt_c = (P->n_e - f->n_fact) * P->n_qp;
    double *Z = scratch(P->nI * P->nD + 1);
    if (!Z) {
        f->info[j] = -1;
        return;
    }
    double *buf = f->cache + f->slot[j] * P->nbuf;
    assemble(P, buf, f->Cip ? f->Cip + 9 * npt_c * j : NULL, f->tK ? f->tK + npt_f * j : NULL,
             f->tg2 ? f->tg2 + npt_f * j : NULL, f->tcoef ? f->tcoef + npt_f * j : NULL,
             f->tnb ? f->tnb + 4 * npt_f * j : NULL, f->pstress, f->n_fact,
             f->dKe ? f->dKe + 64 * (P->n_e - f->e0) * j : NULL, f->e0);
    f->info[j] = factor(P, buf, Z);
}

/* Assemble and factor members: slot[j] (into cache (n_slots, nbuf)) from the tangents of row
 * j. Solder points (elements < n_fact) from the factored tangent (tK, tg2, tcoef (k, n_fact,
 * n_qp), tnb (.., 4)), the others from Cip (k, n_e - n_fact, n_qp, 3, 3); dKe (k, n_e - e0,
 * 8, 8) is subtracted from the element matrices e >= e0 (or NULL). info[j]: 0, the failing
 * pivot + 1, or -1 (out of memory). */
void sp_bb_factor(const long *dims, const int *emap, const int *brow, const int *bcol,
                  const int *perm, const double *SD, const double *B, const double *Bw,
                  long k, const long *slot, double *cache, const double *tK, const double *tg2,
                  const double *tcoef, const double *tnb, long n_fact, const double *Cip,
                  int pstress, const double *dKe, long e0, int *info, int nthreads) {
    Plan P = {dims[0], dims[1], dims[2], dims[3], dims[4], dims[5], dims[6], dims[7],
              emap, brow, bcol, perm, SD, B, Bw};
    FactorJob job = {&P, slot, cache, tK, tg2, tcoef, tnb, Cip, dKe, n_fact, e0, pstress, info};
    sp_parallel(k, nthreads, run_factor, &job);
}

typedef struct {
    const Plan *P;
    const long *slot;
    const double *cache, *rhs;
    double *x;
} SolveJob;

static void run_solve(void *ctx, long j) {
    const SolveJob *s = (const SolveJob *)ctx;
    const Plan *P = s->P;
    double *t = scratch(2 * P->nI + P->nD + 1);
    if (!t) { /* out of memory: NaN, which the solver treats as a failed update */
        for (long i = 0; i < P->n_r; ++i) s->x[P->n_r * j + i] = NAN;
        return;
    }
    solve(P, s->cache + s->slot[j] * P->nbuf, s->rhs + P->n_r * j, s->x + P->n_r * j, t);
}

/* x[j] = K[slot[j]]^-1 rhs[j] for j < k (rhs, x: (k, n_r)) */
void sp_bb_solve(const long *dims, const int *brow, const int *bcol, const int *perm, long k,
                 const long *slot, const double *cache, const double *rhs, double *x,
                 int nthreads) {
    Plan P = {dims[0], dims[1], dims[2], dims[3], dims[4], dims[5], dims[6], dims[7],
              NULL, brow, bcol, perm, NULL, NULL, NULL};
    SolveJob job = {&P, slot, cache, rhs, x};
    sp_parallel(k, nthreads, run_solve, &job);
}
