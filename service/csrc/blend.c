/*
 * blend.c — ScLERP, DLB, DIB and the baselines Lin, Dec, Log, and the one dispatch over them
 * (dq_blend_set). Conventions in dq.h.
 */
/* GCC will not if-convert a select over a division while FP traps count as side effects, and
 * then the batch loops do not vectorise. This changes no value: it is not -ffast-math (NaN,
 * infinities, signed zeros and rounding are untouched); it applies to this file, before the
 * headers so their inline functions get it too. */
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC optimize("no-trapping-math")
#endif

#include "blend.h"

#include <math.h>

#include "dq.h"
#include "vecmath.h"

/* The same threshold as dq_screw: below it m' = d_perp / phi could overflow, and the rotation
 * is far below rounding, so the pair is interpolated as a pure translation. */
#define SCLERP_MIN_PHI 1e-150

/* Rows of the block in the batch loops. */
#define DQ_BLK 64

/* ---- ScLERP ----------------------------------------------------------------------------- */

void dq_sclerp_prepare(const double *a, const double *b, dq_sclerp_pair *p)
{
    double ac[8], bb[8], rel[8], l[6];
    double dot = a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3];
    double sg = dot < 0.0 ? -1.0 : 1.0; /* shortest path */
    for (int i = 0; i < 8; i++) bb[i] = sg * b[i];
    dq_conj(a, ac);
    dq_mul(ac, bb, rel);
    dq_log(rel, l);
    double phi = sqrt(l[0] * l[0] + l[1] * l[1] + l[2] * l[2]);
    for (int i = 0; i < 4; i++) { p->p0[i] = a[i]; p->p3[i] = a[4 + i]; }
    p->phi = phi;
    if (phi > SCLERP_MIN_PHI) {
        double s[4] = {0.0, l[0] / phi, l[1] / phi, l[2] / phi};
        double h = s[1] * l[3] + s[2] * l[4] + s[3] * l[5];
        double m[4] = {0.0, (l[3] - h * s[1]) / phi, (l[4] - h * s[2]) / phi,
                       (l[5] - h * s[3]) / phi};
        double t1[4], t2[4];
        p->h = h;
        p->pure = 0;
        dq_qmul(a, s, p->p1);
        dq_qmul(a + 4, s, t1);
        dq_qmul(a, m, t2);
        for (int i = 0; i < 4; i++) { p->q[i] = t1[i] + t2[i]; p->p2[i] = 0.0; }
    } else {
        double d[4] = {0.0, l[3], l[4], l[5]};
        p->h = 0.0;
        p->pure = 1;
        dq_qmul(a, d, p->p2);
        for (int i = 0; i < 4; i++) { p->p1[i] = 0.0; p->q[i] = 0.0; }
    }
}

/* a exp(tau l) with exp(tau l) = (C + S s) + eps (-tau h S + S m' + tau h C s),
 * C = cos(tau phi), S = sin(tau phi); the products with a are the precomputed p0..q. */
void dq_sclerp_eval(const dq_sclerp_pair *p, double tau, double *out)
{
    if (p->pure) {
        for (int i = 0; i < 4; i++) {
            out[i] = p->p0[i];
            out[4 + i] = p->p3[i] + tau * p->p2[i];
        }
        return;
    }
    double ang = tau * p->phi;
    double C = cos(ang), S = sin(ang);
    double th = tau * p->h;
    for (int i = 0; i < 4; i++) {
        out[i] = C * p->p0[i] + S * p->p1[i];
        out[4 + i] = C * p->p3[i] + S * p->q[i] + th * (C * p->p1[i] - S * p->p0[i]);
    }
}

void dq_sclerp(const double *a, const double *b, double tau, double *out)
{
    dq_sclerp_pair p;
    dq_sclerp_prepare(a, b, &p);
    dq_sclerp_eval(&p, tau, out);
}

/* s log(a b) for unit a, b, as dq_log but with both of its branches computed and one selected,
 * so the block loops that inline it vectorise. The product is put in the short hemisphere. */
static inline void scaled_log_of_product(const double *a, const double *b, double s, double *l)
{
    double r[4], d1[4], d2[4];
    dq_qmul(a, b, r);
    dq_qmul(a, b + 4, d1);
    dq_qmul(a + 4, b, d2);
    double sg = r[0] < 0.0 ? -1.0 : 1.0; /* the short way round */
    double w0 = sg * r[0], v0 = sg * r[1], v1 = sg * r[2], v2 = sg * r[3];
    double wd = sg * (d1[0] + d2[0]), u0 = sg * (d1[1] + d2[1]);
    double u1 = sg * (d1[2] + d2[2]), u2 = sg * (d1[3] + d2[3]);
    double x = v0 * v0 + v1 * v1 + v2 * v2;
    double as = 1.0 + x * (1.0 / 6 + x * (3.0 / 40 + x * (5.0 / 112 + x * (35.0 / 1152
          + x * (63.0 / 2816 + x * (231.0 / 13312 + x * (143.0 / 10240)))))));
    double bs = 1.0 / 3 + x * (2.0 / 15 + x * (8.0 / 105 + x * (16.0 / 315 + x * (128.0 / 3465
          + x * (256.0 / 9009 + x * (1024.0 / 45045 + x * (2048.0 / 109395)))))));
    double n = sqrt(x);
    double acl = atan2_q1(n, w0) / n;
    double bcl = (1.0 - acl * w0) / x;
    int ser = x < DQ_LOG_SERIES_MAX;
    double la = ser ? as : acl, lb = ser ? bs : bcl;
    double vu = v0 * u0 + v1 * u1 + v2 * u2;
    double k = lb * (w0 * vu - wd * x);
    l[0] = s * (la * v0); l[1] = s * (la * v1); l[2] = s * (la * v2);
    l[3] = s * (la * u0 + k * v0);
    l[4] = s * (la * u1 + k * v1);
    l[5] = s * (la * u2 + k * v2);
}

/* Independent pairs: a_i exp(tau_i log(a_i* b_i)), in blocks like log_sum. Here nothing is
 * shared between the poses, so the screw form of dq_sclerp_prepare would cost more than it
 * saves; exp and log are written out with both of their branches and a select. */
DQ_INLINE void sclerp_block(const double *restrict a, const double *restrict b,
                                const double *restrict tau, size_t m, double *restrict out)
{
    double L[6][DQ_BLK], E[8][DQ_BLK];
    /* 1: tau log(a* b) */
    for (size_t j = 0; j < m; j++) {
        const double *aj = a + 8 * j;
        double ac[8] = {aj[0], -aj[1], -aj[2], -aj[3], aj[4], -aj[5], -aj[6], -aj[7]};
        double l[6];
        /* the log's own hemisphere choice is the shortest path: (a* b)_w = <a_r, b_r> */
        scaled_log_of_product(ac, b + 8 * j, tau[j], l);
        for (int k = 0; k < 6; k++) L[k][j] = l[k];
    }
    /* 2: exp, as dq_exp */
    for (size_t j = 0; j < m; j++) {
        double lr0 = L[0][j], lr1 = L[1][j], lr2 = L[2][j];
        double ld0 = L[3][j], ld1 = L[4][j], ld2 = L[5][j];
        double y = lr0 * lr0 + lr1 * lr1 + lr2 * lr2;
        double rd = lr0 * ld0 + lr1 * ld1 + lr2 * ld2;
        double css = 1.0 + y * (-1.0 / 2 + y * (1.0 / 24 + y * (-1.0 / 720 + y * (1.0 / 40320
              + y * (-1.0 / 3628800 + y * (1.0 / 479001600))))));
        double scs = 1.0 + y * (-1.0 / 6 + y * (1.0 / 120 + y * (-1.0 / 5040 + y * (1.0 / 362880
              + y * (-1.0 / 39916800 + y * (1.0 / 6227020800.0))))));
        double cs_ = -1.0 / 3 + y * (1.0 / 30 + y * (-1.0 / 840 + y * (1.0 / 45360
              + y * (-1.0 / 3991680 + y * (1.0 / 518918400 + y * (-1.0 / 93405312000.0))))));
        double phi = sqrt(y);
        double sn, cn;
        sincos_v(y < DQ_SINCOS_MAX * DQ_SINCOS_MAX ? phi : 0.0, &sn, &cn);
        double scl = sn / phi, ccl = (phi * cn - sn) / (phi * y);
        int es = y < 1e-2;
        double cs = es ? css : cn, sc = es ? scs : scl, c = es ? cs_ : ccl;
        double kk = c * rd;
        E[0][j] = cs; E[1][j] = sc * lr0; E[2][j] = sc * lr1; E[3][j] = sc * lr2;
        E[4][j] = -sc * rd;
        E[5][j] = sc * ld0 + kk * lr0;
        E[6][j] = sc * ld1 + kk * lr1;
        E[7][j] = sc * ld2 + kk * lr2;
    }
    /* 3: a e, as dq_mul */
    for (size_t j = 0; j < m; j++) {
        const double *aj = a + 8 * j;
        double e[8] = {E[0][j], E[1][j], E[2][j], E[3][j], E[4][j], E[5][j], E[6][j], E[7][j]};
        double o[4], d1[4], d2[4];
        double *oj = out + 8 * j;
        dq_qmul(aj, e, o);
        dq_qmul(aj, e + 4, d1);
        dq_qmul(aj + 4, e, d2);
        oj[0] = o[0]; oj[1] = o[1]; oj[2] = o[2]; oj[3] = o[3];
        oj[4] = d1[0] + d2[0]; oj[5] = d1[1] + d2[1]; oj[6] = d1[2] + d2[2]; oj[7] = d1[3] + d2[3];
    }
}

/* One block of pairs: the kernel, then the pairs whose tau is beyond its sin/cos reduction's
 * range (|tau| ~ 1e5 and more) by libm's sin/cos. */
DQ_INLINE void sclerp_pairs_block(const double *restrict a, const double *restrict b,
                                  const double *restrict tau, size_t m, double *restrict out)
{
    sclerp_block(a, b, tau, m, out);
    for (size_t j = 0; j < m; j++) {
        double t = tau[j];
        if (t > 1e4 || t < -1e4) dq_sclerp(a + 8 * j, b + 8 * j, t, out + 8 * j);
    }
}

DQ_CLONES void dq_sclerp_pairs(const double *a, const double *b, const double *tau, size_t n,
                              double *out)
{
    for (size_t i0 = 0; i0 < n; i0 += DQ_BLK) {
        size_t m = n - i0 < DQ_BLK ? n - i0 : DQ_BLK;
        sclerp_pairs_block(a + 8 * i0, b + 8 * i0, tau + i0, m, out + 8 * i0);
    }
}

DQ_CLONES int dq_sclerp_pairs_checked(const double *a, const double *b, const double *tau,
                                      size_t n, double *out)
{
    double ua[8 * DQ_BLK], ub[8 * DQ_BLK];
    for (size_t i0 = 0; i0 < n; i0 += DQ_BLK) {
        size_t m = n - i0 < DQ_BLK ? n - i0 : DQ_BLK;
        const double *pa = a + 8 * i0, *pb = b + 8 * i0, *pt = tau + i0;
        double *po = out + 8 * i0;
        /* the block's checks in one pass without branches (it vectorises): every pose as
         * dq_unit would use it as it is, every tau finite */
        int plain = 1;
        for (size_t j = 0; j < m; j++)
            plain &= dq_unit_as_is(pa + 8 * j) & dq_unit_as_is(pb + 8 * j) & (pt[j] * 0.0 == 0.0);
        if (!plain) {
            /* a pose to normalise (or refuse): the block's poses through dq_unit into copies */
            for (size_t j = 0; j < m; j++) {
                int rc = dq_unit(pa + 8 * j, ua + 8 * j);
                if (rc == DQ_OK) rc = dq_unit(pb + 8 * j, ub + 8 * j);
                if (rc == DQ_OK && !(pt[j] * 0.0 == 0.0)) rc = DQ_E_NONFINITE;
                if (rc != DQ_OK) return rc;
            }
            pa = ua;
            pb = ub;
        }
        sclerp_pairs_block(pa, pb, pt, m, po);
        if (!dq_finite_n(po, 8 * m)) return DQ_E_OVERFLOW;
    }
    return DQ_OK;
}

/* ---- weights ---------------------------------------------------------------------------- */

int dq_weights(const double *w, size_t n, double *wn, size_t *bad)
{
    if (!w) {
        for (size_t i = 0; i < n; i++) wn[i] = 1.0 / (double)n;
        return DQ_OK;
    }
    double sum = 0.0, big = 0.0;
    for (size_t i = 0; i < n; i++) {
        double v = w[i];
        if (!(v * 0.0 == 0.0)) { *bad = i; return DQ_E_NONFINITE; }
        if (v < 0.0) { *bad = i; return DQ_E_WEIGHT_NEG; }
        if (v > big) big = v;
        sum += v;
    }
    if (!(sum > 0.0)) { *bad = n; return DQ_E_WEIGHT_SUM; }
    double inv = 1.0 / sum;
    if (!(sum * 0.0 == 0.0) || !(inv * 0.0 == 0.0)) {
        /* Finite weights whose sum overflows (or whose sum is subnormal, so 1/sum overflows):
         * scale by the largest first; they are still a valid set of weights. */
        sum = 0.0;
        for (size_t i = 0; i < n; i++) sum += w[i] / big;
        inv = 1.0 / sum;
        for (size_t i = 0; i < n; i++) wn[i] = (w[i] / big) * inv;
        return DQ_OK;
    }
    for (size_t i = 0; i < n; i++) wn[i] = w[i] * inv;
    return DQ_OK;
}

/* ---- DLB -------------------------------------------------------------------------------- */

static size_t argmax(const double *w, size_t n)
{
    size_t k = 0;
    for (size_t i = 1; i < n; i++)
        if (w[i] > w[k]) k = i;
    return k;
}

static void normalize_unit(double *q)
{
    double rr = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3];
    double inv = 1.0 / sqrt(rr);
    double k = (q[0] * q[4] + q[1] * q[5] + q[2] * q[6] + q[3] * q[7]) * inv * inv;
    for (int i = 0; i < 4; i++) {
        q[4 + i] = (q[4 + i] - k * q[i]) * inv;
        q[i] *= inv;
    }
}

/* Vectorising this loop across poses needs stride-8 gathers and measured 1.5x slower than the
 * scalar loop (which GCC still pairs up within a pose). */
#if defined(__GNUC__) && !defined(__clang__)
__attribute__((optimize("no-tree-loop-vectorize")))
#endif
void dq_dlb(const double *q, const double *w, size_t n, double *out)
{
    const double *pv = q + 8 * argmax(w, n);
    const double p0 = pv[0], p1 = pv[1], p2 = pv[2], p3 = pv[3];
    /* Named accumulators rather than an array: GCC keeps them in registers. */
    double s0 = 0, s1 = 0, s2 = 0, s3 = 0, s4 = 0, s5 = 0, s6 = 0, s7 = 0;
    for (size_t i = 0; i < n; i++) {
        const double *qi = q + 8 * i;
        double dot = p0 * qi[0] + p1 * qi[1] + p2 * qi[2] + p3 * qi[3];
        /* copysign, not a branch: the signs of real data are unpredictable */
        double wi = copysign(w[i], dot);
        s0 += wi * qi[0]; s1 += wi * qi[1]; s2 += wi * qi[2]; s3 += wi * qi[3];
        s4 += wi * qi[4]; s5 += wi * qi[5]; s6 += wi * qi[6]; s7 += wi * qi[7];
    }
    /* <pivot, s> >= w_pivot > 0, so the real part never vanishes. */
    double s[8] = {s0, s1, s2, s3, s4, s5, s6, s7};
    normalize_unit(s);
    for (int k = 0; k < 8; k++) out[k] = s[k];
}

/* ---- DIB -------------------------------------------------------------------------------- */

/* w_i log(bc q_i) for a block of m <= DQ_BLK poses, as the columns of L: dq_mul and dq_log
 * (both branches, then a select) written out so the loop vectorises. */
static inline void wlog_block(const double *bc, const double *q, const double *w,
                                     size_t m, double L[6][DQ_BLK])
{
    for (size_t j = 0; j < m; j++) {
        const double *qi = q + 8 * j;
        double l[6];
        scaled_log_of_product(bc, qi, w[j], l);
        for (int k = 0; k < 6; k++) L[k][j] = l[k];
    }
}

/* Weighted sum of log(bc q_i) for all i, where bc is the conjugate of the current mean. */
DQ_CLONES static double log_sum(const double *bc, const double *q, const double *w, size_t n,
                               double *x)
{
    double x0 = 0, x1 = 0, x2 = 0, x3 = 0, x4 = 0, x5 = 0;
    double L[6][DQ_BLK];
    for (size_t i0 = 0; i0 < n; i0 += DQ_BLK) {
        size_t m = n - i0 < DQ_BLK ? n - i0 : DQ_BLK;
        wlog_block(bc, q + 8 * i0, w + i0, m, L);
        /* Summed in order, outside the vector loop, so the result does not depend on the width. */
        for (size_t j = 0; j < m; j++) {
            x0 += L[0][j]; x1 += L[1][j]; x2 += L[2][j];
            x3 += L[3][j]; x4 += L[4][j]; x5 += L[5][j];
        }
    }
    x[0] = x0; x[1] = x1; x[2] = x2; x[3] = x3; x[4] = x4; x[5] = x5;
    return sqrt(x0 * x0 + x1 * x1 + x2 * x2 + x3 * x3 + x4 * x4 + x5 * x5);
}

void dq_dib(const double *q, const double *w, size_t n, double tol, int max_iter, double *out,
            int *iters, double *residual)
{
    double b[8], bc[8], x[6], e[8], nb[8];
    dq_dlb(q, w, n, b);
    int k = 0;
    double res;
    for (;;) {
        dq_conj(b, bc);
        res = log_sum(bc, q, w, n, x);
        /* "!(res >= tol)" also ends the loop on NaN, which validated input never produces. */
        if (!(res >= tol) || k >= max_iter) break;
        dq_exp(x, e);
        dq_mul(b, e, nb);
        for (int i = 0; i < 8; i++) b[i] = nb[i];
        k++;
    }
    /* Products of unit dual quaternions drift off the unit manifold by rounding only (~1e-16 a
     * step), which the log-sum does not notice; one normalisation at the end removes it. */
    normalize_unit(b);
    for (int i = 0; i < 8; i++) out[i] = b[i];
    *iters = k;
    *residual = res;
}

/* ---- baselines -------------------------------------------------------------------------- */

void dq_lin(const double *q, const double *w, size_t n, double *m_out)
{
    double m[16];
    for (int k = 0; k < 16; k++) m_out[k] = 0.0;
    for (size_t i = 0; i < n; i++) {
        dq_to_matrix(q + 8 * i, m);
        for (int k = 0; k < 16; k++) m_out[k] += w[i] * m[k];
    }
    /* The weights sum to 1 up to rounding; the bottom row is exactly [0 0 0 1] by definition. */
    m_out[12] = m_out[13] = m_out[14] = 0.0;
    m_out[15] = 1.0;
}

void dq_dec(const double *q, const double *w, size_t n, double tol, int max_iter, double *out)
{
    /* Rotation: the spherical weighted mean (Buss and Fillmore), computed as DIB on the
     * rotation parts alone; for two poses it is slerp. Translation: the weighted mean. */
    double t[3] = {0, 0, 0}, r[4] = {0, 0, 0, 0};
    const double *pv = q + 8 * argmax(w, n);
    for (size_t i = 0; i < n; i++) {
        double qi[4], ti[3];
        dq_to_pose(q + 8 * i, qi, ti);
        double dot = pv[0] * qi[0] + pv[1] * qi[1] + pv[2] * qi[2] + pv[3] * qi[3];
        double wi = dot < 0.0 ? -w[i] : w[i];
        for (int k = 0; k < 4; k++) r[k] += wi * qi[k];
        for (int k = 0; k < 3; k++) t[k] += w[i] * ti[k];
    }
    double b[8] = {r[0], r[1], r[2], r[3], 0, 0, 0, 0};
    normalize_unit(b);
    for (int it = 0; it <= max_iter; it++) {
        double x[6] = {0, 0, 0, 0, 0, 0}, bc[8], e[8], nb[8];
        dq_conj(b, bc);
        for (size_t i = 0; i < n; i++) {
            const double *qi = q + 8 * i;
            double rot[8] = {qi[0], qi[1], qi[2], qi[3], 0, 0, 0, 0}, rel[8], l[6];
            dq_mul(bc, rot, rel);
            dq_log(rel, l);
            for (int k = 0; k < 3; k++) x[k] += w[i] * l[k];
        }
        double res = sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2]);
        if (!(res >= tol) || it == max_iter) break;
        dq_exp(x, e);
        dq_mul(b, e, nb);
        normalize_unit(nb);
        for (int k = 0; k < 8; k++) b[k] = nb[k];
    }
    double rq[4] = {b[0], b[1], b[2], b[3]};
    dq_from_pose(rq, t, out);
}

void dq_logblend(const double *q, const double *w, size_t n, double *out)
{
    double x[6] = {0, 0, 0, 0, 0, 0};
    for (size_t i = 0; i < n; i++) {
        double l[6];
        dq_log(q + 8 * i, l);
        for (int k = 0; k < 6; k++) x[k] += w[i] * l[k];
    }
    dq_exp(x, out);
}

/* ---- the dispatch ----------------------------------------------------------------------- */

int dq_method_known(int method)
{
    switch (method) {
#define DQ_METHOD_CASE_(name, value) case DQ_##name:
    DQ_METHODS(DQ_METHOD_CASE_)
#undef DQ_METHOD_CASE_
        return 1;
    default:
        return 0;
    }
}

int dq_blend_check(int method, size_t n)
{
    if (!dq_method_known(method)) return DQ_E_METHOD;
    if (method == DQ_SCLERP && n != 2) return DQ_E_SET_SIZE;
    return DQ_OK;
}

int dq_blend_set(const double *q, const double *w, size_t n, const dq_blend_params *p,
                 double *out, int *iters, double *residual)
{
    int rc = dq_blend_check(p->method, n);
    *iters = 0;
    *residual = 0.0;
    if (rc) return rc;
    switch ((dq_method)p->method) {
    case DQ_DIB: dq_dib(q, w, n, p->tol, p->max_iter, out, iters, residual); break;
    case DQ_DLB: dq_dlb(q, w, n, out); break;
    /* the pair with weights (1 - tau, tau) */
    case DQ_SCLERP: dq_sclerp(q, q + 8, w[1], out); break;
    case DQ_LIN: {
        double m[16], quat[4];
        dq_lin(q, w, n, m);
        if (!dq_finite_n(m, 16)) return DQ_E_OVERFLOW;
        dq_nearest_rotation(m, quat);
        double t[3] = {m[3], m[7], m[11]};
        rc = dq_from_pose(quat, t, out);
        if (rc) return DQ_E_OVERFLOW;
        break;
    }
    case DQ_DEC: dq_dec(q, w, n, p->tol, p->max_iter, out); break;
    case DQ_LOG: dq_logblend(q, w, n, out); break;
    }
    if (!dq_finite8(out) || !(*residual * 0.0 == 0.0)) return DQ_E_OVERFLOW;
    return DQ_OK;
}
