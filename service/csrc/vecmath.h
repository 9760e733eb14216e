/*
 * vecmath.h — what the core's vectorised batch loops share (blend.c: ScLERP pairs and the DIB
 * log-sum; traj_eval.c: dense evaluation): branch-free elementary functions, 3-vector helpers,
 * and the AVX2 / baseline clones.
 */
#ifndef DQPOSE_VECMATH_H
#define DQPOSE_VECMATH_H

#include <math.h>

/* ---- vector-friendly elementary functions ----------------------------------------------------
 * The batch loops run over blocks of poses stored side by side, with every branch written
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
/* A loop body that a clone calls must be inlined into it to be compiled for the clone's ISA;
 * GCC keeps a large body called from two clones out of line (baseline ISA for both) unless told. */
#if defined(__GNUC__)
#define DQ_INLINE static inline __attribute__((always_inline))
#else
#define DQ_INLINE static inline
#endif

/* Four doubles in one vector (GCC's vector extension; two SSE2 registers without AVX2): the
 * element-wise IEEE operations of the scalar code, lane by lane, so a loop over four problems
 * gives each the bits it has alone (ISO C: no FMA contraction). */
#if defined(__GNUC__)
#define DQ_V4 1
#include <string.h>
typedef double dq_v4 __attribute__((vector_size(32)));
#define dq_v4_of(x) ((dq_v4){(x), (x), (x), (x)})
#define dq_v4_load(p) (__extension__({ dq_v4 v_; memcpy(&v_, (p), sizeof v_); v_; }))
#define dq_v4_store(p, v) (__extension__({ dq_v4 v_ = (v); memcpy((p), &v_, sizeof v_); }))
#else
#define DQ_V4 0
#endif

#define DQ_PIO2 1.57079632679489661923
#define DQ_PIO4 7.85398163397448309616E-1
#define DQ_MOREBITS 6.123233995736765886130E-17 /* pi/2 - DQ_PIO2 */

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

/* Angles beyond this go to libm: the three-part Cody-Waite reduction stays exact far past it. */
#define DQ_SINCOS_MAX 1e5

/* sin and cos of x for |x| <= DQ_SINCOS_MAX: reduction by pi/2 (Cephes' DP1..DP3 split, so
 * k * part is exact), Cephes' kernels on [-pi/4, pi/4], quadrant by selects. */
static inline void sincos_v(double x, double *s_out, double *c_out)
{
    const double magic = 6755399441055744.0; /* 1.5 * 2^52: adding it rounds to an integer */
    double kd = (x * 0.63661977236758134308 + magic) - magic;
    double r = ((x - kd * 1.57079625129699707031) - kd * 7.54978941586159635335E-8)
               - kd * 5.39030285815811905290E-15;
    double z = r * r;
    double s = r + r * (z * (((((1.58962301576546568060E-10 * z - 2.50507477628578072866E-8) * z
                 + 2.75573136213857245213E-6) * z - 1.98412698295895385996E-4) * z
                 + 8.33333333332211858878E-3) * z - 1.66666666666666307295E-1));
    double c = 1.0 - 0.5 * z + z * z * (((((-1.13585365213876817300E-11 * z
                 + 2.08757008419747316778E-9) * z - 2.75573141792967388112E-7) * z
                 + 2.48015872888517045348E-5) * z - 1.38888888888730564116E-3) * z
                 + 4.16666666666665929218E-2);
    /* quadrant k mod 4 as q = k - 4 round(k / 4) in {-2, -1, 0, 1, 2} */
    double qd = kd - 4.0 * ((kd * 0.25 + magic) - magic);
    double so = fabs(qd) == 1.0 ? c : s, co = fabs(qd) == 1.0 ? s : c;
    *s_out = fabs(qd - 0.5) > 1.0 ? -so : so; /* negated in quadrants 2 and 3 (-1) */
    *c_out = fabs(qd + 0.5) > 1.0 ? -co : co; /* negated in quadrants 1 and 2 */
}

/* ---- 3-vectors and selects ------------------------------------------------------------------ */

/* fmin/fmax are library calls under -std=c99; nothing here is NaN (the input is checked). */
static inline double lo2(double a, double b) { return a < b ? a : b; }
static inline double hi2(double a, double b) { return a > b ? a : b; }

static inline double norm3(const double *v) { return sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]); }

DQ_INLINE void cross3(const double *a, const double *b, double *c)
{
    c[0] = a[1] * b[2] - a[2] * b[1];
    c[1] = a[2] * b[0] - a[0] * b[2];
    c[2] = a[0] * b[1] - a[1] * b[0];
}

/* R(q) v for a unit quaternion q = (w, u): v + 2w (u x v) + 2 u x (u x v) */
DQ_INLINE void rotate(const double *q, const double *v, double *out)
{
    double t[3], tt[3];
    cross3(q + 1, v, t);
    for (int i = 0; i < 3; i++) t[i] *= 2.0;
    cross3(q + 1, t, tt);
    for (int i = 0; i < 3; i++) out[i] = v[i] + q[0] * t[i] + tt[i];
}

#endif
