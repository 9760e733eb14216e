/*
 * motion.c — the constant-twist fit of motion.h: Gauss-Newton over pose, twist and latencies
 * with the priors' information, each measurement whitened by its covariance's Cholesky factor as
 * in fusion.c, its Jacobian G_i kept compact (the columns it touches) and scattered into the
 * state's.
 */
#include "motion.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "dq.h"
#include "gn.h"
#include "linalg6.h"
#include "motion_work.h"
#include "se3.h"
#include "vecmath.h"

size_t dq_motion_dim(const dq_motion_model *m) { return (m->twist ? 12 : 6) + m->k; }

size_t dq_motion_workspace(size_t n, const dq_motion_model *m)
{
    size_t dim = dq_motion_dim(m);
    return (M_HJ + dim * (dim + 1) / 2) * n + 5 * dim * dim + 7 * dim + 6 * (dim + 1) * n +
           (2 * dim * dim + 2 * dim) * DQ_LANES;
}

/* The motion fit as a Gauss-Newton problem (gn.h): the state X, V, ell and a trial point's
 * Xn, Vn, elln; the inliers' residuals of the current point in slot ro, a trial's in rt. */
typedef struct {
    const dq_motion_model *m;
    const double *z;
    const unsigned char *inlier;
    size_t n;
    double *work;
    size_t stride;
    int dim, off, ro, rt;
    double *X, *V, *ell, Xn[8], Vn[6], *elln;
    double *H, *Lh, *g, *dh;
} motion_fit;

static void motion_fit_linearize(void *self)
{
    motion_fit *f = self;
    motion_linearize(f->m, f->V, f->work, f->stride, f->n, f->inlier, 0, f->ro, f->dim, f->H,
                     f->g, NULL);
    motion_prior_terms(f->m, f->V, f->ell, f->dim, f->H, f->g);
    dq_mirror(f->H, f->dim);
}

static int motion_fit_step(void *self, double *delta, double *length)
{
    motion_fit *f = self;
    return dq_newton_step(f->H, f->g, f->dim, f->Lh, f->dh, delta, length);
}

static int motion_fit_trial(void *self, const double *delta, double *cost)
{
    motion_fit *f = self;
    const dq_motion_model *m = f->m;
    if (dq_retract(f->X, delta, f->Xn)) return DQ_E_OVERFLOW;
    for (int j = 0; j < 6; j++) f->Vn[j] = m->twist ? f->V[j] + delta[6 + j] : f->V[j];
    for (int j = 0; j < (int)m->k; j++) f->elln[j] = f->ell[j] + delta[f->off + j];
    *cost = motion_evaluate(f->Xn, f->Vn, f->elln, f->z, m, f->work, f->stride, f->n, f->inlier,
                            1, f->rt) +
            motion_prior_cost(m, f->Vn, f->elln);
    return DQ_OK;
}

static void motion_fit_accept(void *self)
{
    motion_fit *f = self;
    for (int j = 0; j < 8; j++) f->X[j] = f->Xn[j];
    for (int j = 0; j < 6; j++) f->V[j] = f->Vn[j];
    for (int j = 0; j < (int)f->m->k; j++) f->ell[j] = f->elln[j];
    int t = f->ro; f->ro = f->rt; f->rt = t;
}

/* Gauss-Newton from out's X, V, ell over the selected measurements (motion.h), updated in place;
 * *slot is the workspace slot left holding the inliers' r, e at the estimate. The solver's
 * dim-sized arrays follow the measurements' blocks in work. *current = 1 (gn.h) says that the
 * information H (priors included, mirrored) and the inliers' whitened Jacobians (stacked by
 * motion_linearize) are at the estimate, and need not be computed again. */
static int motion_solve(const double *z, const unsigned char *inlier, size_t n,
                        const dq_motion_model *m, const dq_fuse_params *p, double *work,
                        size_t stride, int dim, int start_slot, double start_total,
                        dq_motion_fitted *out, int *slot, int *current)
{
    double *H = work + stride * n, *Lh = H + dim * dim, *g = Lh + dim * dim, *delta = g + dim;
    double *dh = delta + dim, *elln = dh + dim;
    /* the start's residuals and cost are the caller's */
    motion_fit f = {m, z, inlier, n, work, stride, dim, m->twist ? 12 : 6, start_slot,
                    start_slot == M_S0 ? M_S1 : M_S0, out->mean, out->twist, out->ell,
                    {0}, {0}, elln, H, Lh, g, dh};
    const dq_gn_problem problem = {dim, motion_fit_linearize, motion_fit_step, motion_fit_trial,
                                   motion_fit_accept};
    double total = start_total;
    int rc = dq_gauss_newton(&problem, &f, delta, p, &total, &out->status, &out->iterations,
                             current);
    *slot = f.ro;
    return rc;
}

/* Where the twist starts: the motion between the inliers taken first and last,
 * Log(Z_a^-1 Z_b) / (t_b - t_a) (exact for a constant twist without noise), when their
 * rotation is within a quarter turn (beyond, the logarithm could take the short way round a
 * faster spin); else (or with one instant) at rest. */
static void motion_twist_start(const double *z, const unsigned char *inlier, size_t n,
                               const dq_motion_model *m, double *V)
{
    size_t a = n, b = n;
    double ta = INFINITY, tb = -INFINITY;
    for (size_t i = 0; i < n; i++) {
        if (!dq_selected(inlier, i)) continue;
        double t = m->stamp[i] - (m->slot[i] >= 0 ? m->prior[m->slot[i]] : m->latency[i]);
        if (t < ta) { ta = t; a = i; }
        if (t > tb) { tb = t; b = i; }
    }
    for (int k = 0; k < 6; k++) V[k] = 0.0;
    if (a == n || !(tb > ta)) return;
    double ac[8], r[6], sc[2];
    dq_conj(z + 8 * a, ac);
    dq_se3_residual(ac, z + 8 * b, r, sc);
    if (!(fabs(sc[1]) >= 0.9238795325112867)) return;   /* cos(pi / 8): a quarter turn */
    for (int k = 0; k < 6; k++) V[k] = r[k] / (tb - ta);
    if (!dq_finite_n(V, 6))
        for (int k = 0; k < 6; k++) V[k] = 0.0;
}

int dq_motion_fit(const double *z, const double *cov, const unsigned char *inlier, size_t n,
                  const dq_motion_model *m, const double *start, const unsigned char *tested,
                  const dq_fuse_params *p, double *work, dq_motion_fitted *out,
                  const dq_motion_outputs *per, size_t *bad)
{
    const int dim = (int)dq_motion_dim(m), k = (int)m->k;
    /* the prefix sums of the information only when the leave-one-out NIS are wanted: without
     * them a measurement's block is a third of the size (fewer pages and cache lines) */
    const size_t stride = per->nis && tested ? M_HJ + (size_t)dim * (dim + 1) / 2 : M_PER;
    size_t n_in = 0;
    for (size_t i = 0; i < n; i++) {
        double *blk = work + stride * i;
        if (!dq_chol6(cov + 36 * i, blk + M_L, blk + M_DI)) {
            *bad = i;
            return DQ_E_NOT_SPD;
        }
        if (dq_selected(inlier, i)) n_in++;
    }
    if (n_in == 0) return DQ_E_NO_INLIERS;
    double *H = work + stride * n, *g = H + 2 * dim * dim, *scratch = g + 4 * dim;
    double *X = out->mean, *V = out->twist, *ell = out->ell;
    for (int j = 0; j < 8; j++) X[j] = start[j];
    for (int j = 0; j < k; j++) ell[j] = m->prior[j];
    for (int j = 0; j < 6; j++) V[j] = 0.0;
    int start_slot = M_S0;
    double total = motion_evaluate(X, V, ell, z, m, work, stride, n, inlier, 1, M_S0) +
                   motion_prior_cost(m, V, ell);
    if (m->twist) {
        /* the data's twist when it fits them better than rest does */
        double V0[6];
        motion_twist_start(z, inlier, n, m, V0);
        if (V0[0] != 0.0 || V0[1] != 0.0 || V0[2] != 0.0 || V0[3] != 0.0 || V0[4] != 0.0 ||
            V0[5] != 0.0) {
            double moving = motion_evaluate(X, V0, ell, z, m, work, stride, n, inlier, 1, M_S1) +
                            motion_prior_cost(m, V0, ell);
            if (moving < total) {
                for (int j = 0; j < 6; j++) V[j] = V0[j];
                total = moving;
                start_slot = M_S1;
            }
        }
    }
    int ro, current = 0, rc = motion_solve(z, inlier, n, m, p, work, stride, dim, start_slot,
                                           total, out, &ro, &current);
    if (rc) return rc;
    /* Everything at the estimate: the others' residuals (the inliers' are in slot ro), every
     * Jacobian, the inliers' information with the priors' (the solver's last when it is at the
     * estimate: then only the others' Jacobians are new). */
    motion_evaluate(X, V, ell, z, m, work, stride, n, inlier, 0, ro);
    if (current && !per->G) {
        for (size_t i = 0; i < n; i++)
            if (!dq_selected(inlier, i))
                motion_jacobian(m, V, i, work + stride * i, ro, dim, NULL, NULL, NULL, 0);
    } else {
        motion_linearize(m, V, work, stride, n, inlier, 1, ro, dim, H, g, per->G);
        motion_prior_terms(m, V, ell, dim, H, g);
        dq_mirror(H, dim);
    }
    double chi2 = motion_prior_cost(m, V, ell);
    for (size_t i = 0; i < n; i++) {
        const double *s = work + stride * i + ro, *e = s + S_E;
        double c = dq_sq6(e);
        if (dq_selected(inlier, i)) chi2 += c;
        if (per->cost) per->cost[i] = c;
        if (per->dt) per->dt[i] = s[S_DT];
        if (per->residuals)
            for (int j = 0; j < 6; j++) per->residuals[6 * i + j] = s[S_R + j];
    }
    out->chi2 = chi2;
    for (int j = 0; j < dim * dim; j++) out->H[j] = H[j];
    if (!dq_finite8(X) || !dq_finite_n(V, 6) || !dq_finite_n(ell, (size_t)k) ||
        !dq_finite_n(H, (size_t)dim * dim) || !(chi2 * 0.0 == 0.0))
        return DQ_E_OVERFLOW;
    if (per->nis && tested) {
        rc = motion_leave_one_out(m, V, ell, work, stride, n, inlier, tested, ro, dim, H,
                                  scratch, per->nis);
        if (rc) return rc;
        if (!dq_finite_n(per->nis, n)) return DQ_E_OVERFLOW;
    }
    return DQ_OK;
}

size_t dq_motion_nearest(const dq_motion_model *m, const unsigned char *inlier, size_t n)
{
    size_t best = n;
    double nearest = INFINITY;
    for (size_t i = 0; i < n; i++) {
        if (!dq_selected(inlier, i)) continue;
        double lat = m->slot[i] >= 0 ? m->prior[m->slot[i]] : m->latency[i];
        double d = fabs(m->stamp[i] - lat);
        if (d < nearest) {
            nearest = d;
            best = i;
        }
    }
    return best;
}

static int by_taken(const void *a, const void *b)
{
    double ta = ((const dq_taken *)a)->t, tb = ((const dq_taken *)b)->t;
    return (ta > tb) - (ta < tb);
}

void dq_motion_determined(const dq_motion_model *m, const unsigned char *inlier, size_t n,
                          dq_taken *work, unsigned char *det)
{
    size_t k = 0;
    for (size_t i = 0; i < n; i++)
        if (dq_selected(inlier, i)) {
            work[k].t = m->stamp[i] - m->latency[i];
            work[k++].i = i;
        }
    if (!m->twist || m->twist_w) {
        for (size_t i = 0; i < n; i++) det[i] = k - (dq_selected(inlier, i) ? 1 : 0) >= 1;
        return;
    }
    /* Sorted by the time taken, equal times are runs; an inlier alone in its run is the only
     * one of its instant, and leaving it out loses that instant. Rows come mostly in time order:
     * sorted already, they are not sorted again (the runs, all that is read, are the same). */
    size_t sorted = 1;
    while (sorted < k && work[sorted].t >= work[sorted - 1].t) sorted++;
    if (sorted < k) qsort(work, k, sizeof *work, by_taken);
    size_t instants = 0;
    for (size_t a = 0, b; a < k; a = b) {
        for (b = a + 1; b < k && work[b].t == work[a].t; b++) continue;
        instants++;
    }
    for (size_t i = 0; i < n; i++) det[i] = instants >= 2;
    for (size_t a = 0, b; a < k; a = b) {
        for (b = a + 1; b < k && work[b].t == work[a].t; b++) continue;
        if (b == a + 1) det[work[a].i] = instants - 1 >= 2;
    }
}

int dq_motion_run(const dq_motion_run_args *c, const dq_motion_model *m, dq_motion_fitted *f,
                  const dq_motion_outputs *per, size_t *bad, const char **bad_name)
{
    const size_t n = c->n;
    int code = DQ_OK;
    double start[8];
    for (size_t i = 0; i < n && code == DQ_OK; i++) {
        if ((code = dq_unit(c->poses + 8 * i, c->zu + 8 * i))) *bad = i;
        else if (!dq_finite_n(c->covs + 36 * i, 36)) {
            code = DQ_E_NONFINITE; *bad = i; *bad_name = "covariances";
        }
    }
    if (code == DQ_OK && !c->start) {
        size_t j = dq_motion_nearest(m, c->inlier, n);
        if (j == n) code = DQ_E_NO_INLIERS;
        else memcpy(start, c->zu + 8 * j, sizeof start);
    } else if (code == DQ_OK && (code = dq_unit(c->start, start))) {
        *bad_name = "start";
    }
    if (code == DQ_OK && c->tested) {
        if (c->find_tested) {
            dq_motion_determined(m, c->inlier, n, c->taken, c->tested);
            for (size_t i = 0; i < n; i++)
                c->tested[i] = c->tested[i] || (c->inlier && !c->inlier[i]);
        } else {
            memcpy(c->tested, c->tested_in, n);
        }
    }
    if (code == DQ_OK) {
        code = dq_motion_fit(c->zu, c->covs, c->inlier, n, m, start, c->tested, c->p, c->work, f,
                             per, bad);
        *bad_name = "covariances";
    }
    /* (dq_spd_inverse's workspace fits in the fit's, spent by then) */
    if (code == DQ_OK && !dq_spd_inverse(f->H, (int)dq_motion_dim(m), c->work, c->P))
        code = DQ_E_SINGULAR;
    return code;
}
