/*
 * fusion.h — exact maximum-likelihood fusion of n poses with full 6x6 covariances, in pure C99.
 *
 * Conventions (those of service/fusion/, GTSAM's Pose3):
 *   - A covariance is 6x6 row-major, rotation first [wx wy wz vx vy vz], of a right (body-frame)
 *     perturbation T Exp(xi) with the SE(3) exponential (Exp(xi) = dq_exp(xi / 2)).
 *   - The residual of measurement Z_i at the estimate X is r_i = Log(X^-1 Z_i); its Jacobian for
 *     X Exp(d) is -Jl^-1(r_i). The cost is sum_i r_i^T S_i^-1 r_i over the inliers.
 *
 * dq_fuse starts at the DIB mean (dq_dib) of the inliers, weighted by det(S_i^-1)^(1/6), and takes
 * Gauss-Newton steps X <- X Exp(d), halving a step that raises the cost, until a step is shorter
 * than tol (that step is not taken: X is the optimum to within tol, and the information the step
 * was solved with is the one at X). The covariance is the inverse of the information
 * sum_i Jl^-T S_i^-1 Jl^-1 at the optimum (GTSAM's marginal). Every measurement, inlier or not,
 * gets its residual, Mahalanobis distance and leave-one-out NIS at the optimum (see dq_fuse).
 * The constant-twist fit of a moving body is motion.h's.
 *
 * Nothing here allocates or touches Python; the caller validates the poses (unit) and passes
 * symmetric covariances.
 */
#ifndef DQPOSE_FUSION_H
#define DQPOSE_FUSION_H

#include <stddef.h>

/* How the estimate was reached; the values are dqpose.fusion.Status's. */
typedef enum {
    DQ_FUSE_CONVERGED = 0,      /* the last step was shorter than tol */
    DQ_FUSE_MAX_ITERATIONS = 1  /* max_iter steps taken, the last one still longer than tol */
} dq_fuse_status;

/* Result codes beyond dq.h's. */
enum {
    DQ_E_NOT_SPD = 11,     /* a covariance is not symmetric positive definite (*bad: which) */
    DQ_E_SINGULAR = 12,    /* the information at the optimum is not positive definite */
    DQ_E_NO_INLIERS = 13,  /* the inlier mask selects no measurement */
    DQ_E_ASYMMETRIC = 14,  /* a covariance is not symmetric within the tolerance */
    DQ_E_BORDERLINE = 15,  /* too close to the edge of positive definite to be sure */
    DQ_E_SCALE = 16        /* a variance outside [DQ_MIN_VARIANCE, DQ_MAX_VARIANCE] */
};

/* The variances (diagonal entries) a covariance may have: standard deviations from 1e-12 to
 * 1e12 (rad or m). Beyond them the information matrix cannot be used: its products with the
 * others' overflow, or leave the fit's normal equations singular (1e-300 I did both). */
#define DQ_MIN_VARIANCE 1e-24
#define DQ_MAX_VARIANCE 1e24

/*
 * Checks one covariance (36 values, row-major) by the rules of service/fusion/validation.py:
 * finite; symmetric, max |S - S^T| <= sym_tol * max |S| (the tolerance is the caller's, so the
 * rule has one source); every positive variance within [DQ_MIN_VARIANCE, DQ_MAX_VARIANCE] (DQ_E_SCALE);
 * positive definite, by Cholesky of its symmetric part, which it writes
 * to sym (0.5 (S + S^T), the same operations as NumPy's, so the same bits). Returns DQ_OK,
 * DQ_E_NONFINITE, DQ_E_ASYMMETRIC, DQ_E_NOT_SPD, or DQ_E_BORDERLINE where LAPACK's factorisation
 * could decide otherwise than ours (the caller then asks LAPACK, through NumPy).
 */
int dq_covariance_check(const double *S, double sym_tol, double *sym);

typedef struct {
    double tol;    /* stop when a Gauss-Newton step is shorter than this */
    int max_iter;  /* at most this many steps */
} dq_fuse_params;

typedef struct {
    double mean[8];         /* the estimate X (unit) */
    double covariance[36];  /* inverse information at X, symmetric */
    double chi2;            /* sum of the inliers' squared distances (the cost at X) */
    int status;             /* a dq_fuse_status */
    int iterations;         /* Gauss-Newton steps taken */
} dq_fused;

/* Per-measurement outputs (n each; residuals n x 6). nis and tested may be NULL to skip the
 * leave-one-out statistics. */
typedef struct {
    double *residuals;       /* r_i = Log(X^-1 Z_i) */
    double *distances;       /* sqrt(r_i^T S_i^-1 r_i) */
    double *nis;             /* leave-one-out NIS, 0 where untested */
    unsigned char *tested;   /* 0 for an inlier with no other inlier to check it against */
} dq_fuse_outputs;

/* Doubles of workspace dq_fuse needs for n measurements. */
size_t dq_fuse_workspace(size_t n);

/*
 * Fuses the unit poses z (n x 8) with covariances cov (n x 6 x 6, symmetric) over the
 * measurements inlier selects (NULL: all). work holds dq_fuse_workspace(n) doubles.
 *
 * The NIS of measurement j is nu^T (S_j + K)^-1 nu with K = A_j Hj^-1 A_j^T, A_j = Jl^-1(r_j),
 * Hj the information of the other inliers (the whole information for an outlier) and the
 * innovation nu = r_j + K S_j^-1 r_j (r_j for an outlier): measurement j against the fit of the
 * others, one Gauss-Newton step from the optimum.
 *
 * Returns DQ_OK; DQ_E_NOT_SPD with *bad the measurement; DQ_E_NO_INLIERS; DQ_E_SINGULAR; or
 * DQ_E_OVERFLOW when a result is not finite.
 */
int dq_fuse(const double *z, const double *cov, const unsigned char *inlier, size_t n,
            const dq_fuse_params *p, double *work, dq_fused *out, const dq_fuse_outputs *per,
            size_t *bad);

/*
 * The squared Mahalanobis distances of the robust mode's consensus (service/fusion/): between
 * candidate c = cand[a] and every measurement j, d2[a n + j] = r^T (S_c + S_j)^-1 r with
 * r = Log(Z_c^-1 Z_j) (first order: both errors in the body frame). O(m n) time, no memory of
 * its own. Returns DQ_OK, or DQ_E_NOT_SPD with *bad = j when S_c + S_j does not factor.
 */
int dq_pair_distances(const double *z, const double *cov, size_t n, const long long *cand,
                      size_t m, double *d2, size_t *bad);

/* Whether the inlier mask (NULL: all) selects measurement i. */
static inline int dq_selected(const unsigned char *inlier, size_t i) { return !inlier || inlier[i]; }

#endif
