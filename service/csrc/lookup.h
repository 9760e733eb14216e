/*
 * lookup.h — a World's Lookup in one call, in pure C99 (service/lookup.py): T_target_source at a
 * time from each body's rows of a store, each body fitted over time with the constant-twist
 * model (joint.h's fit, one part), or both together (two parts) when a source whose extrinsic is
 * uncertain or whose latency is estimated has rows in both bodies' windows (then the errors
 * they share are one state, and the relative pose's covariance has their cross-covariance);
 * then T_a^-1 T_b and its covariance J P J^T, J = [-Ad(T_ab^-1), I] (right perturbations).
 *
 * A fit starts where the caller says: a body's earlier estimate (pose and twist at its time,
 * carried to this time on the twist), a source's earlier latency and extrinsic estimate (warm
 * starts, which change the answer only within the fit's tol); or, given the record of the same
 * fit's last run (its state, rows and normal equations at its estimate), that state moved by
 * one Newton step of those normal equations less the rows that left plus those that came, then
 * carried to this time on the twist; else where the fits of
 * alignment.py start (the row taken nearest the time, at rest; latencies at their priors,
 * extrinsics as configured). Not here (DQ_LOOKUP_ELSEWHERE, the caller's other path): rows of
 * one instant, a time farther than max_extrapolation outside a body's rows, a fit that did not
 * converge from either start.
 */
#ifndef DQPOSE_LOOKUP_H
#define DQPOSE_LOOKUP_H

#include <stddef.h>

#include "fusion.h"

/* The answer belongs to another path (see above); no memory for the fit. */
#define DQ_LOOKUP_ELSEWHERE 40
#define DQ_LOOKUP_NOMEM 41

/* A store's columns (rows in the world frame, as service/fusion/store.py keeps them) and its
 * sources' table, by source code. */
typedef struct {
    size_t rows;
    const long long *ids;           /* rows: each row's measurement id */
    const double *poses;            /* rows x 8 (unit to DQ_UNIT_TOL) */
    const double *covs;             /* rows x 36 (symmetric positive definite) */
    const double *times;            /* rows: stamps */
    const long long *codes;         /* rows: the source's code, < ncodes */
    size_t ncodes;
    const double *latency;          /* ncodes: configured latency */
    const double *latency_w;        /* ncodes: 1 / sigma^2 of an estimated latency, else 0 */
    const double *E;                /* ncodes x 8: extrinsic (unit) */
    const double *E_info;           /* ncodes x 36: its prior's information, where uncertain */
    const unsigned char *uncertain; /* ncodes: the extrinsic is uncertain */
} dq_lookup_store;

/* One side of a Lookup: a body's rows (n = 0: the world frame, exact) and its warm start. */
typedef struct {
    const long long *rows;
    size_t n;
    int warm;        /* in: start from X, V (at t0) carried to the Lookup's time */
    double t0;
    double X[8];     /* in: the warm start; out: the estimate at the Lookup's time */
    double V[6];
} dq_lookup_body;

typedef struct {
    double at;                 /* the Lookup's time */
    const double *twist_w;     /* 36: the twist's prior information, or NULL */
    double max_extrapolation;  /* seconds (HUGE_VAL: no bound) */
    dq_fuse_params p;
    /* ncodes each, in: warm starts (NaN: none), out: the estimates of those fitted */
    double *L;                 /* latencies */
    double *Ehat;              /* ncodes x 8: extrinsics */
    /* the records of the fits of body 0 alone, body 1 alone, both together: in (NULL: none)
     * and out (malloc'd here, NULL where that fit did not run; the caller frees) */
    const double *rec_in[3];
    size_t rec_in_n[3];
    double *rec_out[3];
    size_t rec_out_n[3];
} dq_lookup_args;

/* T_target_source (pose 8, cov 36) of body[0] = target, body[1] = source; *shared = fitted
 * together. DQ_OK, DQ_LOOKUP_ELSEWHERE, DQ_LOOKUP_NOMEM, or a fit's DQ_E* code. */
int dq_lookup(const dq_lookup_store *s, dq_lookup_body *body, dq_lookup_args *a, double *pose,
              double *cov, int *shared);

/* A RelativePose's bytes (proto/dqpose/v1/world.proto) of the unit pose (8), its covariance
 * (36) and time, as protobuf writes the message world_convert.relative_msg makes: the pose's
 * position and orientation always present, zero doubles left out (+0.0 only), the covariance
 * packed. out: DQ_RELATIVE_POSE_MAX bytes; returns the length. */
#define DQ_RELATIVE_POSE_MAX 384
size_t dq_relative_pose_write(const double *pose, const double *cov, double time,
                              unsigned char *out);

#endif
