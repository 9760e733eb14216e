/*
 * trajectory.h — time scaling of keyframe paths on SE(3) under coupled Cartesian limits, and
 * their dense evaluation (service/trajectory.py is the API; conventions in dq.h).
 *
 * Each segment k moves a parameter s in [0, 1] from waypoint k to k+1: the pose is ScLERP
 * (DQ_TRAJ_SCREW) or the tool point on the straight line with the orientation slerped
 * (DQ_TRAJ_LINEAR). The rate ds/dt rises from its start value (0, or the rate at a blended
 * corner) to a cruise rate sigma over a ramp, cruises, and falls over another ramp to 0 or to the
 * next corner's rate. Every ramp has the shape g of a jerk-limited S-curve (trapezoidal dg/dtau
 * over tau in [0, 1], jerk phases of fraction beta). At a corner with a blend radius the two
 * segments' corner rates fall to 0 and rise from 0 at the same time with the same g ("time
 * blending"): the position is c_k(s_k) + c_{k+1}(s_{k+1}) - corner and the rotation the progress
 * of segment k+1 applied to that of segment k, so the velocity is the convex combination
 * (1 - g) V_k + g V_{k+1} and its derivatives are g', g'' times known differences plus terms
 * that the planner bounds (traj_law.c). Every limit is checked on these bounds, never on
 * samples. A corner's rates are lowered (only there: the cruise keeps its speed) until its blend
 * fits the radius; at rate 0 the corner is a stop. A LINEAR segment at rest at both ends (a
 * stop, not the first segment when it starts moving) is split: the tool point follows s(t) and
 * the orientation its own s'(t), each time-optimal under its own limits, the faster stretched
 * to the slower one's duration.
 */
#ifndef DQPOSE_TRAJECTORY_H
#define DQPOSE_TRAJECTORY_H

#include <stddef.h>

#include "blend.h"

enum { DQ_TRAJ_LINEAR = 1, DQ_TRAJ_SCREW = 2 };

/* What decided a segment's cruise rate; the names are the Limits fields (trajectory.py). */
enum {
    DQ_BIND_LIN_VEL = 0, DQ_BIND_ANG_VEL, DQ_BIND_LIN_ACC, DQ_BIND_ANG_ACC, DQ_BIND_LIN_JERK,
    DQ_BIND_ANG_JERK, DQ_BIND_TIME
};

/* Planner results besides DQ_OK. *bad is the waypoint index they concern. */
enum {
    DQ_TRAJ_E_TIME = 20,      /* waypoint *bad cannot be reached by its time */
    DQ_TRAJ_E_START = 21,     /* the start velocity cannot be brought into the path */
    DQ_TRAJ_E_STUCK = 22,     /* no positive rate satisfies the limits around waypoint *bad */
    DQ_TRAJ_E_MEMORY = 23
};

typedef struct {
    double vel[2], acc[2], jerk[2]; /* [linear, angular]; jerk 0 = no limit */
} dq_traj_limits;

/* A time law s(t): five phases, each taking ds/dt from rate[i] to rate[i+1] over T[i] with the
 * ramp shape of fraction beta[i]: the blend from the previous segment (rates 0 -> sig_in; T 0
 * when the corner is a stop), the ramp to the cruise, the cruise, the ramp to sig_out, the blend
 * into the next segment (sig_out -> 0). */
typedef struct {
    double T[5], beta[5], rate[6];
    double t_at[6], s_at[6];         /* time since start and s at the start of each phase */
    double inv_T[5], h[5], inv_beta[5];
} dq_traj_law;

typedef struct {
    dq_sclerp_pair pair;   /* the whole pose (SCREW) or the rotation only (LINEAR) */
    double a[8], b[8];     /* the waypoints, b in a's hemisphere */
    double pa[3], dp[3];   /* LINEAR: start point and its displacement */
    double qa_conj[4];     /* rotation of a, conjugated: the blend composes through it */
    double w[3];           /* angular velocity per unit ds/dt, base frame (theta * axis) */
    double vb[3];          /* SCREW: tool-point velocity per unit ds/dt, tool frame */
    double vs[3];          /* SCREW: linear part of the spatial twist per unit ds/dt */
    double cv0[3], cv1[3]; /* tool-point velocity per unit ds/dt at s = 0 and 1, base frame */
    double len, theta, nu; /* |c'|, rotation angle, rate at which c' turns (SCREW: theta) */
    double cap;            /* the largest cruise rate the velocity limits and the cruise allow */
    int cap_bind;
    double start, sigma, sig_in, sig_out;
    dq_traj_law law;       /* s(t): the whole pose, or (split) the tool point only */
    dq_traj_law turn;      /* split: the orientation's own s(t), as long as law */
    int split;             /* LINEAR, at rest at both ends, translating and turning: translation
                            * and rotation each time-optimal under their own limits,
                            * synchronised to the slower (one moving part: law alone) */
    int blend_in;          /* phase 0 is shared with the previous segment's phase 4 */
    int bind;
} dq_traj_seg;

/* Plans the path through K >= 2 unit waypoints wp (K x 8, each in the previous one's
 * hemisphere, no two consecutive equal). radius[k] > 0 blends the corner at waypoint k
 * (1 <= k <= K-2) and must be at most half of both neighbouring path lengths (the caller
 * checks); times[k] > 0 is the time waypoint k must be reached (0: free; increasing).
 * sigma0 is the start rate ds/dt of segment 0. Fills seg[0..K-2]; *duration the total. */
int dq_traj_plan(const double *wp, size_t K, int mode, const double *radius, const double *times,
                 const dq_traj_limits *lim, double sigma0, dq_traj_seg *seg, double *duration,
                 size_t *bad);

/* A planned segment's duration (its law's end; a blend into the next overlaps the last phase). */
static inline double dq_traj_seg_duration(const dq_traj_seg *g) { return g->law.t_at[5]; }

/* Pose (n x 8), tool-point velocity and angular velocity (n x 3, base frame) at times t, in
 * any order; sorted times are evaluated in runs side by side (traj_eval.c), several times
 * faster. */
void dq_traj_eval(const dq_traj_seg *seg, size_t nseg, int mode, double duration,
                  const double *t, size_t n, double *pose, double *lin, double *ang);

#endif
