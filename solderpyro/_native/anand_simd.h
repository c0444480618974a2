/* 4-lane (AVX2) joint Newton of anand.c, with glibc's vector math library (libmvec).
 *
 * Four points iterate in lock step; a lane that has converged is frozen (its values are no
 * longer updated), so each lane goes through exactly the iterates of the scalar joint() and
 * stops where it would. Only the rounding of exp/log/log1p/expm1/pow differs (libmvec: a few
 * ulp). Compiled in when the build defines SP_MVEC on an AVX2 target (see __init__.py).
 */
#if defined(SP_MVEC) && defined(__AVX2__)
#define SP_SIMD4 1
#include <immintrin.h>

typedef __m256d V;

__m256d _ZGVdN4v_exp(__m256d);
__m256d _ZGVdN4v_log(__m256d);
__m256d _ZGVdN4v_log1p(__m256d);
__m256d _ZGVdN4v_expm1(__m256d);
__m256d _ZGVdN4vv_pow(__m256d, __m256d);

#define VS(x) _mm256_set1_pd(x)
#define CMP(a, b, op) _mm256_cmp_pd((a), (b), (op))
static inline V vsel(V mask, V a, V b) { return _mm256_blendv_pd(b, a, mask); }
static inline V vabs(V a) { return _mm256_andnot_pd(VS(-0.0), a); }
static inline V vand(V a, V b) { return _mm256_and_pd(a, b); }

/* _partials_raw for four points (see partials() in anand.c, same formulas) */
static inline void partials4(V base, V lxq, V eb, V xq, V c, V s_n, V s_hat, V n, V a, V h0,
                             V m, V zeta, V s, V *R, V *H, V J[4], V *yc, V *dH_ds,
                             V *dH_dL) {
    V one = VS(1.0);
    V e = _ZGVdN4v_exp(-vabs(zeta));
    V t = _ZGVdN4v_log1p(e);
    V opz = one + e;
    V pos = CMP(zeta, VS(0.0), _CMP_GE_OQ);
    V inv = one / opz, eo = e / opz;
    V sg = vsel(pos, inv, eo), sgm = vsel(pos, eo, inv);
    V lsg = vsel(pos, -t, zeta - t), lsgm = vsel(pos, -zeta - t, -t);
    V L = base + lsgm;
    V s_star = s_hat * _ZGVdN4v_exp(n * (L - c));
    V r = one - s / s_star;
    V ar = vabs(r);
    ar = vsel(CMP(ar, VS(1e-300), _CMP_LT_OQ), VS(1e-300), ar);
    V sgn = vsel(CMP(r, VS(0.0), _CMP_EQ_OQ), VS(0.0), r);
    sgn = vsel(CMP(r, VS(0.0), _CMP_GT_OQ), VS(1.0), sgn);
    sgn = vsel(CMP(r, VS(0.0), _CMP_LT_OQ), VS(-1.0), sgn);
    V ara = _ZGVdN4vv_pow(ar, a);
    V phi = ara * sgn;
    V dphi_dr = a * (ara / ar);
    V dep = eb * sgm;
    *H = s - s_n - h0 * dep * phi;
    *dH_ds = one + h0 * dep * dphi_dr / s_star;
    *dH_dL = -h0 * dep * (phi + dphi_dr * n * s / s_star);
    V ly = lxq + lsg - _ZGVdN4v_log(s);
    V y = vsel(CMP(ly, VS(700.0), _CMP_LT_OQ), xq * sg / s, VS(exp(700.0)));
    V em = _ZGVdN4v_expm1(VS(-2.0) * y);
    V lsl = vsel(CMP(ly, VS(-18.0), _CMP_LT_OQ), ly + y * y / VS(6.0),
                 y + _ZGVdN4v_log(-em) - VS(LN2));
    V ycv = vsel(CMP(ly, VS(-9.0), _CMP_LT_OQ), one + y * y / VS(3.0),
                 y * (VS(2.0) + em) / (-em));
    V nan = CMP(ly, ly, _CMP_UNORD_Q);
    lsl = vsel(nan, ly, lsl);
    ycv = vsel(nan, ly, ycv);
    *R = L - c - lsl / m;
    *yc = ycv;
    J[0] = -sg - ycv * sgm / m;
    J[1] = ycv / (m * s);
    J[2] = -*dH_dL * sg;
    J[3] = *dH_ds;
}

#define GATHER(field) _mm256_set_pd(d[3].field, d[2].field, d[1].field, d[0].field)

/* joint() for four points */
static void joint4(Point d[4]) {
    V zeta = GATHER(zeta), s = GATHER(s), s_n = GATHER(q.s_n);
    V base = GATHER(q.base), lxq = GATHER(q.lxq), eb = GATHER(q.eb), xq = GATHER(q.xq);
    V c = GATHER(q.c), s_hat = GATHER(P.s_hat), n = GATHER(P.n), a = GATHER(P.a);
    V h0 = GATHER(P.h0), m = GATHER(P.m);
    V yc = VS(0.0), dH_ds = VS(0.0), dH_dL = VS(0.0);
    V active = CMP(VS(0.0), VS(0.0), _CMP_EQ_OQ), done = VS(0.0);
    for (int it = 0; it <= 12; ++it) {
        V R, H, J[4], ycn, dHs, dHL;
        partials4(base, lxq, eb, xq, c, s_n, s_hat, n, a, h0, m, zeta, s, &R, &H, J, &ycn, &dHs,
                  &dHL);
        V conv = vand(CMP(vabs(R), VS(1e-11), _CMP_LT_OQ),
                      CMP(vabs(H), VS(1e-13) * s_n, _CMP_LE_OQ));
        if (it == 12) conv = vand(conv, CMP(vabs(zeta), VS(INFINITY), _CMP_LT_OQ));
        yc = vsel(active, ycn, yc);
        dH_ds = vsel(active, dHs, dH_ds);
        dH_dL = vsel(active, dHL, dH_dL);
        done = _mm256_or_pd(done, vand(active, conv));
        if (it == 12) break;
        active = _mm256_andnot_pd(conv, active);
        if (_mm256_movemask_pd(active) == 0) break;
        V det = J[0] * J[3] - J[1] * J[2];
        V dz = -(J[3] * R - J[1] * H) / det;
        V ds = -(J[0] * H - J[2] * R) / det;
        V dzc = vsel(CMP(dz, VS(10.0), _CMP_GT_OQ), VS(10.0), dz);
        dzc = vsel(CMP(dz, VS(-10.0), _CMP_LT_OQ), VS(-10.0), dzc);
        V s1 = s + ds, lo = VS(1e-3) * s_n;
        s1 = vsel(CMP(s1, lo, _CMP_LT_OQ), lo, s1);
        zeta = vsel(active, zeta + dzc, zeta);
        s = vsel(active, s1, s);
    }
    double z4[4], s4[4], y4[4], hs4[4], hl4[4];
    _mm256_storeu_pd(z4, zeta);
    _mm256_storeu_pd(s4, s);
    _mm256_storeu_pd(y4, yc);
    _mm256_storeu_pd(hs4, dH_ds);
    _mm256_storeu_pd(hl4, dH_dL);
    int dm = _mm256_movemask_pd(done);
    for (int l = 0; l < 4; ++l) {
        d[l].zeta = z4[l];
        d[l].s = s4[l];
        d[l].yc = y4[l];
        d[l].dH_ds = hs4[l];
        d[l].dH_dL = hl4[l];
        d[l].done = (dm >> l) & 1;
    }
}

/* 4x4 transpose: rows (one per point) <-> columns (one per component) */
static inline void tr4(V *r0, V *r1, V *r2, V *r3) {
    V t0 = _mm256_unpacklo_pd(*r0, *r1), t1 = _mm256_unpackhi_pd(*r0, *r1);
    V t2 = _mm256_unpacklo_pd(*r2, *r3), t3 = _mm256_unpackhi_pd(*r2, *r3);
    *r0 = _mm256_permute2f128_pd(t0, t2, 0x20);
    *r1 = _mm256_permute2f128_pd(t1, t3, 0x20);
    *r2 = _mm256_permute2f128_pd(t0, t2, 0x31);
    *r3 = _mm256_permute2f128_pd(t1, t3, 0x31);
}

/* the four Mandel components of points i..i+3 of an (n, 4) array, as component vectors */
static inline void load44(const double *p, V c[4]) {
    c[0] = _mm256_loadu_pd(p);
    c[1] = _mm256_loadu_pd(p + 4);
    c[2] = _mm256_loadu_pd(p + 8);
    c[3] = _mm256_loadu_pd(p + 12);
    tr4(&c[0], &c[1], &c[2], &c[3]);
}

static inline void store44(double *p, V c0, V c1, V c2, V c3) {
    tr4(&c0, &c1, &c2, &c3);
    _mm256_storeu_pd(p, c0);
    _mm256_storeu_pd(p + 4, c1);
    _mm256_storeu_pd(p + 8, c2);
    _mm256_storeu_pd(p + 12, c3);
}

/* log(sinh(exp(ly))) (log_sinh_of_log) */
static inline V lsl4(V ly) {
    V y = _ZGVdN4v_exp(vsel(CMP(ly, VS(700.0), _CMP_GT_OQ), VS(700.0), ly));
    V big = y + _ZGVdN4v_log(-_ZGVdN4v_expm1(VS(-2.0) * y)) - VS(LN2);
    V r = vsel(CMP(ly, VS(-18.0), _CMP_LT_OQ), ly + y * y / VS(6.0), big);
    return vsel(CMP(ly, ly, _CMP_UNORD_Q), ly, r);
}

#define GATHERG(field) _mm256_set_pd(g[3].field, g[2].field, g[1].field, g[0].field)

/* setup(), joint(), finish() of anand.c for the points i..i+3 */
static void point4(const Args *a, long i, Group g[4]) {
    for (int l = 0; l < 4; ++l) {
        if (l > 0) g[l] = g[l - 1];
        group(a, i + l, &g[l]);
    }
    V one = VS(1.0), two = VS(2.0), three = VS(3.0);
    V eth = GATHERG(eth), c = GATHERG(c), K = GATHERG(K), G = GATHERG(G), Gk = GATHERG(Gk);
    V Ck = GATHERG(Ck), l3g = GATHERG(l3g), lxi = GATHERG(lxi);
    V xi = GATHERG(P.xi), m = GATHERG(P.m);
    V s_n = _mm256_loadu_pd(a->s_n + i);
    /* elastic trial */
    V ep[4], pn[4], xt[4];
    load44(a->eps + 4 * i, ep);
    load44(a->epsp_n + 4 * i, pn);
    V ee0 = ep[0] - pn[0] - eth, ee1 = ep[1] - pn[1] - eth, ee2 = ep[2] - pn[2] - eth;
    V ee3 = ep[3] - pn[3] - eth * VS(0.0);
    V tr = ee0 + ee1 + ee2;
    V pres = K * tr;
    V t3 = tr * one / three;
    xt[0] = two * G * (ee0 - t3);
    xt[1] = two * G * (ee1 - t3);
    xt[2] = two * G * (ee2 - t3);
    xt[3] = two * G * (ee3 - tr * VS(0.0) / three);
    V Xn[4] = {VS(0.0), VS(0.0), VS(0.0), VS(0.0)};
    if (a->X_n) {
        load44(a->X_n + 4 * i, Xn);
        for (int k = 0; k < 4; ++k) xt[k] = xt[k] - Xn[k];
    }
    V ss = xt[0] * xt[0] + xt[1] * xt[1] + xt[2] * xt[2] + xt[3] * xt[3] + VS(TINY6);
    V nrm = _mm256_sqrt_pd(ss);
    V log_qtr = VS(0.5) * _ZGVdN4v_log(VS(1.5) * ss);
    V q_tr = _mm256_sqrt_pd(VS(1.5) * ss);
    V zeta, s;
    if (a->guess) {
        V g01 = _mm256_loadu_pd(a->guess + 2 * i), g23 = _mm256_loadu_pd(a->guess + 2 * i + 4);
        /* (z0 s0 z1 s1), (z2 s2 z3 s3) -> (z0 z1 z2 z3), (s0 s1 s2 s3) */
        V lo = _mm256_permute2f128_pd(g01, g23, 0x20), hi = _mm256_permute2f128_pd(g01, g23, 0x31);
        zeta = _mm256_unpacklo_pd(lo, hi);
        s = _mm256_unpackhi_pd(lo, hi);
    } else { /* initial_zeta */
        V ly = lxi + log_qtr - _ZGVdN4v_log(s_n);
        V d = c + lsl4(ly) / m - log_qtr + l3g;
        d = vsel(CMP(d, VS(-1e-3), _CMP_GT_OQ), VS(-1e-3), d);
        zeta = -d + _ZGVdN4v_log(-_ZGVdN4v_expm1(d));
        s = s_n;
    }
    Point d[4];
    V base = log_qtr - l3g, lxq = lxi + log_qtr, eb = q_tr / (three * Gk), xq = xi * q_tr;
    double tmp[8][4];
    _mm256_storeu_pd(tmp[0], zeta);
    _mm256_storeu_pd(tmp[1], s);
    _mm256_storeu_pd(tmp[2], s_n);
    _mm256_storeu_pd(tmp[3], base);
    _mm256_storeu_pd(tmp[4], lxq);
    _mm256_storeu_pd(tmp[5], eb);
    _mm256_storeu_pd(tmp[6], xq);
    _mm256_storeu_pd(tmp[7], c);
    for (int l = 0; l < 4; ++l) {
        d[l].P = g[l].P;
        d[l].zeta = tmp[0][l];
        d[l].s = tmp[1][l];
        Pt q = {tmp[3][l], tmp[4][l], tmp[5][l], tmp[6][l], tmp[7][l], tmp[2][l]};
        d[l].q = q;
    }
    joint4(d);
    zeta = GATHER(zeta);
    s = GATHER(s);
    /* finish: tangent, stress, state */
    V ez = _ZGVdN4v_exp(-vabs(zeta)), opz = one + ez;
    V pos = CMP(zeta, VS(0.0), _CMP_GE_OQ), nan = CMP(zeta, zeta, _CMP_UNORD_Q);
    V sg = vsel(pos, one / opz, ez / opz), sgm = vsel(pos, ez / opz, one / opz);
    sg = vsel(nan, zeta, sg);
    sgm = vsel(nan, zeta, sgm);
    int kin = a->Ck != NULL;
    if (a->tangent) {
        V yc = GATHER(yc), dH_ds = GATHER(dH_ds), dH_dL = GATHER(dH_dL);
        V emz = vsel(pos, ez, vsel(CMP(zeta, VS(-700.0), _CMP_GT_OQ), one / ez,
                                   VS(exp(700.0))));
        emz = vsel(nan, zeta, emz);
        V w = yc * emz / m;
        V Fs_dHdL = yc / (m * s) * dH_dL;
        V bracket = sgm - w * dH_ds / ((one + w) * dH_ds - Fs_dHdL);
        V g2, coef;
        if (!kin) {
            g2 = two * G * sg;
            coef = two * G * bracket;
        } else {
            g2 = two * G * (sg + sgm * (Ck / three) / Gk);
            coef = two * G * (G / Gk) * bracket;
        }
        _mm256_storeu_pd(a->K + i, K);
        _mm256_storeu_pd(a->g2 + i, g2);
        _mm256_storeu_pd(a->coef + i, coef);
        store44(a->nb + 4 * i, xt[0] / nrm, xt[1] / nrm, xt[2] / nrm, xt[3] / nrm);
    }
    V f = sgm / (two * Gk);
    V dp[4], sig[4];
    for (int k = 0; k < 4; ++k) {
        dp[k] = f * xt[k];
        sig[k] = pres * (k < 3 ? one : VS(0.0)) + sg * xt[k];
    }
    store44(a->epsp + 4 * i, pn[0] + dp[0], pn[1] + dp[1], pn[2] + dp[2], pn[3] + dp[3]);
    if (a->X_out) {
        V X[4];
        for (int k = 0; k < 4; ++k) {
            if (kin) {
                V dX = VS(2.0 / 3.0) * Ck * dp[k];
                if (a->X_n)
                    X[k] = Xn[k] + dX;
                else
                    X[k] = dX;
            } else {
                X[k] = Xn[k];
            }
            sig[k] = sig[k] + X[k];
        }
        store44(a->X_out + 4 * i, X[0], X[1], X[2], X[3]);
    }
    store44(a->sigma + 4 * i, sig[0], sig[1], sig[2], sig[3]);
    _mm256_storeu_pd(a->dep + i, eb * sgm);
    _mm256_storeu_pd(a->s_out + i, s);
    V lo = _mm256_unpacklo_pd(zeta, s), hi = _mm256_unpackhi_pd(zeta, s); /* z0 s0 z2 s2 | z1 s1 z3 s3 */
    _mm256_storeu_pd(a->x + 2 * i, _mm256_permute2f128_pd(lo, hi, 0x20));
    _mm256_storeu_pd(a->x + 2 * i + 4, _mm256_permute2f128_pd(lo, hi, 0x31));
    for (int l = 0; l < 4; ++l)
        if (!d[l].done) { /* the scalar path, with the bracketed fallback, for this point */
            Point p;
            setup(a, i + l, &p, &g[l]);
            p.done = 0;
            finish(a, i + l, &p);
        }
}
#endif
