/*
 * joint_ctx.h — what joint.c and joint_nis.c share inside the joint fit (not an interface: the
 * fit's is joint.h): the layout of a measurement's block of the workspace, the fit's context,
 * and the helpers both use.
 */
#ifndef DQPOSE_JOINT_CTX_H
#define DQPOSE_JOINT_CTX_H

#include <stddef.h>

#include "joint.h"

/* A measurement's compact columns: its part's pose (6) and twist (6), its latency (1), its
 * extrinsic's error (6); absent ones map to -1. */
#define JC 19

/* A measurement's block: its covariance factor L and DI, A = Ad(W^-1 E_s), its whitened compact
 * Jacobian L^-1 G, then r, e = L^-1 r, sin^2 and cos of half r's angle, Exp(dt V) and dt at the
 * point last evaluated (every trial step is taken once its halving ends, so one slot is
 * enough). */
enum { J_L = 0, J_DI = 36, J_A = 42, J_G = 78, J_R = 192, J_E = 198, J_SC = 204, J_EXP = 206,
       J_DT = 214, J_GRP = 215, J_PER = 216 };
/* The measurements of a part whose latency and extrinsic slots are the same touch the same
 * state columns: their information is summed compact (JC x JC, and the gradient's JC) per such
 * group, with fixed bounds the compiler vectorises, and scattered into the state's once. A
 * group's accumulator, then one of its measurements, its part's offset and twist. */
enum { G_G = JC * JC, G_REP = JC * JC + JC, G_OFF, G_TWIST, G_PER };
/* An extrinsic's prior residual Log(E^-1 Ehat) and [s2, ch] of its rotation. */
enum { E_R = 0, E_SC = 6, E_PER = 8 };

typedef struct {
    const dq_joint_model *m;
    const double *z;
    const unsigned char *inlier;
    size_t N;
    int dim, lat, ext;   /* the state's size, where its latencies and extrinsics start */
    double *blocks;      /* N x J_PER */
    double *groups;      /* ngroups x G_PER */
    size_t ngroups;
    double *shift;       /* m x 8: Ehat E^-1 at the point last evaluated */
    double *eres;        /* m x E_PER */
} joint_ctx;

/* The state columns of measurement i's compact columns, for its part's offset and twist. */
void joint_map(const joint_ctx *c, size_t i, int off, int twist, int *map);
/* The columns of map that are in the state: their compact indices and state columns,
 * ascending in both; returns their count. */
int joint_present(const int *map, int *cols, int *at);
/* H += the priors' information (upper triangle at least), g += their part of the descent
 * direction. */
void joint_prior_terms(const joint_ctx *c, const double *V, const double *L, double *H,
                       double *g);
/* Each tested measurement's leave-one-out NIS (joint_nis.c). */
int joint_leave_one_out(const joint_ctx *c, const double *V, const double *L, const double *P,
                        const double *Pg, double *scratch, double *pre, dq_taken *taken,
                        const dq_joint_outputs *per);

#endif
