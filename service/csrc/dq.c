/*
 * dq.c — dual-quaternion algebra, exp/log, conversions and screw parameters.
 * Conventions are stated once in dq.h.
 */
#include "dq.h"

#include <math.h>

#include "vecmath.h"

/* The series of dq_exp (Taylor in y = phi^2; 7 terms leave < 1e-19 relative error at y = 1e-2)
 * and dq_log (asin(n)/n and (n - asin(n) sqrt(1-n^2))/n^3 in x = n^2; 8 terms < 1e-18 at
 * x = 1e-2), one text for the scalar functions and their lanes (the same operations). */
#define EXP_SERIES_MAX 1e-2
#define EXP_CS(y) (1.0 + (y) * (-1.0 / 2 + (y) * (1.0 / 24 + (y) * (-1.0 / 720 + (y) * (1.0 / 40320 \
              + (y) * (-1.0 / 3628800 + (y) * (1.0 / 479001600)))))))
#define EXP_SC(y) (1.0 + (y) * (-1.0 / 6 + (y) * (1.0 / 120 + (y) * (-1.0 / 5040 + (y) * (1.0 / 362880 \
              + (y) * (-1.0 / 39916800 + (y) * (1.0 / 6227020800.0)))))))
#define EXP_C(y) (-1.0 / 3 + (y) * (1.0 / 30 + (y) * (-1.0 / 840 + (y) * (1.0 / 45360 \
              + (y) * (-1.0 / 3991680 + (y) * (1.0 / 518918400 + (y) * (-1.0 / 93405312000.0)))))))
#define LOG_A(x) (1.0 + (x) * (1.0 / 6 + (x) * (3.0 / 40 + (x) * (5.0 / 112 + (x) * (35.0 / 1152 \
              + (x) * (63.0 / 2816 + (x) * (231.0 / 13312 + (x) * (143.0 / 10240))))))))
#define LOG_B(x) (1.0 / 3 + (x) * (2.0 / 15 + (x) * (8.0 / 105 + (x) * (16.0 / 315 + (x) * (128.0 / 3465 \
              + (x) * (256.0 / 9009 + (x) * (1024.0 / 45045 + (x) * (2048.0 / 109395))))))))

/* Half rotation angles at or below this count as zero in dq_screw (blend.c's ScLERP uses the
 * same value): the moment |t|/phi would overflow, and the rotation is far below rounding. */
#define DQ_SCREW_MIN_PHI 1e-150

static inline int dual_too_large(const double *q)
{
    double dd = q[4] * q[4] + q[5] * q[5] + q[6] * q[6] + q[7] * q[7];
    return !(dd <= DQ_DUAL_NORM2_MAX);
}

void dq_mul(const double *a, const double *b, double *out)
{
    double r[4], d1[4], d2[4];
    dq_qmul(a, b, r);
    dq_qmul(a, b + 4, d1);
    dq_qmul(a + 4, b, d2);
    out[0] = r[0]; out[1] = r[1]; out[2] = r[2]; out[3] = r[3];
    out[4] = d1[0] + d2[0]; out[5] = d1[1] + d2[1];
    out[6] = d1[2] + d2[2]; out[7] = d1[3] + d2[3];
}

void dq_conj(const double *a, double *out)
{
    out[0] = a[0]; out[1] = -a[1]; out[2] = -a[2]; out[3] = -a[3];
    out[4] = a[4]; out[5] = -a[5]; out[6] = -a[6]; out[7] = -a[7];
}

/* Divide by the dual-number norm: r/|r| and d/|r| - r <r,d>/|r|^3, which makes the result
 * exactly unit (|r| = 1 and <r, d> = 0). */
static inline void normalize_by(const double *q, double rr, double *out)
{
    double inv = 1.0 / sqrt(rr);
    double rd = q[0] * q[4] + q[1] * q[5] + q[2] * q[6] + q[3] * q[7];
    double k = rd * inv * inv;
    double r0 = q[0], r1 = q[1], r2 = q[2], r3 = q[3];
    out[4] = (q[4] - k * r0) * inv;
    out[5] = (q[5] - k * r1) * inv;
    out[6] = (q[6] - k * r2) * inv;
    out[7] = (q[7] - k * r3) * inv;
    out[0] = r0 * inv; out[1] = r1 * inv; out[2] = r2 * inv; out[3] = r3 * inv;
}

int dq_normalize(const double *q, double *out)
{
    if (!dq_finite8(q)) return DQ_E_NONFINITE;
    double rr = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3];
    /* Below this the direction of the real part is noise. */
    if (!(rr > 1e-200)) return DQ_E_ZERO;
    normalize_by(q, rr, out);
    if (!dq_finite8(out)) return DQ_E_OVERFLOW;
    return DQ_OK;
}

int dq_unit(const double *q, double *out)
{
    /* Unit to a few ulps already (any computed pose): normalising would move it by as little, so
     * the input is used as it is and a batch pays no sqrt or division per pose. */
    if (dq_unit_as_is(q)) {
        if (out != q) for (int i = 0; i < 8; i++) out[i] = q[i];
        return DQ_OK;
    }
    if (!dq_finite8(q)) return DQ_E_NONFINITE;
    double rr = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3];
    if (!(rr > 1e-200)) return DQ_E_ZERO;
    /* |r|^2 - 1 ~ 2 (|r| - 1): compare squared norms to avoid a sqrt on the fast path. */
    double e = rr - 1.0;
    if (fabs(e) > 2.0 * DQ_UNIT_TOL + DQ_UNIT_TOL * DQ_UNIT_TOL) {
        if (fabs(sqrt(rr) - 1.0) > DQ_UNIT_TOL) return DQ_E_NOT_UNIT;
    }
    double dd = q[4] * q[4] + q[5] * q[5] + q[6] * q[6] + q[7] * q[7];
    if (!(dd <= DQ_DUAL_NORM2_MAX)) return DQ_E_OVERFLOW;
    double rd = q[0] * q[4] + q[1] * q[5] + q[2] * q[6] + q[3] * q[7];
    /* Relative to the size of the dual part, so a 1 km translation has the same slack as 1 m;
     * squared, so no sqrt (rd^2 <= rr dd cannot overflow after the check above). */
    double scale2 = dd > 1.0 ? dd : 1.0;
    if (rd * rd > DQ_UNIT_TOL * DQ_UNIT_TOL * scale2) return DQ_E_DUAL;
    normalize_by(q, rr, out);
    if (!dq_finite8(out)) return DQ_E_OVERFLOW;
    return DQ_OK;
}

/* ---- exp / log -------------------------------------------------------------------------- */

/* exp(x), x = [r, d] (real and dual vector parts). With phi = |r|:
 *   real = (cos phi, sinc(phi) r)
 *   dual = (-sinc(phi) <r,d>, sinc(phi) d + c(phi) <r,d> r),  c = (phi cos phi - sin phi)/phi^3
 * i.e. the dual part is the derivative of the quaternion exp along d. */
void dq_exp(const double *x, double *out)
{
    const double *r = x, *d = x + 3;
    double y = r[0] * r[0] + r[1] * r[1] + r[2] * r[2];
    double rd = r[0] * d[0] + r[1] * d[1] + r[2] * d[2];
    double cs, sc, c;
    if (y < EXP_SERIES_MAX) {
        cs = EXP_CS(y);
        sc = EXP_SC(y);
        c = EXP_C(y);
    } else {
        double phi = sqrt(y);
        double s = sin(phi);
        cs = cos(phi);
        sc = s / phi;
        c = (phi * cs - s) / (phi * y);
    }
    out[0] = cs;
    out[1] = sc * r[0]; out[2] = sc * r[1]; out[3] = sc * r[2];
    double k = c * rd;
    out[4] = -sc * rd;
    out[5] = sc * d[0] + k * r[0];
    out[6] = sc * d[1] + k * r[1];
    out[7] = sc * d[2] + k * r[2];
}

/* log(q) for unit q. With the real part (w, v), n = |v| = sin(phi), phi = theta/2, w >= 0:
 *   real = a v,                     a = phi / sin(phi)
 *   dual = a v_d + b (w <v,v_d> - w_d n^2) v,   b = (sin(phi) - phi cos(phi)) / sin(phi)^3
 * Both a and b are smooth in n^2, so near theta = 0 the series in n^2 avoids atan2 and the
 * cancellation in b; near theta = pi (w -> 0) the closed form is well conditioned. */
void dq_log(const double *q, double *out)
{
    double w = q[0], v0 = q[1], v1 = q[2], v2 = q[3];
    double wd = q[4], u0 = q[5], u1 = q[6], u2 = q[7];
    if (w < 0.0) { /* the same pose, the short way round */
        w = -w; v0 = -v0; v1 = -v1; v2 = -v2;
        wd = -wd; u0 = -u0; u1 = -u1; u2 = -u2;
    }
    double x = v0 * v0 + v1 * v1 + v2 * v2;
    double a, b;
    if (x < DQ_LOG_SERIES_MAX) {
        a = LOG_A(x);
        b = LOG_B(x);
    } else {
        double n = sqrt(x);
        double phi = atan2(n, w);
        a = phi / n;
        b = (1.0 - a * w) / x;
    }
    double vu = v0 * u0 + v1 * u1 + v2 * u2;
    double k = b * (w * vu - wd * x);
    out[0] = a * v0; out[1] = a * v1; out[2] = a * v2;
    out[3] = a * u0 + k * v0;
    out[4] = a * u1 + k * v1;
    out[5] = a * u2 + k * v2;
}

void dq_pow(const double *q, double tau, double *out)
{
    double l[6];
    dq_log(q, l);
    for (int i = 0; i < 6; i++) l[i] *= tau;
    dq_exp(l, out);
}

/* ---- conversions ------------------------------------------------------------------------ */

void dq_to_matrix(const double *q, double *m)
{
    double w = q[0], x = q[1], y = q[2], z = q[3];
    double t[3];
    /* t = 2 vec(d r*) */
    t[0] = 2.0 * (-q[4] * x + q[5] * w - q[6] * z + q[7] * y);
    t[1] = 2.0 * (-q[4] * y + q[5] * z + q[6] * w - q[7] * x);
    t[2] = 2.0 * (-q[4] * z - q[5] * y + q[6] * x + q[7] * w);
    m[0] = 1.0 - 2.0 * (y * y + z * z); m[1] = 2.0 * (x * y - w * z);       m[2] = 2.0 * (x * z + w * y);       m[3] = t[0];
    m[4] = 2.0 * (x * y + w * z);       m[5] = 1.0 - 2.0 * (x * x + z * z); m[6] = 2.0 * (y * z - w * x);       m[7] = t[1];
    m[8] = 2.0 * (x * z - w * y);       m[9] = 2.0 * (y * z + w * x);       m[10] = 1.0 - 2.0 * (x * x + y * y); m[11] = t[2];
    m[12] = 0.0; m[13] = 0.0; m[14] = 0.0; m[15] = 1.0;
}

/* Rotation matrix -> quaternion by the largest-diagonal branch (Shepperd), which keeps the
 * divisor >= 1/2 and so is accurate near every angle including pi. */
static void quat_from_rot(const double *m, int stride, double *q)
{
#define M(i, j) m[(i) * stride + (j)]
    double tr = M(0, 0) + M(1, 1) + M(2, 2);
    if (tr >= M(0, 0) && tr >= M(1, 1) && tr >= M(2, 2)) {
        double s = 2.0 * sqrt(1.0 + tr);
        q[0] = 0.25 * s;
        q[1] = (M(2, 1) - M(1, 2)) / s;
        q[2] = (M(0, 2) - M(2, 0)) / s;
        q[3] = (M(1, 0) - M(0, 1)) / s;
    } else if (M(0, 0) >= M(1, 1) && M(0, 0) >= M(2, 2)) {
        double s = 2.0 * sqrt(1.0 + M(0, 0) - M(1, 1) - M(2, 2));
        q[0] = (M(2, 1) - M(1, 2)) / s;
        q[1] = 0.25 * s;
        q[2] = (M(0, 1) + M(1, 0)) / s;
        q[3] = (M(0, 2) + M(2, 0)) / s;
    } else if (M(1, 1) >= M(2, 2)) {
        double s = 2.0 * sqrt(1.0 + M(1, 1) - M(0, 0) - M(2, 2));
        q[0] = (M(0, 2) - M(2, 0)) / s;
        q[1] = (M(0, 1) + M(1, 0)) / s;
        q[2] = 0.25 * s;
        q[3] = (M(1, 2) + M(2, 1)) / s;
    } else {
        double s = 2.0 * sqrt(1.0 + M(2, 2) - M(0, 0) - M(1, 1));
        q[0] = (M(1, 0) - M(0, 1)) / s;
        q[1] = (M(0, 2) + M(2, 0)) / s;
        q[2] = (M(1, 2) + M(2, 1)) / s;
        q[3] = 0.25 * s;
    }
#undef M
    /* A canonical sign keeps conversions deterministic. */
    if (q[0] < 0.0) { q[0] = -q[0]; q[1] = -q[1]; q[2] = -q[2]; q[3] = -q[3]; }
}

static void dual_from_rt(const double *r, const double *t, double *out)
{
    /* d = 1/2 (0, t) r */
    out[0] = r[0]; out[1] = r[1]; out[2] = r[2]; out[3] = r[3];
    out[4] = 0.5 * (-t[0] * r[1] - t[1] * r[2] - t[2] * r[3]);
    out[5] = 0.5 * (t[0] * r[0] + t[1] * r[3] - t[2] * r[2]);
    out[6] = 0.5 * (-t[0] * r[3] + t[1] * r[0] + t[2] * r[1]);
    out[7] = 0.5 * (t[0] * r[2] - t[1] * r[1] + t[2] * r[0]);
}

/* The unit quaternion of the rotation nearest to the 3x3 block of the 4x4 row-major m in the
 * Frobenius norm (special orthogonal Procrustes, what the SVD with det correction gives).
 * |R - M|^2 = 3 + |M|^2 - 2 trace(R^T M), and trace(R(q)^T M) = q^T K q for the symmetric 4x4 K
 * of Bar-Itzhack ("New method for extracting the quaternion from a rotation matrix", 2000;
 * Horn's matrix), so q is the eigenvector of K's largest eigenvalue. A 4x4 symmetric eigenproblem
 * is what cyclic Jacobi does best: a few sweeps, accurate to rounding relative to |K|, no
 * iteration count to tune and no library. Scalar part made >= 0, as quat_from_rot does. */
void dq_nearest_rotation(const double *m, double *quat)
{
#define M(i, j) m[4 * (i) + (j)]
    double a[4][4] = {
        {M(0, 0) + M(1, 1) + M(2, 2), M(2, 1) - M(1, 2), M(0, 2) - M(2, 0), M(1, 0) - M(0, 1)},
        {M(2, 1) - M(1, 2), M(0, 0) - M(1, 1) - M(2, 2), M(0, 1) + M(1, 0), M(0, 2) + M(2, 0)},
        {M(0, 2) - M(2, 0), M(0, 1) + M(1, 0), M(1, 1) - M(0, 0) - M(2, 2), M(1, 2) + M(2, 1)},
        {M(1, 0) - M(0, 1), M(0, 2) + M(2, 0), M(1, 2) + M(2, 1), M(2, 2) - M(0, 0) - M(1, 1)},
    };
#undef M
    double v[4][4] = {{1, 0, 0, 0}, {0, 1, 0, 0}, {0, 0, 1, 0}, {0, 0, 0, 1}};
    double norm = 0.0;
    for (int i = 0; i < 4; i++)
        for (int j = 0; j < 4; j++) norm += a[i][j] * a[i][j];
    /* Off-diagonal entries below this move no eigenvector component above rounding. The rotations
     * keep |K| and converge quadratically (three to five sweeps); the cap is a guard. */
    double small = 1e-18 * sqrt(norm);
    for (int sweep = 0; sweep < 32; sweep++) {
        int rotated = 0;
        for (int p = 0; p < 3; p++)
            for (int q = p + 1; q < 4; q++) {
                double apq = a[p][q];
                if (!(fabs(apq) > small)) continue;
                rotated = 1;
                /* The rotation that zeroes a[p][q] (the smaller angle; Rutishauser's update). */
                double theta = (a[q][q] - a[p][p]) / (2.0 * apq);
                double t = fabs(theta) > 1e150 ? 0.5 / theta
                                               : copysign(1.0, theta) /
                                                     (fabs(theta) + sqrt(theta * theta + 1.0));
                double c = 1.0 / sqrt(t * t + 1.0), s = t * c, tau = s / (1.0 + c);
                a[p][p] -= t * apq;
                a[q][q] += t * apq;
                a[p][q] = a[q][p] = 0.0;
                for (int r = 0; r < 4; r++) {
                    if (r != p && r != q) {
                        double arp = a[r][p], arq = a[r][q];
                        a[r][p] = a[p][r] = arp - s * (arq + tau * arp);
                        a[r][q] = a[q][r] = arq + s * (arp - tau * arq);
                    }
                    double vrp = v[r][p], vrq = v[r][q];
                    v[r][p] = vrp - s * (vrq + tau * vrp);
                    v[r][q] = vrq + s * (vrp - tau * vrq);
                }
            }
        if (!rotated) break;
    }
    int k = 0;
    for (int i = 1; i < 4; i++)
        if (a[i][i] > a[k][k]) k = i;
    double sg = v[0][k] < 0.0 ? -1.0 : 1.0;
    for (int i = 0; i < 4; i++) quat[i] = sg * v[i][k];
}

double dq_rotation_error(const double *m)
{
    double worst = 0.0;
    for (int i = 0; i < 3; i++)
        for (int j = i; j < 3; j++) {
            double s = m[i] * m[j] + m[4 + i] * m[4 + j] + m[8 + i] * m[8 + j];
            double e = fabs(s - (i == j ? 1.0 : 0.0));
            if (e > worst) worst = e;
        }
    return worst;
}

double dq_det3(const double *m)
{
    return m[0] * (m[5] * m[10] - m[6] * m[9]) - m[1] * (m[4] * m[10] - m[6] * m[8]) +
           m[2] * (m[4] * m[9] - m[5] * m[8]);
}

int dq_from_matrix(const double *m, double *out)
{
    if (!dq_finite_n(m, 16)) return DQ_E_NONFINITE;
    if (fabs(m[12]) > DQ_UNIT_TOL || fabs(m[13]) > DQ_UNIT_TOL || fabs(m[14]) > DQ_UNIT_TOL ||
        fabs(m[15] - 1.0) > DQ_UNIT_TOL)
        return DQ_E_NOT_RIGID;
    /* Orthonormal within the tolerance (so |det| is 1 within ~1.5 of it): the sign of det tells a
     * rotation from a reflection. */
    double worst = dq_rotation_error(m);
    if (worst > DQ_UNIT_TOL || !(dq_det3(m) > 0.0)) return DQ_E_NOT_RIGID;
    double q[4], t[3] = {m[3], m[7], m[11]};
    if (worst <= DQ_ROTATION_EXACT) {
        /* A rotation to rounding (any computed one): Shepperd's closed form gives the nearest
         * rotation's quaternion to rounding at a tenth of the eigenproblem's cost. */
        quat_from_rot(m, 4, q);
        double inv = 1.0 / sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
        for (int i = 0; i < 4; i++) q[i] *= inv;
    } else {
        dq_nearest_rotation(m, q);
    }
    dual_from_rt(q, t, out);
    if (!dq_finite8(out) || dual_too_large(out)) return DQ_E_OVERFLOW;
    return DQ_OK;
}

int dq_from_pose(const double *quat, const double *t, double *out)
{
    if (!dq_finite_n(quat, 4) || !dq_finite_n(t, 3)) return DQ_E_NONFINITE;
    double rr = quat[0] * quat[0] + quat[1] * quat[1] + quat[2] * quat[2] + quat[3] * quat[3];
    if (!(rr > 1e-200)) return DQ_E_ZERO;
    double n = sqrt(rr);
    if (fabs(n - 1.0) > DQ_UNIT_TOL) return DQ_E_NOT_UNIT;
    double q[4] = {quat[0] / n, quat[1] / n, quat[2] / n, quat[3] / n};
    dual_from_rt(q, t, out);
    if (!dq_finite8(out) || dual_too_large(out)) return DQ_E_OVERFLOW;
    return DQ_OK;
}

void dq_to_pose(const double *q, double *quat, double *t)
{
    double w = q[0], x = q[1], y = q[2], z = q[3];
    quat[0] = w; quat[1] = x; quat[2] = y; quat[3] = z;
    t[0] = 2.0 * (-q[4] * x + q[5] * w - q[6] * z + q[7] * y);
    t[1] = 2.0 * (-q[4] * y + q[5] * z + q[6] * w - q[7] * x);
    t[2] = 2.0 * (-q[4] * z - q[5] * y + q[6] * x + q[7] * w);
}

void dq_transform_point(const double *q, const double *p, double *out)
{
    double w = q[0], x = q[1], y = q[2], z = q[3];
    double t[3];
    t[0] = 2.0 * (-q[4] * x + q[5] * w - q[6] * z + q[7] * y);
    t[1] = 2.0 * (-q[4] * y + q[5] * z + q[6] * w - q[7] * x);
    t[2] = 2.0 * (-q[4] * z - q[5] * y + q[6] * x + q[7] * w);
    /* p' = p + 2w (v x p) + 2 v x (v x p) */
    double cx = y * p[2] - z * p[1], cy = z * p[0] - x * p[2], cz = x * p[1] - y * p[0];
    double ccx = y * cz - z * cy, ccy = z * cx - x * cz, ccz = x * cy - y * cx;
    out[0] = p[0] + 2.0 * (w * cx + ccx) + t[0];
    out[1] = p[1] + 2.0 * (w * cy + ccy) + t[1];
    out[2] = p[2] + 2.0 * (w * cz + ccz) + t[2];
}

void dq_screw(const double *q, double *theta, double *d, double *l, double *m)
{
    /* log = [ (theta/2) l, (d/2) l + (theta/2) m ] */
    double x[6];
    dq_log(q, x);
    double phi = sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2]);
    /* Below DQ_SCREW_MIN_PHI the moment (~|t|/phi) could overflow; such a rotation is below
     * rounding of any pose, so it is treated as the pure translation it is numerically. */
    if (phi > DQ_SCREW_MIN_PHI) {
        double s0 = x[0] / phi, s1 = x[1] / phi, s2 = x[2] / phi;
        double hd = s0 * x[3] + s1 * x[4] + s2 * x[5];
        *theta = 2.0 * phi;
        *d = 2.0 * hd;
        l[0] = s0; l[1] = s1; l[2] = s2;
        m[0] = (x[3] - hd * s0) / phi;
        m[1] = (x[4] - hd * s1) / phi;
        m[2] = (x[5] - hd * s2) / phi;
    } else {
        double tn = 2.0 * sqrt(x[3] * x[3] + x[4] * x[4] + x[5] * x[5]);
        *theta = 0.0;
        *d = tn;
        m[0] = m[1] = m[2] = 0.0;
        if (tn > 0.0) {
            l[0] = 2.0 * x[3] / tn; l[1] = 2.0 * x[4] / tn; l[2] = 2.0 * x[5] / tn;
        } else {
            l[0] = l[1] = l[2] = 0.0;
        }
    }
}

#if DQ_V4
/* ---- four at a time (motion.c's residuals): entry k of lane l at [4 k + l], each lane the
 * operations of the scalar function on its own input (so the same bits). The series branch only:
 * 0, with nothing written, when a lane is beyond it (then the scalar function serves). */
#define LD(p, k) dq_v4_load((p) + 4 * (k))
#define ST(p, k, v) dq_v4_store((p) + 4 * (k), (v))

DQ_CLONES int dq_exp_lanes(const double *x, double *out)
{
    dq_v4 r0 = LD(x, 0), r1 = LD(x, 1), r2 = LD(x, 2), d0 = LD(x, 3), d1 = LD(x, 4), d2 = LD(x, 5);
    dq_v4 y = r0 * r0 + r1 * r1 + r2 * r2;
    for (int l = 0; l < 4; l++)
        if (!(y[l] < EXP_SERIES_MAX)) return 0;
    dq_v4 rd = r0 * d0 + r1 * d1 + r2 * d2;
    dq_v4 cs = EXP_CS(y), sc = EXP_SC(y), c = EXP_C(y), k = c * rd;
    ST(out, 0, cs);
    ST(out, 1, sc * r0); ST(out, 2, sc * r1); ST(out, 3, sc * r2);
    ST(out, 4, -sc * rd);
    ST(out, 5, sc * d0 + k * r0); ST(out, 6, sc * d1 + k * r1); ST(out, 7, sc * d2 + k * r2);
    return 1;
}

/* dq_qmul's */
#define QMUL_V4(a, b, c) do { \
    c[0] = a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3]; \
    c[1] = a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2]; \
    c[2] = a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1]; \
    c[3] = a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0]; } while (0)

DQ_CLONES void dq_mul_lanes(const double *a, const double *b, double *out)
{
    dq_v4 av[8], bv[8], r[4], d1[4], d2[4];
    for (int k = 0; k < 8; k++) {
        av[k] = LD(a, k);
        bv[k] = LD(b, k);
    }
    QMUL_V4(av, bv, r);
    QMUL_V4(av, (bv + 4), d1);
    QMUL_V4((av + 4), bv, d2);
    for (int k = 0; k < 4; k++) {
        ST(out, k, r[k]);
        ST(out, 4 + k, d1[k] + d2[k]);
    }
}

DQ_CLONES int dq_log_lanes(const double *q, double *out)
{
    double f[32];
    for (int k = 0; k < 32; k++) f[k] = q[k];
    for (int l = 0; l < 4; l++)
        if (f[l] < 0.0) /* the same pose, the short way round */
            for (int k = 0; k < 8; k++) f[4 * k + l] = -f[4 * k + l];
    dq_v4 w = LD(f, 0), v0 = LD(f, 1), v1 = LD(f, 2), v2 = LD(f, 3);
    dq_v4 wd = LD(f, 4), u0 = LD(f, 5), u1 = LD(f, 6), u2 = LD(f, 7);
    dq_v4 x = v0 * v0 + v1 * v1 + v2 * v2;
    for (int l = 0; l < 4; l++)
        if (!(x[l] < DQ_LOG_SERIES_MAX)) return 0;
    dq_v4 a = LOG_A(x), b = LOG_B(x);
    dq_v4 vu = v0 * u0 + v1 * u1 + v2 * u2;
    dq_v4 k = b * (w * vu - wd * x);
    ST(out, 0, a * v0); ST(out, 1, a * v1); ST(out, 2, a * v2);
    ST(out, 3, a * u0 + k * v0);
    ST(out, 4, a * u1 + k * v1);
    ST(out, 5, a * u2 + k * v2);
    return 1;
}
#undef QMUL_V4
#undef LD
#undef ST
#endif
