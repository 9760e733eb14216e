/*
 * traj_law.h — the time laws the trajectory planner (traj_plan.c) builds its segments from, in
 * pure C99: the shortest ramp between two rates within the limits (traj_law.c states the bounds
 * it is sized by), and a split segment's two rest-to-rest laws. Private to the trajectory files;
 * trajectory.h is the interface.
 */
#ifndef DQPOSE_TRAJ_LAW_H
#define DQPOSE_TRAJ_LAW_H

#include "trajectory.h"

/* Steps of the planner's bisections (a rest law's take twice as many). */
#define DQ_TRAJ_BISECT 60

/* The motion on one side of a ramp: its velocities at the corner and what bounds the rest. */
typedef struct {
    double v[3], w[3];  /* tool-point and angular velocity at the junction */
    double speed, spin; /* |v|, |w| (constant along a segment) */
    double nus, kappa;  /* rate at which v turns; centripetal acceleration = nus * speed */
} dq_traj_side;

/* Segment g at rate sigma, at its start (at_end 0) or its end. Inline: the planner's searches
 * build four a step. */
static inline dq_traj_side dq_traj_side_of(const dq_traj_seg *g, double sigma, int at_end)
{
    dq_traj_side s;
    const double *cv = at_end ? g->cv1 : g->cv0;
    for (int i = 0; i < 3; i++) { s.v[i] = sigma * cv[i]; s.w[i] = sigma * g->w[i]; }
    s.speed = sigma * g->len;
    s.spin = sigma * g->theta;
    s.nus = sigma * g->nu;
    s.kappa = s.nus * s.speed;
    return s;
}

/* The shortest ramp from A to B within the limits: its duration, beta and the limit that
 * decides it. Returns 0, or -1 when no duration will do (a constant term is over its limit). */
int dq_traj_ramp(const dq_traj_side *A, const dq_traj_side *B, const dq_traj_limits *L, double *T,
                 double *beta, int *bind);

/* A split segment's two laws, both as long as the slower one at full speed over lam (lam < 1:
 * slowed for a waypoint time). On the line the tool point's velocity is dp ds/dt and the tool's
 * theta axis ds'/dt, so each 1-D law within its own limits (per unit s: the limit over the
 * distance) is exactly within them. */
void dq_traj_split_laws(dq_traj_seg *g, const dq_traj_limits *L, double lam);

/* What evaluating a law needs: phase starts in t and s, and what the ramp shape divides by. */
void dq_traj_law_finish(dq_traj_law *law);

#endif
