/*
 * blend.c — ScLERP, DLB, DIB and the baselines Lin, Dec, Log. Conventions in dq.h.
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

/* The same threshold as dq_screw: below it m' = d_perp / phi could overflow, and the rotation
 * is far below rounding, so the pair is interpolated as a pure translation. */
#define SCLERP_MIN_PHI 1e-150

/* ---- vector-friendly elementary functions ----------------------------------------------------
 * The batch loops below run over blocks of poses stored side by side, with every branch written
 * as a select, so GCC vectorises them. libm's atan2/sin/cos are calls and stop that, so these
 * loops use Cephes' atan (rational 4/5, ~1 ulp) and sin/cos kernels (Cody-Waite reduction by
 * pi/2, ~1 ulp) instead. */

/* Where the compiler supports it, the batch loops are built twice, for AVX2 and for the baseline
 * ISA, and the loader picks one (ifunc). ISO C mode (-std=c99) means -ffp-contract=off, so no
 * FMA is formed and both versions give the same bits. */
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && defined(__linux__) && \
    !defined(DQ_NO_CLONES)
#define DQ_CLONES __attribute__((target_clones("avx2", "default")))
#else
#define DQ_CLONES
#endif
#define DQ_BATCH DQ_CLONES

#define DQ_PIO2 1.57079632679489661923
#define DQ_PIO4 7.85398163397448309616E-1
#define DQ_MOREBITS 6.123233995736765886130E-17 /* pi/2 - DQ_PIO2 */
/* Rows of the block in the batch loops. */
#define DQ_BLK 64

/* atan(t) for t in [0, 1] */
static inline double atan_01(double t)
{
    int big = t > 0.66;
    double tr = (t - 1.0) / (t + 1.0); /* unconditionally, so the select needs no branch */
    double x = big ? tr : t;
    double y = big ? DQ_PIO4 : 0.0;
    double mb = big ? 0.5 * DQ_MOREBITS : 0.0;
    double z = x * x;
    double p = ((((-8.750608600031904122785E-1 * z - 1.615753718733365076637E1) * z
                  - 7.500855792314704667340E1) * z - 1.228866684490136173410E2) * z
                - 6.485021904942025371773E1) * z;
    double q = ((((z + 2.485846490142306297962E1) * z + 1.650270098316988542046E2) * z
                 + 4.328810604912902668951E2) * z + 4.853903996359136964868E2) * z
               + 1.945506571482613964425E2;
    return y + ((x * (p / q) + x) + mb);
}

/* atan2(n, w) for n, w >= 0, not both zero */
static inline double atan2_q1(double n, double w)
{
    int swap = n > w;
    double r = atan_01((swap ? w : n) / (swap ? n : w));
    return swap ? DQ_PIO2 + (DQ_MOREBITS - r) : r;
}

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

/* ---- weights ---------------------------------------------------------------------------- */

int dq_weights(const double *w, size_t n, double *wn, size_t *bad)
{
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

void dq_dlb(const double *q, const double *w, size_t n, double *out)
{
    const double *pv = q + 8 * argmax(w, n);
    double s[8] = {0, 0, 0, 0, 0, 0, 0, 0};
    for (size_t i = 0; i < n; i++) {
        const double *qi = q + 8 * i;
        double dot = pv[0] * qi[0] + pv[1] * qi[1] + pv[2] * qi[2] + pv[3] * qi[3];
        double wi = dot < 0.0 ? -w[i] : w[i];
        for (int k = 0; k < 8; k++) s[k] += wi * qi[k];
    }
    /* <pivot, s> >= w_pivot > 0, so the real part never vanishes. */
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
        double r[4], d1[4], d2[4];
        dq_qmul(bc, qi, r);
        dq_qmul(bc, qi + 4, d1);
        dq_qmul(bc + 4, qi, d2);
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
        double ac = atan2_q1(n, w0) / n;
        double bcl = (1.0 - ac * w0) / x;
        int ser = x < DQ_LOG_SERIES_MAX;
        double a = ser ? as : ac, b = ser ? bs : bcl;
        double vu = v0 * u0 + v1 * u1 + v2 * u2;
        double k = b * (w0 * vu - wd * x);
        double wi = w[j];
        L[0][j] = wi * (a * v0); L[1][j] = wi * (a * v1); L[2][j] = wi * (a * v2);
        L[3][j] = wi * (a * u0 + k * v0);
        L[4][j] = wi * (a * u1 + k * v1);
        L[5][j] = wi * (a * u2 + k * v2);
    }
}

/* Weighted sum of log(bc q_i) for all i, where bc is the conjugate of the current mean. */
DQ_BATCH static double log_sum(const double *bc, const double *q, const double *w, size_t n,
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
        normalize_unit(nb); /* keeps rounding from drifting off the unit manifold */
        for (int i = 0; i < 8; i++) b[i] = nb[i];
        k++;
    }
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
