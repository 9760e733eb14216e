/*
 * tick.h — one tick's answer in one call: a body's rows (the store's columns and the picked row
 * numbers) to the FusedPose bytes of its fit over time (service/fusion/alignment.py's
 * fuse_in_time, not robust, the constant twist, every extrinsic exact), the same operations in
 * the same order, so the same bits: the set-up (time_setup, _span), the fit (dq_motion_run, as
 * _dqcore.motion_fit runs it; one instant at the fusion time: dq_fuse, as _dqcore.fuse runs
 * it; uncertain extrinsics: dq_joint_fit of one part from that fit, as _dqcore.joint_fit runs
 * it), the result (_result or the static fit's, consistency.source_stats) and the message
 * (fused_wire.h, as wire.fused_pose_bytes writes it). What it does not port (robust and
 * correlated fits are not asked for; any error: the texts are Python's) is DQ_TICK_PYTHON: the
 * caller runs the Python path for that tick.
 */
#ifndef DQPOSE_TICK_H
#define DQPOSE_TICK_H

#include <stddef.h>
#include <stdint.h>

#include "fused_wire.h"
#include "fusion.h"

/* the caller's Python path makes this tick's answer (or names its error) */
#define DQ_TICK_PYTHON 1

/* What every tick of one configuration shares: per source code (0..m-1, the tracker's) its
 * configured latency, whether it is estimated (latency_sigma given) with its prior's sigma and
 * information (sigma^-2 as Python computes it), whether its extrinsic is exact, its name; the
 * options; and the chi2 bounds of the per-source verdict by count (low[c], high[c] for c tested
 * measurements, c < n_bounds, filled by chi2.chi2_quantile). */
typedef struct {
    size_t m;
    const double *latency, *sigma, *prior_w;
    const unsigned char *estimated, *exact;
    const dq_str *names;
    int has_skew, has_extrapolation;
    double max_skew, max_extrapolation;
    const double *twist_w; /* 36, or NULL: no twist prior */
    const double *twist_cov; /* 36: the prior's covariance (as checked), with twist_w */
    const double *E, *E_info; /* m x 8, m x 36: an uncertain extrinsic and its information */
    double probability;
    dq_fuse_params p;
    const double *low, *high;
    size_t n_bounds;
} dq_tick_options;

/* One tick: the store's columns (world-frame poses n x 8 and covariances n x 36, stamps, source
 * codes, ids) read at rows[0..n), the fusion time (NaN: the rows' newest taken), the answer's
 * body and request; pose (8) and cov (36): the answer's pose and covariance instead of the fit's
 * (a World answer relative to another body), or NULL. */
typedef struct {
    const double *poses, *covs, *times;
    const int64_t *codes, *ids, *rows;
    size_t n;
    double time;
    dq_str body;
    uint32_t request;
    const double *pose, *cov;
} dq_tick_input;

/* The tick's FusedPose bytes in *out (malloc'd, *len bytes; the caller frees it): 0; or
 * DQ_TICK_PYTHON (nothing allocated); or -1: out of memory. */
int dq_tick(const dq_tick_options *o, const dq_tick_input *in, uint8_t **out, size_t *len);

#endif
