/* The ridge map of solderpyro.calibration.ridgemap (RidgeMap.forward for one point and
 * RidgeMap.vjp), in C: the same formulas in the same order. Why: in NumPy the map made ~60
 * calls on vectors of d <= 8 values per gradient (36 us of the loop's 137 us gradient).
 *
 * dims: d
 * par:  mean (d), sd (d), span (d), c0 (d), b (d, d) (row k: b_k in columns < k),
 *       A (d, d, d) (A_k: (k, k) in the leading block), S (d, d, d) (S_k = A_k + A_k^T)
 */
#include <math.h>

static double h1(double z, double a) {
    double over = fabs(z) - a;
    return over <= 0.0 ? z : copysign(a + tanh(over), z);
}

/* w (d,) -> q (d,), z (d,) */
void sp_ridge_forward(long d, const double *mean, const double *sd, const double *span,
                      const double *c0, const double *b, const double *A, const double *w,
                      double *q, double *z) {
    double h[64];
    z[0] = w[0];
    h[0] = h1(z[0], span[0]);
    for (long k = 1; k < d; ++k) {
        const double *bk = b + k * d, *Ak = A + k * d * d;
        double lin = 0.0, quad = 0.0;
        for (long i = 0; i < k; ++i) lin += h[i] * bk[i];
        for (long i = 0; i < k; ++i) {
            double s = 0.0;
            for (long j = 0; j < k; ++j) s += h[j] * Ak[j * d + i];
            quad += s * h[i];
        }
        z[k] = w[k] + (c0[k] + lin + quad);
        h[k] = h1(z[k], span[k]);
    }
    for (long k = 0; k < d; ++k) q[k] = mean[k] + sd[k] * z[k];
}

/* (dq/dw)^T g at the point with standardized coordinates z: out (d,) */
void sp_ridge_vjp(long d, const double *sd, const double *span, const double *b,
                  const double *S, const double *z, const double *g, double *out) {
    double h[64], dh[64];
    for (long k = 0; k < d; ++k) {
        double over = fabs(z[k]) - span[k];
        if (over < 0.0) over = 0.0;
        h[k] = over > 0.0 ? copysign(span[k] + tanh(over), z[k]) : z[k];
        double t = tanh(over);
        dh[k] = 1.0 - t * t;
        out[k] = g[k] * sd[k];
    }
    for (long k = d - 1; k > 0; --k) {
        const double *bk = b + k * d, *Sk = S + k * d * d;
        double ak = out[k];
        for (long i = 0; i < k; ++i) {
            double s = 0.0;
            for (long j = 0; j < k; ++j) s += Sk[i * d + j] * h[j];
            out[i] += ak * (bk[i] + s) * dh[i];
        }
    }
}
