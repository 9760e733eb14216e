/*
 * blend.h — blending of rigid motions (Kavan et al., "Dual Quaternions for Rigid Transformation
 * Blending"): ScLERP, DLB, DIB and the paper's baselines Lin, Dec and Log.
 *
 * Every function here takes unit dual quaternions (see dq_unit) and weights that are
 * non-negative and sum to 1 (see dq_weights); the callers (py_dq.c, wire.c) validate first.
 * Conventions are those of dq.h.
 */
#ifndef DQPOSE_BLEND_H
#define DQPOSE_BLEND_H

#include <stddef.h>

/* The blending methods, X(NAME, value). The values are those of dqpose.v1.Method, so the wire
 * decoder passes a request's method through unchanged. service/dq.py's METHODS table is the one
 * list of names; tests check this enum (tests/dq/test_hard_cases.py) and the proto enum
 * (tests/rpc/test_geometry.py) against it. */
#define DQ_METHODS(X) X(DIB, 1) X(DLB, 2) X(SCLERP, 3) X(LIN, 4) X(DEC, 5) X(LOG, 6)

#define DQ_METHOD_ENUM_(name, value) DQ_##name = value,
typedef enum { DQ_METHODS(DQ_METHOD_ENUM_) } dq_method;
#undef DQ_METHOD_ENUM_

typedef struct {
    int method;    /* a dq_method */
    double tol;    /* DIB, DEC: stop when the step is shorter */
    int max_iter;  /* DIB, DEC: at most this many steps */
} dq_blend_params;

/* 1 when method is a dq_method. */
int dq_method_known(int method);

/* Whether method can blend a set of n poses: DQ_OK, DQ_E_METHOD, or DQ_E_SET_SIZE (SCLERP
 * takes exactly two). */
int dq_blend_check(int method, size_t n);

/* The one dispatch: the set q (n unit poses) with weights w (from dq_weights) blended by
 * p->method into the unit pose out. SCLERP interpolates the pair at tau = w[1]. LIN's matrix
 * blend is projected to the nearest rigid motion (the nearest rotation in the Frobenius norm,
 * the weighted mean of the translations); dq_lin is the raw blend. *iters and *residual are
 * DIB's (0 for the other methods). Returns DQ_OK, a dq_blend_check code, or DQ_E_OVERFLOW when
 * the result is not finite. */
int dq_blend_set(const double *q, const double *w, size_t n, const dq_blend_params *p,
                 double *out, int *iters, double *residual);

/* ScLERP(tau; a, b) = a (a* b)^tau, b first put in a's hemisphere. The screw of a* b is
 * computed once per pair, so evaluating many tau costs one sincos and ~30 flops each. */
typedef struct {
    double p0[4];  /* a_r */
    double p1[4];  /* a_r (0, s)        s: screw axis */
    double p3[4];  /* a_d */
    double q[4];   /* a_d (0, s) + a_r (0, m')   m' = d_perp / phi */
    double p2[4];  /* a_r (0, d) for a pure translation */
    double phi;    /* half the rotation angle of a* b */
    double h;      /* half the translation along the axis */
    int pure;      /* phi == 0: a pure translation, the axis is undefined */
} dq_sclerp_pair;

void dq_sclerp_prepare(const double *a, const double *b, dq_sclerp_pair *p);
void dq_sclerp_eval(const dq_sclerp_pair *p, double tau, double *out);
void dq_sclerp(const double *a, const double *b, double tau, double *out);
/* dq_sclerp for n independent pairs (out[i] from a[i], b[i], tau[i]); vectorised. */
void dq_sclerp_pairs(const double *a, const double *b, const double *tau, size_t n, double *out);
/* dq_sclerp_pairs of poses as given (not yet checked by dq_unit), each block of them checked
 * while it is in cache: the poses by dq_unit's rules (only a block holding a pose that is not
 * unit to a few ulps is copied, normalised), tau and the output finite. Returns DQ_OK, or the
 * first failure's code (out then partly written; the caller names the element). */
int dq_sclerp_pairs_checked(const double *a, const double *b, const double *tau, size_t n,
                            double *out);

/* Checks weights (finite, >= 0, positive sum) and writes them normalised to sum 1; w NULL
 * means equal weights. On error *bad is the offending index (for a zero sum, n). */
int dq_weights(const double *w, size_t n, double *wn, size_t *bad);

/* DLB: the normalised weighted sum, every input first put in the hemisphere of the pose with
 * the largest weight. */
void dq_dlb(const double *q, const double *w, size_t n, double *out);

/* DIB: start at DLB, then b <- b exp(sum w_i log(b* q_i)) until |step| < tol or max_iter steps.
 * *iters is the number of steps taken, *residual the norm of the last step computed (at the
 * returned mean). */
void dq_dib(const double *q, const double *w, size_t n, double tol, int max_iter, double *out,
            int *iters, double *residual);

/* Baselines. Lin writes the weighted sum of the 4x4 row-major matrices (not rigid in general;
 * dq_blend_set projects it). Dec blends the
 * rotation (spherical weighted mean, slerp for two) and the translation (weighted mean)
 * separately. Log is exp of the weighted sum of principal logs (Alexa's log-matrix blend). */
void dq_lin(const double *q, const double *w, size_t n, double *m_out);
void dq_dec(const double *q, const double *w, size_t n, double tol, int max_iter, double *out);
void dq_logblend(const double *q, const double *w, size_t n, double *out);

#endif
