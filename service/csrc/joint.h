/*
 * joint.h — the joint fit of uncertain extrinsics (service/fusion/extrinsics.py), in pure C99:
 * one or several bodies ("parts") over time, each with the constant-twist model of motion.h,
 * fitted together with one extrinsic error per uncertain source and the latencies the parts
 * share. Conventions, result codes and dq_fuse_params are fusion.h's.
 *
 * The state is every part's pose (6) and twist (6, when estimated) in order, then the k
 * latencies, then 6 per uncertain extrinsic: dim = sum (6 [+ 6]) + k + 6 m. Measurement i
 * (a world-frame pose W_i, of part p, its source's extrinsic E_s with error slot s or none) has
 * the residual r_i = Log(P_i^-1 Ehat_s E_s^-1 W_i), P_i = X_p Exp(dt_i V_p); extrinsic s has
 * the prior residual p_s = Log(E_s^-1 Ehat_s) with information I_s. For X_p Exp(d), V_p + e,
 * ell + l and Ehat_s Exp(D) the residual moves by -G_i [d e l D] with
 * G_i = [Jl^-1(r_i) B_i, -Jr^-1(r_i) A_i], B_i motion.h's and A_i = Ad(W_i^-1 E_s), and p_s by
 * Jr^-1(p_s) D. The cost is sum over the inliers r_i^T S_i^-1 r_i plus the priors' (latencies,
 * twists, extrinsics).
 */
#ifndef DQPOSE_JOINT_H
#define DQPOSE_JOINT_H

#include <stddef.h>

#include "fusion.h"
#include "motion.h"

typedef struct {
    size_t n;               /* its measurements, the next n of the fit's arrays */
    int twist;              /* its twist is estimated */
    const double *twist_w;  /* 36: the twist's zero-mean prior information, or NULL (none) */
} dq_joint_part;

typedef struct {
    size_t parts;
    const dq_joint_part *part;
    const double *stamp;        /* N: a measurement's stamp minus its part's fusion time */
    const double *latency;      /* N: its configured latency (used where lat_slot < 0) */
    const long long *lat_slot;  /* N: its latency's index among the k, or -1 */
    const long long *ext_slot;  /* N: its extrinsic's index among the m, or -1 (exact) */
    size_t k;                   /* latencies estimated */
    const double *prior;        /* k: their prior means */
    const double *prior_w;      /* k: their prior information (1 / sigma^2) */
    size_t m;                   /* uncertain extrinsics */
    const double *E;            /* m x 8: as configured (unit) */
    const double *E_info;       /* m x 36: their priors' information (symmetric) */
} dq_joint_model;

/* The state: in, where the fit starts (Ehat starts at E); out, the estimate. */
typedef struct {
    double *X;       /* parts x 8 */
    double *V;       /* parts x 6 */
    double *L;       /* k */
    double *Ehat;    /* m x 8: out; in too with ehat_given (else the fit starts at E) */
    double *H;       /* dim x dim: the information at the estimate, priors included */
    double *P;       /* dim x dim: H^-1, symmetric */
    double *g;       /* dim: the gradient at the estimate (the step's right-hand side) */
    double chi2;     /* the inliers' cost and the priors' */
    int status;      /* a dq_fuse_status */
    int iterations;
    int ehat_given;  /* Ehat is where the fit starts (a warm start), not E */
} dq_joint_state;

/* Per-measurement outputs at the estimate (N each); any may be NULL. */
typedef struct {
    double *dt;            /* N */
    double *residuals;     /* N x 6 */
    double *cost;          /* N: r_i^T S_i^-1 r_i */
    double *G;             /* N x 6 x dim */
    double *nis;           /* N: leave-one-out NIS where tested, else 0 (needs tested) */
    unsigned char *tested; /* N: an outlier, or an inlier whose part stays determined without it */
} dq_joint_outputs;

size_t dq_joint_dim(const dq_joint_model *m);
/* The doubles of workspace dq_joint_fit needs for N measurements, with the leave-one-out NIS
 * (nis: N dim^2 more) or without. */
size_t dq_joint_workspace(size_t N, const dq_joint_model *m, int nis);

/*
 * Gauss-Newton over the joint state for the measurements inlier selects (NULL: all) from the
 * state given (Ehat = E): gn.h's loop and step rule, the step solved from the normal equations
 * (Cholesky). Then everything at the
 * estimate: H, P = H^-1, g, and per measurement its dt, residual, cost, G_i and, with nis and
 * tested, its leave-one-out NIS (the priors stay in): an inlier's u^T (I - K)^-1 u,
 * u = L^-1 r - (L^-1 G) P g, K = (L^-1 G) P (L^-1 G)^T (S = L L^T; the downdate of the joint
 * fit by measurement i, the gradient at the answer kept), as u^T (I + (L^-1 G) Hj^-1
 * (L^-1 G)^T) u with Hj the information of the priors and the other inliers summed (not H less
 * its own, which a measurement far surer than the rest cancels to rounding), tested where
 * dq_motion_determined says its part stays determined without it (the workspace then needs
 * dq_joint_workspace's nis); any other measurement's r^T (S + G P G^T)^-1 r.
 * The caller validates the poses (unit), the starts and the model (finite; informations
 * symmetric positive definite). taken: N entries (dq_motion_determined's).
 *
 * Returns DQ_OK; DQ_E_NOT_SPD with *bad the measurement; DQ_E_NO_INLIERS; DQ_E_SINGULAR (the
 * normal equations); DQ_E_OVERFLOW.
 */
int dq_joint_fit(const double *z, const double *cov, const unsigned char *inlier, size_t N,
                 const dq_joint_model *m, const dq_fuse_params *p, double *work,
                 dq_taken *taken, dq_joint_state *st, const dq_joint_outputs *per, size_t *bad);

/* H (dim x dim, mirrored) and g of the fit's linearisation at the state st (X, V, L, Ehat) for
 * the measurements inlier selects (none: the priors' alone), the priors included: what
 * dq_joint_fit's normal equations are at that point (a warm start's first step made from the
 * measurements that changed, service/csrc/lookup.c). work: dq_joint_workspace(N, m, 0).
 * DQ_OK, or DQ_E_NOT_SPD with *bad the measurement. */
int dq_joint_linearized(const double *z, const double *cov, const unsigned char *inlier,
                        size_t N, const dq_joint_model *m, double *work,
                        const dq_joint_state *st, double *H, double *g, size_t *bad);

#endif
