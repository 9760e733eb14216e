/*
 * motion.h — fusion with time alignment, in pure C99: the constant-twist motion model
 * (service/fusion/__init__.py), its Gauss-Newton fit over pose, twist and latencies,
 * and the checks around it. Conventions, result codes and dq_fuse_params are fusion.h's.
 *
 * The prediction of measurement i is P_i = X Exp(dt_i V), dt_i = stamp_i - latency_i (stamps
 * relative to the fusion time), its residual r_i = Log(P_i^-1 Z_i). For X Exp(d), V + e and the
 * estimated latencies ell + l the prediction moves by Exp(eta) on the right,
 * eta = Ad(Exp(-dt V)) d + dt Jr(dt V) e - V l, and r_i by -Jl^-1(r_i) eta =: -G_i [d e l]. The
 * measurements are independent (block-diagonal covariances S_i); the state is the pose (6), the
 * twist (6, when estimated) and k latencies: dim = 6 [+ 6] + k, in that order.
 */
#ifndef DQPOSE_MOTION_H
#define DQPOSE_MOTION_H

#include <stddef.h>

#include "fusion.h"

typedef struct {
    const double *stamp;     /* n: a measurement's stamp minus the fusion time */
    const double *latency;   /* n: its configured latency (used where slot < 0) */
    const long long *slot;   /* n: its estimated latency's index, or -1 */
    size_t k;                /* estimated latencies */
    const double *prior;     /* k: their prior means */
    const double *prior_w;   /* k: their prior information (1 / sigma^2) */
    int twist;               /* the twist is estimated (else it is zero) */
    const double *twist_w;   /* 36: the twist's zero-mean prior information, or NULL (none) */
} dq_motion_model;

typedef struct {
    double mean[8];   /* the pose X at the fusion time */
    double twist[6];  /* V (zeros when not estimated) */
    double *ell;      /* k: the estimated latencies (caller's memory) */
    double *H;        /* dim x dim: the inliers' information at X with the priors' (caller's) */
    double chi2;      /* the inliers' cost and the priors' */
    int status;       /* a dq_fuse_status */
    int iterations;
} dq_motion_fitted;

/* Per-measurement outputs at the estimate, for every measurement; any may be NULL. */
typedef struct {
    double *dt;         /* n */
    double *residuals;  /* n x 6 */
    double *cost;       /* n: r_i^T S_i^-1 r_i */
    double *G;          /* n x 6 x dim */
    double *nis;        /* n: leave-one-out NIS where tested, else 0 (needs tested) */
} dq_motion_outputs;

/* The model's state dimension, and the doubles of workspace dq_motion_fit needs. */
size_t dq_motion_dim(const dq_motion_model *m);
size_t dq_motion_workspace(size_t n, const dq_motion_model *m);

/*
 * Gauss-Newton over pose, twist and latencies for the measurements inlier selects (NULL: all)
 * from X = start, V = 0, ell = the priors: the step solved from the whitened normal equations
 * with the priors' information (twist_w on the twist, prior_w on the latencies), halved while it
 * raises the cost by more than 1e-12 (relative), at most 30 times; a step shorter than tol is
 * not taken and ends the loop (the estimate is the point it was solved at, whose linearisation
 * is then reused), one halved below tol is taken and ends it. Then everything at the estimate: the information H (inliers and
 * priors), and per measurement its dt, residual, cost, G_i and, where tested[i], its
 * leave-one-out NIS: an inlier's nu^T (S + K)^-1 nu with K = G Hj^-1 G^T, Hj the information of
 * the priors and the other inliers (summed, not subtracted), nu = r + K S^-1 r; any other
 * measurement's r^T (S + G H^-1 G^T)^-1 r. The caller validates the poses (unit) and the
 * model (finite; twist_w symmetric positive definite).
 *
 * Returns DQ_OK; DQ_E_NOT_SPD with *bad the measurement; DQ_E_NO_INLIERS; DQ_E_SINGULAR (the
 * normal equations, or a tested measurement's Hj, are not positive definite); DQ_E_OVERFLOW.
 */
int dq_motion_fit(const double *z, const double *cov, const unsigned char *inlier, size_t n,
                  const dq_motion_model *m, const double *start, const unsigned char *tested,
                  const dq_fuse_params *p, double *work, dq_motion_fitted *out,
                  const dq_motion_outputs *per, size_t *bad);

/* The inlier taken nearest the fusion time, the estimated latencies at their priors (the
 * first of equals; n when inlier selects none): where the fit of a moving body starts. */
size_t dq_motion_nearest(const dq_motion_model *m, const unsigned char *inlier, size_t n);

/* det[i] = do the inliers other than measurement i determine the state? With no twist to find,
 * or a twist with a prior, any other inlier does; a twist without a prior needs inliers taken
 * (stamp minus configured latency) at two instants. The latencies always have their priors.
 * work: n entries. */
typedef struct {
    double t;
    size_t i;
} dq_taken;
void dq_motion_determined(const dq_motion_model *m, const unsigned char *inlier, size_t n,
                          dq_taken *work, unsigned char *det);

/* One constant-twist fit from its rows as given (what _dqcore.motion_fit runs, the GIL released,
 * and a tick will): poses (n x 8) made unit into zu (n x 8), covariances (n x 36) checked
 * finite, the start (NULL: dq_motion_nearest's inlier; else made unit), the measurements whose
 * NIS is tested (tested NULL: none; else copied from tested_in, or with find_tested those
 * dq_motion_determined finds and every outlier, taken its work), dq_motion_fit, then P = H^-1
 * (dim x dim, dq_motion_dim; work then spent). */
typedef struct {
    const double *poses, *covs;
    const unsigned char *inlier;
    const double *start;
    size_t n;
    const unsigned char *tested_in;
    int find_tested;
    unsigned char *tested;
    const dq_fuse_params *p;
    double *work, *zu, *P;
    dq_taken *taken;
} dq_motion_run_args;

/* DQ_OK, or the DQ_E* code that stopped it with *bad the measurement and *bad_name the argument
 * it concerns ("poses", "covariances", "start"; *bad_name is left as it was for a pose). f->ell
 * and f->H are the caller's memory, as dq_motion_fit's. */
int dq_motion_run(const dq_motion_run_args *c, const dq_motion_model *m, dq_motion_fitted *f,
                  const dq_motion_outputs *per, size_t *bad, const char **bad_name);

#endif
