/*
 * tick.c — one tick's answer in one call (see tick.h). Each step names the Python it moves;
 * the operations are those, in that order.
 */
#include "tick.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "dq.h"
#include "joint.h"
#include "motion.h"

#define REASON_MAX 400 /* a dropped measurement's reason: its source's name is <= 128 bytes */

/* a tick's memory, carved from one block */
static void *carve(char **at, size_t bytes)
{
    void *p = *at;
    *at += (bytes + 15) & ~(size_t)15;
    return p;
}

/* The set-up (alignment.time_setup and _span): per row its latency, when it was taken, its slot
 * among the estimated latencies (sources in order of first appearance); the fusion time; the
 * rows kept (max_skew), their span and the extrapolation. */
typedef struct {
    double *stamp, *latency, *taken;
    long long *slot;
    unsigned char *keep, *drop;
    int *local;      /* per source code: its index among the rows' sources, or -1 */
    int64_t *order;  /* the rows' sources (codes), in order of first appearance */
    size_t n_sources, k;
    double *prior, *prior_w;
    int64_t *estimated; /* k codes */
    long long *ext_slot; /* per row: its source among the uncertain extrinsics, or -1 */
    int64_t *ext;        /* the uncertain extrinsics' sources (codes), in order */
    size_t n_ext;
    double time, lo, hi, extrapolation;
    int skewed, one_instant;
} tick_setup;

static int setup(const dq_tick_options *o, const dq_tick_input *in, tick_setup *u)
{
    const size_t n = in->n;
    for (size_t c = 0; c < o->m; c++) u->local[c] = -1;
    u->n_sources = u->n_ext = 0;
    for (size_t i = 0; i < n; i++) {
        int64_t c = in->codes[in->rows[i]];
        if (c < 0 || (size_t)c >= o->m) return DQ_TICK_PYTHON; /* a source the options lack */
        if (u->local[c] < 0) {
            u->local[c] = (int)u->n_sources;
            u->order[u->n_sources++] = c;
            if (!o->exact[c]) u->ext[u->n_ext++] = c; /* extrinsics.uncertain_extrinsics' order */
        }
        long long e = -1;
        for (size_t j = 0; j < u->n_ext; j++)
            if (u->ext[j] == c) e = (long long)j;
        u->ext_slot[i] = e;
        u->latency[i] = o->latency[c];
        u->taken[i] = in->times[in->rows[i]] - u->latency[i];
    }
    double time = in->time;
    if (isnan(time)) { /* taken.max() */
        time = u->taken[0];
        for (size_t i = 1; i < n; i++)
            if (u->taken[i] > time) time = u->taken[i];
    }
    u->time = time;
    int any = 0;
    u->skewed = 0;
    for (size_t i = 0; i < n; i++) {
        u->drop[i] = o->has_skew && fabs(time - u->taken[i]) > o->max_skew;
        u->keep[i] = !u->drop[i];
        u->skewed |= u->drop[i];
        if (!u->keep[i]) continue;
        if (!any || u->taken[i] < u->lo) u->lo = u->taken[i];
        if (!any || u->taken[i] > u->hi) u->hi = u->taken[i];
        any = 1;
    }
    if (!any) return DQ_TICK_PYTHON; /* every row beyond max_skew: Python names it */
    double e = 0.0; /* max(0.0, time - hi, lo - time) */
    if (time - u->hi > e) e = time - u->hi;
    if (u->lo - time > e) e = u->lo - time;
    u->extrapolation = e;
    if (o->has_extrapolation && e > o->max_extrapolation) return DQ_TICK_PYTHON;
    /* one instant brought elsewhere needs the twist's prior (Python names it); one instant at
     * the fusion time is the static fit */
    if (u->lo == u->hi && e > 0.0 && !o->twist_w) return DQ_TICK_PYTHON;
    u->one_instant = u->lo == u->hi && e == 0.0;
    u->k = 0;
    for (size_t s = 0; s < u->n_sources; s++) {
        int64_t c = u->order[s];
        if (!o->estimated[c]) continue;
        u->prior[u->k] = o->latency[c];
        u->prior_w[u->k] = o->prior_w[c];
        u->estimated[u->k++] = c;
    }
    for (size_t i = 0; i < n; i++) {
        int64_t c = in->codes[in->rows[i]];
        long long slot = -1;
        for (size_t j = 0; j < u->k; j++)
            if (u->estimated[j] == c) slot = (long long)j;
        u->slot[i] = slot;
        u->stamp[i] = in->times[in->rows[i]] - time;
    }
    return 0;
}

/* consistency.source_stats of the non-robust fit: every kept row (keep NULL: every row) an
 * inlier, the dropped ones neither tested nor rejected. */
static void source_stats(const dq_tick_options *o, const dq_tick_input *in, const tick_setup *u,
                         const unsigned char *keep, const double *nis,
                         const unsigned char *tested, dq_wire_source *out)
{
    const size_t n = in->n, m = u->n_sources;
    int used = 0;
    for (size_t s = 0; s < m; s++) {
        memset(out + s, 0, sizeof *out);
        out[s].name = o->names[u->order[s]];
    }
    for (size_t i = 0; i < n; i++) used |= tested[i] && (!keep || keep[i]);
    if (!used) return; /* every source untested, none rejected */
    double *sums = (double *)calloc(m ? m : 1, sizeof *sums);
    for (size_t i = 0; i < n; i++) { /* the bincounts, in row order */
        size_t s = (size_t)u->local[in->codes[in->rows[i]]];
        int use = tested[i] && (!keep || keep[i]);
        out[s].count += use ? 1 : 0;
        sums[s] += use ? nis[i] : 0.0;
    }
    for (size_t s = 0; s < m; s++) {
        uint32_t count = out[s].count;
        if (!count) continue;
        double mean = sums[s] / (double)count;
        double low = o->low[count], high = o->high[count];
        out[s].nis_mean = mean;
        out[s].low = low;
        out[s].high = high;
        out[s].verdict = mean > high ? 2 : mean < low ? 3 : 1; /* Verdict's values */
    }
    free(sums);
}

/* Dropped.reason */
static size_t dropped_reason(char *buf, size_t i, dq_str src, double age, double max_skew)
{
    char who[200];
    if (src.n) snprintf(who, sizeof who, "measurement %zu (%.*s)", i, (int)src.n, src.s);
    else snprintf(who, sizeof who, "measurement %zu", i);
    int len = snprintf(buf, REASON_MAX, "%s: taken %.6g s %s the fusion time, beyond max_skew %g s",
                       who, age >= 0 ? age : -age, age >= 0 ? "before" : "after", max_skew);
    return len < 0 ? 0 : (size_t)len < REASON_MAX ? (size_t)len : REASON_MAX - 1;
}

/* What the fits fill of a tick's answer (the rest is the set-up's): the fused pose's fields. */
typedef struct {
    double *res, *nis, *dist, *cov, *tcov, *P, *ell;
    unsigned char *tested;
    uint32_t *inliers;
    size_t dim;
    double *joint; /* the joint fit's memory (the caller frees it), or NULL */
} tick_fit;

/* With uncertain extrinsics (extrinsics.motion_fit_ext): the joint fit of the one body (its
 * model: the motion model, or static._fit's static_model) and the extrinsics' errors
 * (extrinsics.joint_fit of one part, as _dqcore.joint_fit runs it, NIS included) of the rows
 * inlier selects, from the fit f, which it replaces (mean, twist, latencies, chi2, status,
 * iterations; t: P, the residuals and the NIS). */
static int fit_joint(const dq_tick_options *o, const tick_setup *u, const dq_motion_model *mm,
                     const unsigned char *inlier, const double *s, size_t n, const double *zu,
                     dq_motion_fitted *f, double *dt, double *cost, tick_fit *t)
{
    dq_joint_part part = {n, mm->twist, mm->twist_w};
    dq_joint_model jm = {1, &part, mm->stamp, mm->latency, mm->slot, u->ext_slot, mm->k,
                         mm->prior, mm->prior_w, u->n_ext, NULL, NULL};
    const size_t D = dq_joint_dim(&jm), m = u->n_ext;
    size_t doubles = dq_joint_workspace(n, &jm, 1) + 2 * D * D + D + 8 + 6 + u->k + 1 +
                     8 * m + 8 * m + 36 * m + (sizeof(dq_taken) * n) / sizeof(double) + 1;
    double *mem = t->joint = (double *)malloc(sizeof(double) * doubles);
    if (!mem) return DQ_E_OVERFLOW;
    double *work = mem, *H = work + dq_joint_workspace(n, &jm, 1), *P = H + D * D, *g = P + D * D;
    double *X = g + D, *V = X + 8, *L = V + 6, *E = L + u->k + 1, *Ehat = E + 8 * m;
    double *info = Ehat + 8 * m;
    dq_taken *taken = (dq_taken *)(info + 36 * m);
    int code = dq_unit(f->mean, X); /* joint_run's checks: the start and E unit, all finite */
    for (size_t j = 0; j < m && code == DQ_OK; j++) {
        code = dq_unit(o->E + 8 * u->ext[j], E + 8 * j);
        memcpy(info + 36 * j, o->E_info + 36 * u->ext[j], 36 * sizeof(double));
        if (code == DQ_OK && !dq_finite_n(info + 36 * j, 36)) code = DQ_E_NONFINITE;
    }
    if (code != DQ_OK) return code;
    memcpy(V, f->twist, sizeof f->twist);
    memcpy(L, f->ell, sizeof(double) * mm->k);
    jm.E = E;
    jm.E_info = info;
    dq_joint_state st = {X, V, L, Ehat, H, P, g, 0.0, 0, 0, 0};
    dq_joint_outputs per = {dt, t->res, cost, NULL, t->nis, t->tested};
    size_t bad = 0;
    code = dq_joint_fit(zu, s, inlier, n, &jm, &o->p, work, taken, &st, &per, &bad);
    if (code != DQ_OK) return code;
    memcpy(f->mean, X, sizeof f->mean);
    memcpy(f->twist, V, sizeof f->twist);
    memcpy(f->ell, L, sizeof(double) * mm->k);
    f->chi2 = st.chi2;
    f->status = st.status;
    f->iterations = st.iterations;
    t->P = P;
    t->dim = D;
    return DQ_OK;
}

/* The constant-twist fit (_motion_fit -> constant_twist_fit, NIS included) into w. */
static int fit_motion(const dq_tick_options *o, const tick_setup *u, const double *z,
                      const double *s, size_t n, char **at, tick_fit *t, dq_fused_pose *w,
                      double *mean, double *twist)
{
    dq_motion_model model = {u->stamp, u->latency, u->slot, u->k, u->prior, u->prior_w, 1,
                             o->twist_w};
    const size_t dim0 = t->dim = dq_motion_dim(&model);
    double *dt = carve(at, sizeof(double) * n), *cost = carve(at, sizeof(double) * n);
    double *zu = carve(at, sizeof(double) * 8 * n);
    double *work = carve(at, sizeof(double) * dq_motion_workspace(n, &model));
    double *H = carve(at, sizeof(double) * dim0 * dim0);
    dq_taken *taken_work = carve(at, sizeof(dq_taken) * n);
    t->P = carve(at, sizeof(double) * dim0 * dim0);
    dq_motion_fitted f;
    f.ell = t->ell;
    f.H = H;
    /* with uncertain extrinsics, the fit the joint fit starts from: without its NIS */
    dq_motion_outputs per = {dt, t->res, cost, NULL, u->n_ext ? NULL : t->nis};
    dq_motion_run_args r = {z, s, u->keep, NULL, n, NULL, 1, u->n_ext ? NULL : t->tested, &o->p,
                            work, zu, t->P, taken_work};
    size_t bad = 0;
    const char *bad_name = "poses";
    int code = dq_motion_run(&r, &model, &f, &per, &bad, &bad_name);
    if (code != DQ_OK) return code;
    if (u->n_ext) {
        code = fit_joint(o, u, &model, u->keep, s, n, zu, &f, dt, cost, t);
        if (code != DQ_OK) return code;
    }
    memcpy(mean, f.mean, sizeof f.mean);
    const size_t dim = t->dim;
    for (size_t a = 0; a < 6; a++)
        for (size_t b = 0; b < 6; b++) {
            t->cov[6 * a + b] = t->P[dim * a + b];
            t->tcov[6 * a + b] = t->P[dim * (6 + a) + 6 + b];
        }
    for (size_t i = 0; i < n; i++)
        if (u->keep[i]) t->inliers[w->n_inliers++] = (uint32_t)i;
    /* only the twist's unconstrained 6 reduce the degrees of freedom beyond the pose's */
    w->dof = (uint32_t)(6 * ((long)w->n_inliers - 1) - (o->twist_w ? 0 : 6));
    w->chi2 = f.chi2;
    w->iterations = (uint32_t)f.iterations;
    w->status = (uint32_t)f.status + 1; /* STATUS_ENUMS */
    for (size_t i = 0; i < n; i++) t->dist[i] = sqrt(cost[i]);
    memcpy(twist, f.twist, sizeof f.twist);
    w->twist = twist;
    w->twist_covariance = t->tcov;
    return DQ_OK;
}

/* One instant at the fusion time: the static fit of every row (static._fit, as _dqcore.fuse
 * runs it), the twist at its prior (zeros, the prior's covariance) when it has one. */
static int fit_static(const dq_tick_options *o, const tick_setup *u, const double *z,
                      const double *s, size_t n, char **at, tick_fit *t, dq_fused_pose *w,
                      double *mean, double *twist)
{
    double *zu = carve(at, sizeof(double) * 8 * n);
    double *work = carve(at, sizeof(double) * dq_fuse_workspace(n));
    unsigned char *all = carve(at, n);
    int code = DQ_OK;
    for (size_t i = 0; i < n && code == DQ_OK; i++) {
        code = dq_unit(z + 8 * i, zu + 8 * i);
        if (code == DQ_OK && !dq_finite_n(s + 36 * i, 36)) code = DQ_E_NONFINITE;
        all[i] = 1;
    }
    if (code != DQ_OK) return code;
    dq_fused f;
    dq_fuse_outputs per = {t->res, t->dist, t->nis, t->tested};
    size_t bad = 0;
    if ((code = dq_fuse(zu, s, all, n, &o->p, work, &f, &per, &bad)) != DQ_OK) return code;
    memcpy(mean, f.mean, sizeof f.mean);
    memcpy(t->cov, f.covariance, sizeof f.covariance);
    w->chi2 = f.chi2;
    w->iterations = (uint32_t)f.iterations;
    w->status = (uint32_t)f.status + 1;
    if (u->n_ext) { /* static._fit with ext: the joint fit of static_model from the C fit */
        double *zeros = carve(at, sizeof(double) * n), *dt = carve(at, sizeof(double) * n);
        double *cost = carve(at, sizeof(double) * n);
        long long *none = carve(at, sizeof(long long) * n);
        for (size_t i = 0; i < n; i++) {
            zeros[i] = 0.0;
            none[i] = -1;
        }
        dq_motion_model stat = {zeros, zeros, none, 0, NULL, NULL, 0, NULL};
        dq_motion_fitted jf;
        memcpy(jf.mean, f.mean, sizeof f.mean);
        memset(jf.twist, 0, sizeof jf.twist);
        jf.ell = t->ell;
        if ((code = fit_joint(o, u, &stat, all, s, n, zu, &jf, dt, cost, t)) != DQ_OK)
            return code;
        memcpy(mean, jf.mean, sizeof jf.mean);
        for (size_t a = 0; a < 6; a++)
            for (size_t b = 0; b < 6; b++) t->cov[6 * a + b] = t->P[t->dim * a + b];
        for (size_t i = 0; i < n; i++) t->dist[i] = sqrt(cost[i]);
        w->chi2 = jf.chi2;
        w->iterations = (uint32_t)(f.iterations + jf.iterations);
        w->status = (uint32_t)jf.status + 1;
    }
    for (size_t i = 0; i < n; i++) t->inliers[w->n_inliers++] = (uint32_t)i;
    w->dof = (uint32_t)(6 * ((long)n - 1));
    if (o->twist_w) {
        memset(twist, 0, 6 * sizeof(double));
        w->twist = twist;
        w->twist_covariance = o->twist_cov;
    }
    return DQ_OK;
}

/* The rows max_skew dropped, with their reasons, as the answer's dropped entries. */
static void dropped(const dq_tick_options *o, const dq_tick_input *in, const tick_setup *u,
                    char **at, dq_fused_pose *w)
{
    const size_t n = in->n;
    dq_wire_dropped *d = carve(at, sizeof(dq_wire_dropped) * n);
    char *text = carve(at, (size_t)REASON_MAX * n);
    for (size_t i = 0; i < n; i++) {
        if (!u->drop[i]) continue;
        dq_wire_dropped *x = d + w->n_dropped++;
        x->index = (uint32_t)i;
        x->source = o->names[in->codes[in->rows[i]]];
        x->age = u->time - u->taken[i];
        x->reason.s = text;
        x->reason.n = dropped_reason(text, i, x->source, x->age, o->max_skew);
        text += REASON_MAX;
    }
    w->dropped = d;
}

/* The estimated latencies' entries (one instant shows none estimated: each keeps its prior). */
static void latencies(const dq_tick_options *o, const tick_setup *u, const tick_fit *t,
                      char **at, dq_fused_pose *w)
{
    dq_wire_latency *lat = carve(at, sizeof(dq_wire_latency) * (u->k + 1));
    for (size_t j = 0; j < u->k; j++) {
        int64_t c = u->estimated[j];
        lat[j].source = o->names[c];
        lat[j].configured = o->latency[c];
        lat[j].prior_sigma = o->sigma[c];
        lat[j].value = u->one_instant ? o->latency[c] : t->ell[j];
        lat[j].sigma = u->one_instant ? o->sigma[c]
                                      : sqrt(t->P[(12 + j) * t->dim + 12 + j]);
    }
    w->latencies = lat;
    w->n_latencies = u->k;
}

int dq_tick(const dq_tick_options *o, const dq_tick_input *in, uint8_t **out, size_t *len)
{
    const size_t n = in->n, m = o->m;
    if (!n || in->n > (size_t)1 << 28 || n >= o->n_bounds) return DQ_TICK_PYTHON;
    const size_t dim_max = 12 + m;
    dq_motion_model probe = {NULL, NULL, NULL, m, NULL, NULL, 1, NULL};
    size_t work_n = dq_motion_workspace(n, &probe) + dq_fuse_workspace(n);
    size_t bytes = 16 * (64 + 6 * m + 8 * n) + sizeof(double) * (8 * n + 36 * n + 12 * n +
                   6 * n + 8 * n + work_n + 3 * dim_max * dim_max + 4 * m + 72) +
                   sizeof(long long) * 3 * n + sizeof(int) * m + sizeof(int64_t) * (4 * m + n) +
                   sizeof(dq_taken) * n + sizeof(uint32_t) * n +
                   (sizeof(dq_wire_source) + sizeof(dq_wire_latency)) * (m + 1) +
                   (sizeof(dq_wire_dropped) + REASON_MAX) * n + 5 * n;
    char *block = (char *)malloc(bytes), *at = block;
    if (!block) return -1;
    tick_setup u;
    u.stamp = carve(&at, sizeof(double) * n);
    u.latency = carve(&at, sizeof(double) * n);
    u.taken = carve(&at, sizeof(double) * n);
    u.slot = carve(&at, sizeof(long long) * n);
    u.keep = carve(&at, n);
    u.drop = carve(&at, n);
    u.local = carve(&at, sizeof(int) * (m ? m : 1));
    u.order = carve(&at, sizeof(int64_t) * (m ? m : 1));
    u.prior = carve(&at, sizeof(double) * (m ? m : 1));
    u.prior_w = carve(&at, sizeof(double) * (m ? m : 1));
    u.estimated = carve(&at, sizeof(int64_t) * (m ? m : 1));
    u.ext = carve(&at, sizeof(int64_t) * (m ? m : 1));
    u.ext_slot = carve(&at, sizeof(long long) * n);
    int code = setup(o, in, &u);
    if (code) {
        free(block);
        return code;
    }
    double *z = carve(&at, sizeof(double) * 8 * n), *s = carve(&at, sizeof(double) * 36 * n);
    for (size_t i = 0; i < n; i++) { /* the rows' world-frame poses and covariances */
        memcpy(z + 8 * i, in->poses + 8 * in->rows[i], 8 * sizeof(double));
        memcpy(s + 36 * i, in->covs + 36 * in->rows[i], 36 * sizeof(double));
    }
    tick_fit t;
    t.res = carve(&at, sizeof(double) * 6 * n);
    t.nis = carve(&at, sizeof(double) * n);
    t.dist = carve(&at, sizeof(double) * n);
    t.cov = carve(&at, sizeof(double) * 36);
    t.tcov = carve(&at, sizeof(double) * 36);
    t.ell = carve(&at, sizeof(double) * (u.k ? u.k : 1));
    t.tested = carve(&at, n);
    t.inliers = carve(&at, sizeof(uint32_t) * n);
    t.joint = NULL;
    dq_fused_pose w;
    memset(&w, 0, sizeof w);
    double mean[8], unit[8], twist[6];
    code = u.one_instant ? fit_static(o, &u, z, s, n, &at, &t, &w, mean, twist)
                         : fit_motion(o, &u, z, s, n, &at, &t, &w, mean, twist);
    if (code != DQ_OK || dq_unit(in->pose ? in->pose : mean, unit)) { /* Python names it */
        free(t.joint);
        free(block);
        return DQ_TICK_PYTHON;
    }
    /* _result (the static fit's Fused and its replace, one instant) */
    w.body = in->body;
    w.time = u.time;
    dq_to_pose(unit, w.quat, w.t);
    w.covariance = in->cov ? in->cov : t.cov;
    w.inliers = t.inliers;
    w.distances = t.dist;
    w.nis = t.nis;
    w.tested = t.tested;
    w.residuals = t.res;
    w.n = n;
    dq_wire_source *sources = carve(&at, sizeof(dq_wire_source) * (u.n_sources + 1));
    source_stats(o, in, &u, u.one_instant ? NULL : u.keep, t.nis, t.tested, sources);
    w.sources = sources;
    w.n_sources = u.n_sources;
    w.request = in->request;
    uint64_t *ids = carve(&at, sizeof(uint64_t) * n);
    for (size_t i = 0; i < n; i++) ids[i] = (uint64_t)in->ids[in->rows[i]];
    w.measurements = ids;
    w.n_measurements = n;
    if (u.skewed && !u.one_instant) dropped(o, in, &u, &at, &w); /* the static fit lists none */
    w.extrapolation = u.extrapolation;
    latencies(o, &u, &t, &at, &w);
    *out = (uint8_t *)malloc(dq_fused_pose_bound(&w));
    if (*out) *len = dq_fused_pose_write(&w, *out);
    free(t.joint);
    free(block);
    return *out ? 0 : -1;
}
