/* The reduced PCA likelihood of solderpyro.calibration.reduced in one call: the K component
 * GPs' means and variances at one input, the sigma-dependent sums over the n outputs (from the
 * truncation variance's moment series, or summed directly), the K-dimensional Woodbury terms,
 * the log density and its gradient in the GP inputs and sigma.
 *
 * It is the same algorithm as ComponentGPs.__call__ / its vjp, _WeightMoments.__call__,
 * PCAReduction._loglik_projected and _k_terms (NumPy), step by step; the only difference is
 * P = V^1/2 M^-1 V^1/2 formed from M's Cholesky factor instead of an LU inverse. Why C: the
 * NumPy version makes ~60 calls on arrays of 20-91 values per gradient, and the calls, not
 * the arithmetic, were most of its 128 us (tests/unit/calibration/test_reduced.py checks the two agree).
 *
 * dims: K, n_sim, d' (GP inputs), rows (= K(K+1)/2 + K + 1), n (outputs), kernel (0 gaussian,
 *       1 Matern 5/2), has_w (a linear mean), max_order (moment series' cap, < 128)
 * ptr:  U (n_sim, d'), os (K), inv_ls2 (K, d'), c0 (K), w (K, d') or NULL, alpha (K, n_sim),
 *       Linv (K, n_sim (n_sim + 1) / 2) lower triangles packed by rows,
 *       Mq (rows, max_order + 1), mt (max_order + 1), d (n),
 *       Qt (rows, n)
 * sc:   mid, half (of d's range), tol (series' tail bound)
 * out:  ll, d ll/du (d'), d ll/dsigma, c (K), v (K)
 * work: sp_reduced_work_size(dims) doubles
 * Returns 0, or 1 when I + V^1/2 A V^1/2 is not positive definite (non-finite inputs).
 */
#include <math.h>
#include <string.h>

#define LOG_2PI 1.8378770664093453

#if defined(SP_MVEC) && defined(__AVX2__)
#include <immintrin.h>
__m256d _ZGVdN4v_exp(__m256d);
/* x <- exp(x) in place, four lanes at a time (glibc's libmvec: a few ulp from exp) */
static void vexp(double *x, long n) {
    long i = 0;
    for (; i + 4 <= n; i += 4) _mm256_storeu_pd(x + i, _ZGVdN4v_exp(_mm256_loadu_pd(x + i)));
    for (; i < n; ++i) x[i] = exp(x[i]);
}
#else
static void vexp(double *x, long n) {
    for (long i = 0; i < n; ++i) x[i] = exp(x[i]);
}
#endif

long sp_reduced_work_size(const long *dims) {
    long K = dims[0], ns = dims[1], dp = dims[2], rows = dims[3];
    return ns * dp + 4 * K * ns + 2 * rows + 6 * K * K + 11 * K + 2 * dp;
}

/* the sums Q^T w, Q^T w^2, sum w, sum log w with w_i = 1 / (d_i + s) */
static void weight_sums(const long *dims, void *const *ptr, const double *sc, double s,
                        double *S1, double *S2, double *sum_w, double *sum_log_w) {
    long rows = dims[3], n = dims[4], maxo = dims[7];
    const double *Mq = ptr[7], *mt = ptr[8], *d = ptr[9], *Qt = ptr[10];
    double mid = sc[0], half = sc[1], tol = sc[2];
    double a = mid + s;
    long L = -1;
    if (a > 0.0) {
        double r = half / a;
        if (r <= 0.0) L = 0;
        else if (r < 0.5) {
            double om2 = (1.0 - r) * (1.0 - r);
            for (long l = 0; l <= maxo; ++l)
                if ((l + 2) * pow(r, (double)(l + 1)) / om2 <= tol) { L = l; break; }
        }
        if (L >= 0) {
            double c1[128], c2[128], pw = 1.0, lsum = -(double)n * log(a), sw = 0.0;
            for (long k = 0; k <= L; ++k) {
                c1[k] = pw / a;
                c2[k] = (k + 1.0) * pw / (a * a);
                sw += c1[k] * mt[k];
                if (k > 0) lsum += pw / (double)k * mt[k];
                pw *= -r;
            }
            for (long i = 0; i < rows; ++i) {
                const double *row = Mq + i * (maxo + 1);
                double t1 = 0.0, t2 = 0.0;
                for (long k = 0; k <= L; ++k) { t1 += row[k] * c1[k]; t2 += row[k] * c2[k]; }
                S1[i] = t1;
                S2[i] = t2;
            }
            *sum_w = sw;
            *sum_log_w = lsum;
            return;
        }
    }
    double sw = 0.0, slw = 0.0;
    for (long i = 0; i < rows; ++i) { S1[i] = 0.0; S2[i] = 0.0; }
    for (long j = 0; j < n; ++j) {
        double w = 1.0 / (d[j] + s);
        sw += w;
        slw += log(w);
    }
    for (long i = 0; i < rows; ++i) {
        const double *row = Qt + i * n;
        double t1 = 0.0, t2 = 0.0;
        for (long j = 0; j < n; ++j) {
            double w = 1.0 / (d[j] + s);
            t1 += row[j] * w;
            t2 += row[j] * w * w;
        }
        S1[i] = t1;
        S2[i] = t2;
    }
    *sum_w = sw;
    *sum_log_w = slw;
}

int sp_reduced_loglik(const long *dims, void *const *ptr, const double *sc, const double *u,
                      double sigma, double *out, double *work) {
    long K = dims[0], ns = dims[1], dp = dims[2], rows = dims[3], n = dims[4];
    int matern = (int)dims[5], has_w = (int)dims[6];
    const double *U = ptr[0], *os = ptr[1], *ils = ptr[2], *c0 = ptr[3], *W = ptr[4],
                 *alpha = ptr[5], *Linv = ptr[6];
    double *diff = work, *drho = diff + ns * dp, *kap = drho + K * ns, *hf = kap + K * ns,
           *beta = hf + K * ns, *S1 = beta + K * ns, *S2 = S1 + rows, *A = S2 + rows,
           *A2 = A + K * K, *Mm = A2 + K * K, *Li = Mm + K * K, *P = Li + K * K, *AP = P + K * K,
           *c = AP + K * K, *v = c + K, *sv = v + K, *e = sv + K, *Pe = e + K, *g = Pe + K,
           *gv = g + K, *h = gv + K, *Ac = h + K, *bwv = Ac + K, *pos = bwv + K, *tmp = pos + K,
           *gu = tmp + dp;

    /* component GPs: kernel values, means, variances through L^-1 */
    for (long i = 0; i < ns; ++i)
        for (long l = 0; l < dp; ++l) diff[i * dp + l] = u[l] - U[i * dp + l];
    /* the exponents of all K x n_sim kernel values first, then one vectorized exp */
    for (long k = 0; k < K; ++k) {
        const double *il = ils + k * dp;
        for (long i = 0; i < ns; ++i) {
            const double *di = diff + i * dp;
            double r2 = 0.0;
            for (long l = 0; l < dp; ++l) r2 += di[l] * di[l] * il[l];
            /* (written so that a NaN distance stays NaN, as in NumPy) */
            drho[k * ns + i] = matern ? sqrt(5.0) * sqrt(r2 < 1e-30 ? 1e-30 : r2) : r2;
        }
    }
    for (long j = 0; j < K * ns; ++j) kap[j] = (matern ? -1.0 : -0.5) * drho[j];
    vexp(kap, K * ns);
    for (long j = 0; j < K * ns; ++j) {
        double ex = kap[j], a = drho[j];
        if (matern) {  /* a = sqrt(5) r */
            kap[j] = (1.0 + a + a * a / 3.0) * ex;
            drho[j] = -(5.0 / 3.0) * (1.0 + a) * ex;
        } else {
            drho[j] = -ex;
        }
    }
    for (long k = 0; k < K; ++k) {
        const double *al = alpha + k * ns;
        double ck = c0[k];
        for (long i = 0; i < ns; ++i) {
            kap[k * ns + i] *= os[k];
            ck += kap[k * ns + i] * al[i];
        }
        if (has_w)
            for (long l = 0; l < dp; ++l) ck += W[k * dp + l] * u[l];
        c[k] = ck;
        /* L^-1 kappa by rows (dot products), then L^-T (L^-1 kappa) as axpys along the same
         * rows: one pass each over the packed lower triangle, which stays in a 1 MB L2 */
        const double *Lk = Linv + k * (ns * (ns + 1) / 2), *kk = kap + k * ns;
        double *hk = hf + k * ns, *bk = beta + k * ns, q = 0.0;
        const double *row = Lk;
        for (long i = 0; i < ns; row += ++i) {
            double t = 0.0;
#pragma omp simd reduction(+ : t)
            for (long j = 0; j <= i; ++j) t += row[j] * kk[j];
            hk[i] = t;
            q += t * t;
        }
        memset(bk, 0, sizeof(double) * ns);
        row = Lk;
        for (long i = 0; i < ns; row += ++i) {
            double t = hk[i];
            for (long j = 0; j <= i; ++j) bk[j] += row[j] * t;
        }
        double vr = os[k] - q;
        v[k] = vr > 0.0 ? vr : 0.0;
        pos[k] = vr > 0.0 ? 1.0 : 0.0;
    }

    /* sigma-dependent sums and the K-dimensional algebra */
    double sum_w, sum_log_w;
    weight_sums(dims, ptr, sc, sigma * sigma, S1, S2, &sum_w, &sum_log_w);
    long t = 0;
    for (long i = 0; i < K; ++i)
        for (long j = i; j < K; ++j, ++t) {
            A[i * K + j] = A[j * K + i] = S1[t];
            A2[i * K + j] = A2[j * K + i] = S2[t];
        }
    const double *bw = S1 + t, *bw2 = S2 + t;
    double yw = S1[rows - 1], yw2 = S2[rows - 1];
    for (long i = 0; i < K; ++i) {
        double s = 0.0;
        for (long j = 0; j < K; ++j) s += A[i * K + j] * c[j];
        Ac[i] = s;
        e[i] = bw[i] - s;
        sv[i] = sqrt(v[i]);
        bwv[i] = bw[i];
    }
    for (long i = 0; i < K; ++i)
        for (long j = 0; j < K; ++j)
            Mm[i * K + j] = (i == j ? 1.0 : 0.0) + sv[i] * A[i * K + j] * sv[j];
    /* Cholesky M = L L^T (lower, row-major), then L^-1 and M^-1 = L^-T L^-1 */
    double logdet = 0.0;
    for (long j = 0; j < K; ++j) {
        double dd = Mm[j * K + j];
        for (long k = 0; k < j; ++k) dd -= Mm[j * K + k] * Mm[j * K + k];
        if (!(dd > 0.0)) return 1;
        dd = sqrt(dd);
        Mm[j * K + j] = dd;
        logdet += 2.0 * log(dd);
        for (long i = j + 1; i < K; ++i) {
            double s = Mm[i * K + j];
            for (long k = 0; k < j; ++k) s -= Mm[i * K + k] * Mm[j * K + k];
            Mm[i * K + j] = s / dd;
        }
    }
    memset(Li, 0, sizeof(double) * K * K);
    for (long j = 0; j < K; ++j) {
        Li[j * K + j] = 1.0 / Mm[j * K + j];
        for (long i = j + 1; i < K; ++i) {
            double s = 0.0;
            for (long k = j; k < i; ++k) s -= Mm[i * K + k] * Li[k * K + j];
            Li[i * K + j] = s / Mm[i * K + i];
        }
    }
    for (long i = 0; i < K; ++i)
        for (long j = i; j < K; ++j) {
            double s = 0.0;
            for (long k = j; k < K; ++k) s += Li[k * K + i] * Li[k * K + j];
            P[i * K + j] = P[j * K + i] = s;
        }
    for (long i = 0; i < K; ++i)
        for (long j = 0; j < K; ++j) P[i * K + j] *= sv[i] * sv[j];
    for (long i = 0; i < K; ++i) {
        double s = 0.0;
        for (long j = 0; j < K; ++j) s += P[i * K + j] * e[j];
        Pe[i] = s;
    }
    for (long i = 0; i < K; ++i)
        for (long j = 0; j < K; ++j) {
            double s = 0.0;
            for (long k = 0; k < K; ++k) s += A[i * K + k] * P[k * K + j];
            AP[i * K + j] = s;
        }
    double ePe = 0.0, cbw = 0.0, cAc = 0.0;
    for (long i = 0; i < K; ++i) {
        double s = 0.0, dapa = 0.0;
        for (long j = 0; j < K; ++j) {
            s += A[i * K + j] * Pe[j];
            dapa += AP[i * K + j] * A[j * K + i];
        }
        g[i] = e[i] - s;
        gv[i] = 0.5 * (g[i] * g[i] - (A[i * K + i] - dapa));
        ePe += e[i] * Pe[i];
        cbw += c[i] * bwv[i];
        cAc += c[i] * Ac[i];
        h[i] = c[i] + Pe[i];
    }
    double quad = yw - 2.0 * cbw + cAc - ePe;
    double ll = -0.5 * ((double)n * LOG_2PI - sum_log_w + logdet + quad);
    double zz = yw2, trPA2 = 0.0;
    for (long i = 0; i < K; ++i) {
        double s = 0.0;
        for (long j = 0; j < K; ++j) {
            s += A2[i * K + j] * h[j];
            trPA2 += P[i * K + j] * A2[i * K + j];
        }
        zz += h[i] * s - 2.0 * h[i] * bw2[i];
    }
    double gs = sigma * (zz - (sum_w - trPA2));

    /* back to the GP inputs: d/du of sum(g c + gv v) */
    for (long l = 0; l < dp; ++l) gu[l] = 0.0;
    for (long i = 0; i < ns; ++i) {
        for (long l = 0; l < dp; ++l) tmp[l] = 0.0;
        for (long k = 0; k < K; ++k) {
            double a = (g[k] * alpha[k * ns + i] - 2.0 * pos[k] * gv[k] * beta[k * ns + i])
                       * os[k] * drho[k * ns + i];
            const double *il = ils + k * dp;
            for (long l = 0; l < dp; ++l) tmp[l] += a * il[l];
        }
        const double *di = diff + i * dp;
        for (long l = 0; l < dp; ++l) gu[l] += tmp[l] * di[l];
    }
    if (has_w)
        for (long k = 0; k < K; ++k)
            for (long l = 0; l < dp; ++l) gu[l] += g[k] * W[k * dp + l];

    out[0] = ll;
    for (long l = 0; l < dp; ++l) out[1 + l] = gu[l];
    out[1 + dp] = gs;
    for (long k = 0; k < K; ++k) { out[2 + dp + k] = c[k]; out[2 + dp + K + k] = v[k]; }
    return 0;
}
