/*
 * se3.c — the SE(3) Jacobians of se3.h: their coefficients (closed form, or Taylor series near
 * the identity) and the 3 x 3 blocks they are built from.
 */
#include "se3.h"

#include <math.h>

#include "dq.h"
#include "linalg6.h"
#include "vecmath.h"

/* Below this rotation angle the Jacobian coefficients come from their Taylor series (the closed
 * forms divide cancelling differences by up to t^5); service/lie.py uses the same. */
#define SERIES_ANGLE 0.5

static double series8(const double *c, double t2)
{
    double s = 0.0;
    for (int k = 7; k >= 0; k--) s = s * t2 + c[k];
    return s;
}

static const double B_SERIES[8] = {1.0 / 2, -1.0 / 24, 1.0 / 720, -1.0 / 40320, 1.0 / 3628800,
                                   -1.0 / 479001600, 1.0 / 87178291200.0,
                                   -1.0 / 20922789888000.0};
static const double C_SERIES[8] = {1.0 / 6, -1.0 / 120, 1.0 / 5040, -1.0 / 362880, 1.0 / 39916800,
                                   -1.0 / 6227020800.0, 1.0 / 1307674368000.0,
                                   -1.0 / 355687428096000.0};
static const double C2_SERIES[8] = {1.0 / 24, -1.0 / 720, 1.0 / 40320, -1.0 / 3628800,
                                    1.0 / 479001600, -1.0 / 87178291200.0,
                                    1.0 / 20922789888000.0, -1.0 / 6402373705728000.0};
static const double C3_SERIES[8] = {1.0 / 120, -1.0 / 2520, 1.0 / 120960, -1.0 / 9979200,
                                    1.0 / 1245404160, -1.0 / 217945728000.0,
                                    1.0 / 50812489728000.0, -1.0 / 15205637551104000.0};
static const double D_SERIES[8] = {1.0 / 12, 1.0 / 720, 1.0 / 30240, 1.0 / 1209600,
                                   1.0 / 47900160, 691.0 / 1307674368000.0,
                                   1.0 / 74724249600.0, 3617.0 / 10670622842880000.0};

static inline void mul3(const double *a, const double *b, double *restrict c)
{
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            c[3 * i + j] = a[3 * i] * b[j] + a[3 * i + 1] * b[3 + j] + a[3 * i + 2] * b[6 + j];
}

static inline void hat3(const double *w, double *K)
{
    K[0] = 0.0;   K[1] = -w[2]; K[2] = w[1];
    K[3] = w[2];  K[4] = 0.0;   K[5] = -w[0];
    K[6] = -w[1]; K[7] = w[0];  K[8] = 0.0;
}

/* The coefficients of the SE(3) Jacobians at a rotation of squared angle t2: B = (1 - cos t)/t^2
 * and C = (t - sin t)/t^3 of Jl = I + B w^ + C w^2, c2, c3 of Q (Barfoot's eq. 7.86) and
 * D = (1 - (t/2) cot(t/2))/t^2 of Jl^-1 = I - w^/2 + D w^2 (the formulas of service/lie.py). s2, ch
 * are the squared sine and the cosine of half the angle, from the quaternion the rotation came
 * from, so no trigonometric call is needed. */
typedef struct { double B, C, c2, c3, D; } jac_coef;

static inline jac_coef jacobian_coefficients(double t2, double s2, double ch)
{
    jac_coef k;
    if (t2 < SERIES_ANGLE * SERIES_ANGLE) {
        k.B = series8(B_SERIES, t2);
        k.C = series8(C_SERIES, t2);
        k.c2 = series8(C2_SERIES, t2);
        k.c3 = series8(C3_SERIES, t2);
        k.D = series8(D_SERIES, t2);
    } else {
        double t = sqrt(t2), sh = sqrt(s2), it2 = 1.0 / t2, it3 = it2 / t;
        double st = 2.0 * sh * ch, ct = 1.0 - 2.0 * s2;
        k.B = 2.0 * s2 * it2;
        k.C = (t - st) * it3;
        k.c2 = 0.5 * (t2 - 4.0 * s2) * it2 * it2;
        k.c3 = 0.5 * (2.0 * t - 3.0 * st + t * ct) * it3 * it2;
        k.D = (1.0 - 0.5 * t * ch / sh) * it2;
    }
    return k;
}

/* Q(w, v), the lower-left block of Jl(xi). Its products of w^ and v^ collapse to rank-one terms
 * (a^ b^ = b a^T - (a.b) I, w^ w = 0): w^ v^ w^ = -(w.v) w^, w^ w^ = w w^T - t^2 I,
 * w^ w^ v^ + v^ w^ w^ = w u^T - u w^T - 2 t^2 v^ with u = w x v; so Q = v^/2
 * + C (v w^T + w v^T - 2(w.v) I - (w.v) w^) + c2 (w u^T - u w^T - 2 t^2 v^ + 3 (w.v) w^)
 * - 2 c3 (w.v) (w w^T - t^2 I). */
static inline void q_block(const double *w, const double *v, double t2, const jac_coef *k,
                           double *restrict Q)
{
    double wv = w[0] * v[0] + w[1] * v[1] + w[2] * v[2];
    double u[3] = {w[1] * v[2] - w[2] * v[1], w[2] * v[0] - w[0] * v[2], w[0] * v[1] - w[1] * v[0]};
    double W[9], V[9];
    hat3(w, W);
    hat3(v, V);
    double kv = 0.5 - 2.0 * k->c2 * t2, kw = 3.0 * k->c2 * wv - k->C * wv, kww = -2.0 * k->c3 * wv;
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            double ww = w[i] * w[j] - (i == j ? t2 : 0.0);
            Q[3 * i + j] = kv * V[3 * i + j] + kw * W[3 * i + j] +
                           k->C * (v[i] * w[j] + w[i] * v[j] - (i == j ? 2.0 * wv : 0.0)) +
                           k->c2 * (w[i] * u[j] - u[i] * w[j]) + kww * ww;
        }
}

void dq_jl_inv(const double *xi, double s2, double ch, double *restrict J)
{
    const double *w = xi, *v = xi + 3;
    double t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2];
    jac_coef k = jacobian_coefficients(t2, s2, ch);
    double W[9], Q[9], Ji[9], T[9], M[9];
    q_block(w, v, t2, &k, Q);
    hat3(w, W);
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            double ww = w[i] * w[j] - (i == j ? t2 : 0.0);
            Ji[3 * i + j] = (i == j ? 1.0 : 0.0) - 0.5 * W[3 * i + j] + k.D * ww;
        }
    mul3(Ji, Q, T);
    mul3(T, Ji, M);
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            double a = Ji[3 * i + j];
            J[6 * i + j] = a;
            J[6 * i + 3 + j] = 0.0;
            J[6 * (i + 3) + j] = -M[3 * i + j];
            J[6 * (i + 3) + 3 + j] = a;
        }
}

/* s Jl(-xi) = s [[Jl(w), 0], [Q(w, v), Jl(w)]] at (w, v) = -xi. */
void dq_jr_scaled(const double *xi, double s2, double ch, double s, double *J, int ld)
{
    double w[3] = {-xi[0], -xi[1], -xi[2]}, v[3] = {-xi[3], -xi[4], -xi[5]};
    double t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2];
    jac_coef k = jacobian_coefficients(t2, s2, ch);
    double W[9], Q[9];
    q_block(w, v, t2, &k, Q);
    hat3(w, W);
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            double ww = w[i] * w[j] - (i == j ? t2 : 0.0);
            double a = s * ((i == j ? 1.0 : 0.0) + k.B * W[3 * i + j] + k.C * ww);
            J[ld * i + j] = a;
            J[ld * i + 3 + j] = 0.0;
            J[ld * (i + 3) + j] = s * Q[3 * i + j];
            J[ld * (i + 3) + 3 + j] = a;
        }
}

void dq_se3_residual(const double *xc, const double *z, double *r, double *sc)
{
    double p[8], l[6];
    dq_mul(xc, z, p);
    if (p[0] < 0.0)
        for (int k = 0; k < 8; k++) p[k] = -p[k];
    dq_log(p, l);
    for (int k = 0; k < 6; k++) r[k] = 2.0 * l[k];
    sc[0] = p[1] * p[1] + p[2] * p[2] + p[3] * p[3];
    sc[1] = p[0];
}


void dq_adjoint(const double *q, double *restrict Ad)
{
    double T[16];
    dq_to_matrix(q, T);
    const double t[3] = {T[3], T[7], T[11]};
    for (int a = 0; a < 3; a++)
        for (int b = 0; b < 3; b++) {
            double R = T[4 * a + b];
            double tR = (a == 0 ? -t[2] * T[4 + b] + t[1] * T[8 + b]
                         : a == 1 ? t[2] * T[b] - t[0] * T[8 + b]
                                  : -t[1] * T[b] + t[0] * T[4 + b]);
            Ad[6 * a + b] = R;
            Ad[6 * a + 3 + b] = 0.0;
            Ad[6 * (a + 3) + b] = tR;
            Ad[6 * (a + 3) + 3 + b] = R;
        }
}

int dq_retract(const double *X, const double *delta, double *out)
{
    double half[6], E[8], P[8];
    for (int k = 0; k < 6; k++) half[k] = 0.5 * delta[k];
    dq_exp(half, E);
    dq_mul(X, E, P);
    return dq_normalize(P, out);
}

/* ---- DQ_LANES measurements at a time (motion.c's Jacobians): entry k of lane l at
 * [DQ_LANES k + l], each lane the same operations in the same order as the functions above on
 * its own input (so the same bits), the lanes in one vector (two without AVX2). The series branch
 * only: a lane whose rotation is beyond SERIES_ANGLE makes them return 0 with nothing written,
 * for the scalar functions. */
#if DQ_V4
typedef dq_v4 v4;

/* (pointers, not values: a 32-byte vector passed by value has another ABI without AVX) */
DQ_INLINE void series8_v4(const double *c, const v4 *t2, v4 *out)
{
    v4 s = dq_v4_of(0.0);
    for (int k = 7; k >= 0; k--) s = s * *t2 + c[k];
    *out = s;
}

DQ_INLINE void hat3_v4(const v4 *w, v4 *K)
{
    K[0] = dq_v4_of(0.0); K[1] = -w[2];         K[2] = w[1];
    K[3] = w[2];          K[4] = dq_v4_of(0.0); K[5] = -w[0];
    K[6] = -w[1];         K[7] = w[0];          K[8] = dq_v4_of(0.0);
}

DQ_INLINE void mul3_v4(const v4 *a, const v4 *b, v4 *c)
{
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            c[3 * i + j] = a[3 * i] * b[j] + a[3 * i + 1] * b[3 + j] + a[3 * i + 2] * b[6 + j];
}

DQ_INLINE void q_block_v4(const v4 *w, const v4 *v, const v4 *t2p, const v4 *k, v4 *Q)
{
    const v4 t2 = *t2p, C = k[0], c2 = k[1], c3 = k[2];
    v4 wv = w[0] * v[0] + w[1] * v[1] + w[2] * v[2];
    v4 u[3] = {w[1] * v[2] - w[2] * v[1], w[2] * v[0] - w[0] * v[2], w[0] * v[1] - w[1] * v[0]};
    v4 W[9], V[9];
    hat3_v4(w, W);
    hat3_v4(v, V);
    v4 kv = 0.5 - 2.0 * c2 * t2, kw = 3.0 * c2 * wv - C * wv, kww = -2.0 * c3 * wv;
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            v4 ww = w[i] * w[j] - (i == j ? t2 : dq_v4_of(0.0));
            Q[3 * i + j] = kv * V[3 * i + j] + kw * W[3 * i + j] +
                           C * (v[i] * w[j] + w[i] * v[j] - (i == j ? 2.0 * wv : dq_v4_of(0.0))) +
                           c2 * (w[i] * u[j] - u[i] * w[j]) + kww * ww;
        }
}

/* |w|^2, and whether every lane's is within the series */
DQ_INLINE int series_v4(const v4 *w, v4 *t2)
{
    *t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2];
    const double lim = SERIES_ANGLE * SERIES_ANGLE;
    return (*t2)[0] < lim && (*t2)[1] < lim && (*t2)[2] < lim && (*t2)[3] < lim;
}

DQ_CLONES int dq_jl_inv_lanes(const double *xi, double *J)
{
    v4 w[3], v[3], t2;
    for (int k = 0; k < 3; k++) {
        w[k] = dq_v4_load(xi + 4 * k);
        v[k] = dq_v4_load(xi + 4 * (3 + k));
    }
    if (!series_v4(w, &t2)) return 0;
    v4 k[4];   /* C, c2, c3, D */
    series8_v4(C_SERIES, &t2, k);
    series8_v4(C2_SERIES, &t2, k + 1);
    series8_v4(C3_SERIES, &t2, k + 2);
    series8_v4(D_SERIES, &t2, k + 3);
    v4 Q[9], W[9], Ji[9], T[9], M[9], D = k[3];
    q_block_v4(w, v, &t2, k, Q);
    hat3_v4(w, W);
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            v4 ww = w[i] * w[j] - (i == j ? t2 : dq_v4_of(0.0));
            Ji[3 * i + j] = (i == j ? 1.0 : 0.0) - 0.5 * W[3 * i + j] + D * ww;
        }
    mul3_v4(Ji, Q, T);
    mul3_v4(T, Ji, M);
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            dq_v4_store(J + 4 * (6 * i + j), Ji[3 * i + j]);
            dq_v4_store(J + 4 * (6 * i + 3 + j), dq_v4_of(0.0));
            dq_v4_store(J + 4 * (6 * (i + 3) + j), -M[3 * i + j]);
            dq_v4_store(J + 4 * (6 * (i + 3) + 3 + j), Ji[3 * i + j]);
        }
    return 1;
}

DQ_CLONES int dq_jr_scaled_lanes(const double *xi, const double *s, double *J)
{
    v4 w[3], v[3], t2, sc = dq_v4_load(s);
    for (int k = 0; k < 3; k++) {
        w[k] = -dq_v4_load(xi + 4 * k);
        v[k] = -dq_v4_load(xi + 4 * (3 + k));
    }
    if (!series_v4(w, &t2)) return 0;
    v4 k[4];   /* C, c2, c3, B */
    series8_v4(C_SERIES, &t2, k);
    series8_v4(C2_SERIES, &t2, k + 1);
    series8_v4(C3_SERIES, &t2, k + 2);
    series8_v4(B_SERIES, &t2, k + 3);
    v4 Q[9], W[9], B = k[3], C = k[0];
    q_block_v4(w, v, &t2, k, Q);
    hat3_v4(w, W);
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            v4 ww = w[i] * w[j] - (i == j ? t2 : dq_v4_of(0.0));
            v4 a = sc * ((i == j ? 1.0 : 0.0) + B * W[3 * i + j] + C * ww);
            dq_v4_store(J + 4 * (6 * i + j), a);
            dq_v4_store(J + 4 * (6 * i + 3 + j), dq_v4_of(0.0));
            dq_v4_store(J + 4 * (6 * (i + 3) + j), sc * Q[3 * i + j]);
            dq_v4_store(J + 4 * (6 * (i + 3) + 3 + j), a);
        }
    return 1;
}

DQ_CLONES void dq_adjoint_lanes(const double *q, double *Ad)
{
    v4 w = dq_v4_load(q), x = dq_v4_load(q + 4), y = dq_v4_load(q + 8), z = dq_v4_load(q + 12);
    v4 q4 = dq_v4_load(q + 16), q5 = dq_v4_load(q + 20), q6 = dq_v4_load(q + 24);
    v4 q7 = dq_v4_load(q + 28);
    /* dq_to_matrix's */
    v4 t[3], T[12];
    t[0] = 2.0 * (-q4 * x + q5 * w - q6 * z + q7 * y);
    t[1] = 2.0 * (-q4 * y + q5 * z + q6 * w - q7 * x);
    t[2] = 2.0 * (-q4 * z - q5 * y + q6 * x + q7 * w);
    T[0] = 1.0 - 2.0 * (y * y + z * z); T[1] = 2.0 * (x * y - w * z); T[2] = 2.0 * (x * z + w * y);
    T[4] = 2.0 * (x * y + w * z); T[5] = 1.0 - 2.0 * (x * x + z * z); T[6] = 2.0 * (y * z - w * x);
    T[8] = 2.0 * (x * z - w * y); T[9] = 2.0 * (y * z + w * x); T[10] = 1.0 - 2.0 * (x * x + y * y);
    for (int a = 0; a < 3; a++)
        for (int b = 0; b < 3; b++) {
            v4 R = T[4 * a + b];
            v4 tR = (a == 0 ? -t[2] * T[4 + b] + t[1] * T[8 + b]
                     : a == 1 ? t[2] * T[b] - t[0] * T[8 + b]
                              : -t[1] * T[b] + t[0] * T[4 + b]);
            dq_v4_store(Ad + 4 * (6 * a + b), R);
            dq_v4_store(Ad + 4 * (6 * a + 3 + b), dq_v4_of(0.0));
            dq_v4_store(Ad + 4 * (6 * (a + 3) + b), tR);
            dq_v4_store(Ad + 4 * (6 * (a + 3) + 3 + b), R);
        }
}
#endif
