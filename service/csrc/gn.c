/*
 * gn.c — the fits' Gauss-Newton loop and step rule (see gn.h).
 */
#include "gn.h"

#include <math.h>

#include "linalg6.h"

int dq_newton_step(const double *H, const double *g, int dim, double *Lh, double *dh,
                   double *delta, double *step)
{
    if (!dq_chol(H, Lh, dh, dim)) return DQ_E_SINGULAR;
    dq_lower_solve(Lh, dh, g, delta, dim);
    dq_upper_solve(Lh, dh, delta, delta, dim);
    double s = 0.0;
    for (int j = 0; j < dim; j++) s += delta[j] * delta[j];
    *step = sqrt(s);
    return DQ_OK;
}

int dq_line_search(dq_trial_fn trial, void *solver, double *delta, int dim, double *step,
                   double total, double tol, double *cost)
{
    *cost = total;
    for (int h = 0; h < DQ_GN_MAX_HALVINGS; h++) {
        int rc = trial(solver, delta, cost);
        if (rc) return rc;
        if (*cost <= total * (1.0 + DQ_GN_COST_SLACK) || *step < tol) break;
        for (int j = 0; j < dim; j++) delta[j] *= 0.5;
        *step *= 0.5;
    }
    return DQ_OK;
}

int dq_gauss_newton(const dq_gn_problem *problem, void *self, double *delta,
                    const dq_fuse_params *p, double *total, int *status, int *iterations,
                    int *current)
{
    *current = 0;
    *status = DQ_FUSE_MAX_ITERATIONS;
    *iterations = p->max_iter;
    for (int it = 1; it <= p->max_iter; it++) {
        problem->linearize(self);
        double step, trial;
        int rc = problem->step(self, delta, &step);
        if (rc) return rc;
        if (step < p->tol) {
            *status = DQ_FUSE_CONVERGED;
            *iterations = it;
            *current = 1;
            return DQ_OK;
        }
        rc = dq_line_search(problem->trial, self, delta, problem->dim, &step, *total, p->tol,
                            &trial);
        if (rc) return rc;
        problem->accept(self);
        *total = trial;
        if (step < p->tol) {
            *status = DQ_FUSE_CONVERGED;
            *iterations = it;
            return DQ_OK;
        }
    }
    return DQ_OK;
}
