/*
 * gn.h — the one Gauss-Newton loop of the fits (fusion.c, motion.c, joint.c), GTSAM's split:
 * each fit is a problem (its linearisation, its step, its trial point, its accept), the loop and
 * the step rule are here. The fits keep their own kernels (the static fit's unrolled 6 x 6
 * arithmetic gives other bits than the general one), so the loop only orders their calls.
 */
#ifndef DQ_GN_H
#define DQ_GN_H

#include "dq.h"
#include "fusion.h"

/* The step rule: a step that raises the cost by more than DQ_GN_COST_SLACK (relative) is
 * halved, at most DQ_GN_MAX_HALVINGS times (service/fusion/process_noise.py's NumPy loop reads
 * both from the module). */
#define DQ_GN_COST_SLACK 1e-12
#define DQ_GN_MAX_HALVINGS 30

/* A solver's trial point: the state moved by delta into the solver's trial buffers, and the
 * cost there into *cost; DQ_OK or the DQ_E* code that stops the fit. */
typedef int (*dq_trial_fn)(void *solver, const double *delta, double *cost);

/* A fit as the loop sees it; `self` is the fit's own state. */
typedef struct {
    int dim;
    /* H and g at the current point (no-op for a fit that keeps them current itself) */
    void (*linearize)(void *self);
    /* delta = H^-1 g and its length: DQ_OK, or DQ_E_SINGULAR when H does not factor */
    int (*step)(void *self, double *delta, double *length);
    dq_trial_fn trial;
    /* the trial point left by the last trial becomes the current one */
    void (*accept)(void *self);
} dq_gn_problem;

/* Gauss-Newton from the current point of cost *total: linearize, step; a step shorter than
 * tol is not taken (the point it was computed at is the optimum to within tol, and H is at it:
 * *current = 1); else the line search below, accept, and a step halved below tol ends the loop
 * (the line search found no lower cost). *status and *iterations as dq_fused's, *total the cost
 * at the returned point. */
int dq_gauss_newton(const dq_gn_problem *problem, void *self, double *delta,
                    const dq_fuse_params *p, double *total, int *status, int *iterations,
                    int *current);

/* delta = H^-1 g of the dim x dim information H (mirrored; Lh and dh hold its Cholesky factor)
 * and its length *step: DQ_OK, or DQ_E_SINGULAR when H does not factor. The general step
 * (the static fit's is the 6 x 6 one of linalg6.h). */
int dq_newton_step(const double *H, const double *g, int dim, double *Lh, double *dh,
                   double *delta, double *step);

/* The step rule above: trial(solver, delta) from the full step (dim entries, *step its length)
 * down, halving delta and *step while the cost rises above total by more than the slack; a
 * step halved below tol is taken. *cost is the cost of the trial point left in the solver's
 * buffers. */
int dq_line_search(dq_trial_fn trial, void *solver, double *delta, int dim, double *step,
                   double total, double tol, double *cost);

#endif
