/*
 * dq.h — unit dual quaternions for rigid motions, in pure C99.
 *
 * Conventions (the whole project uses them):
 *   - A dual quaternion is 8 doubles [w, x, y, z, w', x', y', z']: real part r first, then the
 *     dual part d = 1/2 * t * r (t the translation as a pure quaternion).
 *   - Quaternions are scalar first. Metres, radians.
 *   - A pose T_a_b maps points from frame b to frame a; composition is the product.
 *   - log(q) is a 6-vector [real vector part, dual vector part] = half the se(3) twist (w, v),
 *     with the rotation taken the short way (angle in [0, pi]).
 *   - q and -q are the same pose.
 *
 * Functions that can fail return DQ_OK or a DQ_E* code; nothing here allocates or touches Python.
 */
#ifndef DQPOSE_DQ_H
#define DQPOSE_DQ_H

#include <math.h>
#include <stddef.h>

/* Result codes. The module turns each into a ValueError naming the argument. */
enum {
    DQ_OK = 0,
    DQ_E_NONFINITE = 1,   /* NaN or infinity in the input */
    DQ_E_ZERO = 2,        /* zero (or vanishing) quaternion */
    DQ_E_NOT_UNIT = 3,    /* real part norm off 1 by more than DQ_UNIT_TOL */
    DQ_E_DUAL = 4,        /* dual part not orthogonal to the real part */
    DQ_E_NOT_RIGID = 5,   /* matrix not orthonormal, det <= 0, or bottom row != [0 0 0 1] */
    DQ_E_WEIGHT_NEG = 6,  /* a negative weight */
    DQ_E_WEIGHT_SUM = 7,  /* weights sum to zero */
    DQ_E_OVERFLOW = 8,    /* the result is not finite (input too large) */
    DQ_E_METHOD = 9,      /* not a blending method (blend.h) */
    DQ_E_SET_SIZE = 10    /* a blending method given a set size it cannot take (ScLERP: 2) */
};

/* Inputs within this distance of unit norm are normalised; further off is an error. Wide enough
 * for rounded input (a quaternion written with four decimals, 0.7071 for cos 45 deg, is off by
 * up to ~1e-4), narrow enough that what is not a rotation (a scaled or mistyped vector) is
 * refused. The one tolerance of every input check: the real part's norm, the dual part's
 * orthogonality to it (relative to its size), a rotation matrix's max |R^T R - I| (then
 * projected to the nearest rotation). Python reads it as dqpose.dq.UNIT_TOL. */
#define DQ_UNIT_TOL 1e-3
/* |R^T R - I| up to this is a rotation to rounding: dq_from_matrix takes its quaternion in closed
 * form rather than by projection. */
#define DQ_ROTATION_EXACT 1e-14
/* Dual parts with |d|^2 beyond this (translations beyond ~2e150 m) overflow the products in
 * to_matrix, log and screw; validation and conversions reject them so every result is finite. */
#define DQ_DUAL_NORM2_MAX 1e300

/* Algebra (any dual quaternion). */
void dq_mul(const double *a, const double *b, double *out);
void dq_conj(const double *a, double *out);

/* Checks that q is finite and unit within DQ_UNIT_TOL (real part's norm; dual part orthogonal to
 * it within DQ_UNIT_TOL of max(|d|, 1)), then writes the exact unit version (real part
 * normalised, dual part made orthogonal to it). out may alias q. */
int dq_unit(const double *q, double *out);
/* Normalises any dual quaternion with a non-zero real part. */
int dq_normalize(const double *q, double *out);

/* exp: 6-vector -> unit dual quaternion; log: unit dual quaternion -> 6-vector. */
void dq_exp(const double *x, double *out);
void dq_log(const double *q, double *out);
/* Series form of log, valid for |vec(q_r)|^2 < DQ_LOG_SERIES_MAX with scalar part >= 0. */
#define DQ_LOG_SERIES_MAX 1e-2
void dq_pow(const double *q, double tau, double *out);
/* dq_exp, dq_mul and dq_log of four problems side by side (entry k of lane l at [4 k + l]),
 * each lane's bits the scalar function's; dq_exp_lanes and dq_log_lanes take their series
 * branch only and return 0, writing nothing, when a lane is beyond it. Where vecmath.h's
 * DQ_V4. */
int dq_exp_lanes(const double *x, double *out);
void dq_mul_lanes(const double *a, const double *b, double *out);
int dq_log_lanes(const double *q, double *out);

/* Conversions. Matrices are 4x4 row-major. dq_from_matrix takes a rotation block within
 * DQ_UNIT_TOL of orthonormal (dq_rotation_error) with det > 0 and uses the nearest rotation. */
int dq_from_matrix(const double *m, double *out);
double dq_rotation_error(const double *m);   /* max |R^T R - I| of the 3x3 block */
double dq_det3(const double *m);             /* det of the 3x3 block */
/* The unit quaternion (scalar part >= 0) of the rotation nearest to the 3x3 block in the
 * Frobenius norm, for any block (the SVD's answer with det +1). */
void dq_nearest_rotation(const double *m, double *quat);
void dq_to_matrix(const double *q, double *m);
int dq_from_pose(const double *quat, const double *t, double *out);
void dq_to_pose(const double *q, double *quat, double *t);
void dq_transform_point(const double *q, const double *p, double *out);

/* Screw parameters of a unit dual quaternion: rotation angle theta in [0, pi], translation d
 * along the axis, axis direction l and moment m (m = p x l for any point p on the axis).
 * A pure translation has theta = 0, l = t/|t|, d = |t|, m = 0; the identity has all zeros. */
void dq_screw(const double *q, double *theta, double *d, double *l, double *m);

/* Quaternion product c = a b (scalar first); c may alias neither a nor b. */
static inline void dq_qmul(const double *a, const double *b, double *c)
{
    c[0] = a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3];
    c[1] = a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2];
    c[2] = a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1];
    c[3] = a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0];
}

/* Sum of 8 values is finite (NaN/Inf check without libm calls). */
static inline int dq_finite8(const double *q)
{
    double s = 0.0;
    for (int i = 0; i < 8; i++) s += q[i] * 0.0;
    return s == 0.0;
}

static inline int dq_finite_n(const double *v, size_t n)
{
    double s = 0.0;
    for (size_t i = 0; i < n; i++) s += v[i] * 0.0;
    return s == 0.0;
}

/* Whether dq_unit passes q through as it is: unit to a few ulps (any computed pose), so that
 * normalising would move it by as little. Implies every check of dq_unit holds (a NaN or an
 * infinity fails a comparison). Written without branches, so a batch check vectorises. */
static inline int dq_unit_as_is(const double *q)
{
    double rr = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3];
    double dd = q[4] * q[4] + q[5] * q[5] + q[6] * q[6] + q[7] * q[7];
    double rd = q[0] * q[4] + q[1] * q[5] + q[2] * q[6] + q[3] * q[7];
    double scale2 = dd > 1.0 ? dd : 1.0;
    return (fabs(rr - 1.0) <= 1e-15) & (dd <= DQ_DUAL_NORM2_MAX) & (rd * rd <= 1e-30 * scale2);
}

#endif
