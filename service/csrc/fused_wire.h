/*
 * fused_wire.h — a dqpose.v1.FusedPose (proto/dqpose/v1/fusion.proto) written from a fit's
 * numbers in the bytes the protobuf runtime writes for the same message: fields in number
 * order, proto3's zeros left out (-0.0 kept), repeated scalars packed, the pose and its two
 * parts always present. The one writer of a fused answer: StreamFuse's, a World's tick and Fuse
 * (tests/rpc/test_fusion_convert.py checks it against protobuf on random fits).
 */
#ifndef DQPOSE_FUSED_WIRE_H
#define DQPOSE_FUSED_WIRE_H

#include <stddef.h>
#include <stdint.h>

typedef struct {
    const char *s; /* UTF-8 */
    size_t n;
} dq_str;

typedef struct { /* SourceConsistency */
    dq_str name;
    uint32_t count, rejected;
    double nis_mean, low, high;
    uint32_t verdict;
} dq_wire_source;

typedef struct { /* DroppedMeasurement */
    uint32_t index;
    dq_str source;
    double age;
    dq_str reason;
} dq_wire_dropped;

typedef struct { /* LatencyEstimate */
    dq_str source;
    double configured, prior_sigma, value, sigma;
} dq_wire_latency;

typedef struct {
    dq_str body;
    double time;
    double quat[4], t[3];          /* the pose: orientation w x y z, position */
    const double *covariance;      /* 36 */
    const uint32_t *inliers;
    size_t n_inliers;
    const uint32_t *rejected;      /* n_rejected each of rejected, reasons, rejected_sources */
    const dq_str *reasons, *rejected_sources;
    size_t n_rejected;
    double chi2;
    uint32_t dof, iterations, status;
    const double *distances, *nis, *residuals; /* n, n, 6n */
    const uint8_t *tested;                      /* n, 0 or 1 */
    size_t n;
    const dq_wire_source *sources;
    size_t n_sources;
    uint32_t request;
    const uint64_t *measurements;
    size_t n_measurements;
    const dq_wire_dropped *dropped;
    size_t n_dropped;
    const double *twist, *twist_covariance; /* 6 and 36, or NULL: no twist */
    double extrapolation;
    const dq_wire_latency *latencies;
    size_t n_latencies;
} dq_fused_pose;

/* the bytes dq_fused_pose_write writes at most for f */
size_t dq_fused_pose_bound(const dq_fused_pose *f);

/* f's FusedPose into out (dq_fused_pose_bound(f) bytes); returns the bytes written */
size_t dq_fused_pose_write(const dq_fused_pose *f, uint8_t *out);

#endif
