/*
 * traj_plan.c — the planner of trajectory.h: each segment's geometry and cruise cap, then the
 * rates lowered until every corner's blend fits its radius and every segment's ramps fit in it
 * (traj_law.c sizes each ramp), then timed waypoints met by slowing the intervals before them.
 */
#include "trajectory.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "dq.h"
#include "traj_law.h"
#include "vecmath.h"

/* At most this many sweeps over the corners and segments before the plan must have settled. */
#define SWEEPS 100

typedef struct {
    dq_traj_seg *seg;
    size_t n;
    int mode;
    const double *radius;
    const dq_traj_limits *L;
    double sigma0;
    /* the last ramp solved at each corner (its rates, then T, beta, binding, result): the
     * searches over one segment's cruise keep asking for the same corner ramps */
    double (*memo)[6];
} plan_ctx;

static int blended(const plan_ctx *c, size_t k) { return k > 0 && k < c->n && c->seg[k].blend_in; }

/* The blend ramp at corner k between segment k-1 at rate sa and segment k at rate sb. */
static int corner_ramp(const plan_ctx *c, size_t k, double sa, double sb, double *T, double *beta,
                       int *bind)
{
    double *m = c->memo[k];
    if (m[0] != sa || m[1] != sb) {
        dq_traj_side A = dq_traj_side_of(&c->seg[k - 1], sa, 1);
        dq_traj_side B = dq_traj_side_of(&c->seg[k], sb, 0);
        int bd = 0, rc = dq_traj_ramp(&A, &B, c->L, &m[2], &m[3], &bd);
        m[0] = sa, m[1] = sb, m[4] = bd, m[5] = rc;
    }
    *T = m[2], *beta = m[3], *bind = (int)m[4];
    return (int)m[5];
}

/* How far a blended corner k, its two corner rates scaled by f, misses its radius: the tool
 * point's largest distance from the corner over the radius, minus 1 (<= 0: fits; INFINITY: no
 * ramp satisfies the limits). */
static double corner_gap(const plan_ctx *c, size_t k, double f, int *bind)
{
    double T, b, sa = f * c->seg[k - 1].sig_out, sb = f * c->seg[k].sig_in;
    if (corner_ramp(c, k, sa, sb, &T, &b, bind) < 0) return INFINITY;
    return 0.5 * T * hi2(sa * c->seg[k - 1].len, sb * c->seg[k].len) / c->radius[k] - 1.0;
}

/* A segment's speed at rate r, for comparing the two sides of a corner: the tool point's, or
 * the tool's turning speed when the tool point stays put. */
static double corner_speed(const dq_traj_seg *g, double r) { return r * (g->len > 0 ? g->len : g->theta); }

/* The factor that brings the faster side of corner k down to the slower side's speed, and which
 * side that is (1: the segment after the corner). */
static double equalising(const plan_ctx *c, size_t k, int *after)
{
    double va = corner_speed(&c->seg[k - 1], c->seg[k - 1].sig_out);
    double vb = corner_speed(&c->seg[k], c->seg[k].sig_in);
    *after = vb > va;
    return *after ? va / vb : (va > 0 ? vb / va : 1.0);
}

/* corner_gap with only the faster side lowered, from its own rate (f = 1) to the slower side's
 * speed (f = 0). */
static double faster_gap(const plan_ctx *c, size_t k, double f, int *bind)
{
    int after;
    double e = equalising(c, k, &after), m = e + f * (1.0 - e), T, b;
    double sa = c->seg[k - 1].sig_out * (after ? 1.0 : m), sb = c->seg[k].sig_in * (after ? m : 1.0);
    if (corner_ramp(c, k, sa, sb, &T, &b, bind) < 0) return INFINITY;
    return 0.5 * T * hi2(sa * c->seg[k - 1].len, sb * c->seg[k].len) / c->radius[k] - 1.0;
}

/* The five phases of segment k (trajectory.h) at cruise rate s and corner rates si, so (the
 * cruise's duration left 0). Returns the s it covers outside the cruise, or -1 when a ramp is
 * infeasible; *bind the limit of the longest ramp of its own. */
static double phases(const plan_ctx *c, size_t k, double s, double si, double so, double *T,
                     double *B, double *R, int *bind)
{
    const dq_traj_seg *g = &c->seg[k];
    int b1 = DQ_BIND_LIN_ACC, b3 = DQ_BIND_LIN_ACC, b;
    double r[6] = {0.0, si, s, s, so, 0.0};
    memset(T, 0, 5 * sizeof *T);
    for (int i = 0; i < 5; i++) B[i] = 0.5;
    if (blended(c, k) && corner_ramp(c, k, c->seg[k - 1].sig_out, si, &T[0], &B[0], &b) < 0) return -1;
    dq_traj_side S0 = dq_traj_side_of(g, si, 0), S1 = dq_traj_side_of(g, s, 0);
    dq_traj_side S2 = dq_traj_side_of(g, s, 1), S3 = dq_traj_side_of(g, so, 1);
    if (dq_traj_ramp(&S0, &S1, c->L, &T[1], &B[1], &b1) < 0) return -1;
    if (dq_traj_ramp(&S2, &S3, c->L, &T[3], &B[3], &b3) < 0) return -1;
    if (blended(c, k + 1) && corner_ramp(c, k + 1, so, c->seg[k + 1].sig_in, &T[4], &B[4], &b) < 0)
        return -1;
    *bind = T[1] >= T[3] ? b1 : b3;
    double covered = 0.0;
    for (int i = 0; i < 5; i++) {
        if (R) { R[i] = r[i]; R[5] = r[5]; }
        covered += 0.5 * (r[i] + r[i + 1]) * T[i];
    }
    return covered;
}

/* Segment k with its rates scaled to cruise f * sigma: how much more than its s in [0, 1] its
 * ramps need (<= 0: they fit; INFINITY: a ramp is infeasible). Corner rates never exceed the
 * cruise; the start rate sigma0 is given. */
static double fit_gap(const plan_ctx *c, size_t k, double f, int *bind)
{
    const dq_traj_seg *g = &c->seg[k];
    double s = f * g->sigma, T[5], B[5];
    double si = blended(c, k) ? lo2(g->sig_in, s) : g->sig_in;
    double so = lo2(g->sig_out, s);
    double covered = phases(c, k, s, si, so, T, B, NULL, bind);
    return covered < 0.0 ? INFINITY : covered - 1.0;
}

typedef double (*gap_fn)(const plan_ctx *, size_t, double, int *);

/* The largest factor f in [0, 1] with gap(f) <= 0, given gap(0) <= 0 < gap(1), to within
 * 1e-9 of f or of the gap: regula falsi (Illinois), which converges in a few steps where the
 * gap is smooth, with bisection where it is infinite. */
static double largest_factor(gap_fn gap, const plan_ctx *c, size_t k, int *bind)
{
    double lo = 0.0, hi = 1.0, glo = gap(c, k, 0.0, bind), ghi = gap(c, k, 1.0, bind);
    int last = 0;
    for (int it = 0; it < DQ_TRAJ_BISECT && hi - lo > 1e-9 && glo < -1e-9; it++) {
        double f = 0.5 * (lo + hi);
        if (isfinite(ghi)) {
            f = lo + (hi - lo) * glo / (glo - ghi);
            f = lo2(hi2(f, lo + 1e-3 * (hi - lo)), hi - 1e-3 * (hi - lo));
        }
        double gf = gap(c, k, f, bind);
        if (gf <= 0.0) {
            lo = f; glo = gf;
            if (last < 0 && isfinite(ghi)) ghi *= 0.5;
            last = -1;
        } else {
            hi = f; ghi = gf;
            if (last > 0) glo *= 0.5;
            last = 1;
        }
    }
    gap(c, k, lo, bind);
    return lo;
}

/* Cruise rates from the caps scaled by lam; corner rates lowered until each blend fits its
 * radius, cruise rates until each segment's ramps fit in it; then the time law. */
static int solve(plan_ctx *c, const double *lam, size_t *bad)
{
    size_t n = c->n;
    int bind;
    for (size_t k = 0; k < n; k++) {
        dq_traj_seg *g = &c->seg[k];
        g->sigma = lam[k] * g->cap;
        g->bind = lam[k] < 1.0 ? DQ_BIND_TIME : g->cap_bind;
        g->sig_in = blended(c, k) ? g->sigma : k == 0 ? c->sigma0 : 0.0;
        g->sig_out = blended(c, k + 1) ? g->sigma : 0.0;
        g->split = c->mode == DQ_TRAJ_LINEAR && !blended(c, k) && !blended(c, k + 1)
                   && g->sig_in == 0.0;
    }
    int settled = 0;
    for (int sweep = 0; sweep < SWEEPS && !settled; sweep++) {
        settled = 1;
        for (size_t k = 1; k < n; k++) {
            if (!blended(c, k) || corner_gap(c, k, 1.0, &bind) <= 0.0) continue;
            /* unequal corner speeds make a longer blend: lower the faster side first, then both */
            int after;
            double e = equalising(c, k, &after);
            double *fast = after ? &c->seg[k].sig_in : &c->seg[k - 1].sig_out;
            if (faster_gap(c, k, 0.0, &bind) <= 0.0) {
                double f = largest_factor(faster_gap, c, k, &bind);
                *fast *= e + f * (1.0 - e);
            } else {
                *fast *= e;
                double f = largest_factor(corner_gap, c, k, &bind);
                c->seg[k - 1].sig_out *= f;   /* f = 0: no blend fits, a stop */
                c->seg[k].sig_in *= f;
            }
            settled = 0;
        }
        for (size_t k = 0; k < n; k++) {
            dq_traj_seg *g = &c->seg[k];
            if (g->split || fit_gap(c, k, 1.0, &bind) <= 0.0) continue;
            double f = largest_factor(fit_gap, c, k, &bind);
            if (f <= 0.0) {
                *bad = k;
                return k == 0 && c->sigma0 > 0 ? DQ_TRAJ_E_START : DQ_TRAJ_E_STUCK;
            }
            g->sigma *= f;
            if (blended(c, k)) g->sig_in = lo2(g->sig_in, g->sigma);
            g->sig_out = lo2(g->sig_out, g->sigma);
            g->bind = bind;
            settled = 0;
        }
    }
    if (!settled) { *bad = 0; return DQ_TRAJ_E_STUCK; }
    double t = 0.0;
    for (size_t k = 0; k < n; k++) {
        dq_traj_seg *g = &c->seg[k];
        if (g->split) {
            dq_traj_split_laws(g, c->L, lam[k]);
        } else {
            double covered = phases(c, k, g->sigma, g->sig_in, g->sig_out, g->law.T, g->law.beta,
                                    g->law.rate, &bind);
            g->law.T[2] = hi2(0.0, (1.0 - covered) / g->sigma);
            dq_traj_law_finish(&g->law);
        }
        if (k > 0) {
            const dq_traj_seg *p = &c->seg[k - 1];
            t = p->start + (g->blend_in ? p->law.t_at[4] : p->law.t_at[5]); /* a blend overlaps phase 4 */
        }
        g->start = t;
    }
    return DQ_OK;
}

/* When waypoint m (>= 1) is reached: the end of a stop, the middle of a blend. */
static double arrival(const plan_ctx *c, size_t m)
{
    if (m == c->n) return c->seg[m - 1].start + dq_traj_seg_duration(&c->seg[m - 1]);
    const dq_traj_seg *g = &c->seg[m];
    return g->blend_in ? g->start + 0.5 * g->law.T[0] : g->start;
}

static void geometry(const double *a, const double *b, int mode, dq_traj_seg *g)
{
    double ac[8], rel[8], l[6], wb[3];
    memset(g, 0, sizeof *g); /* every field defined: the table is handed to Python as bytes */
    memcpy(g->a, a, sizeof g->a);
    memcpy(g->b, b, sizeof g->b);
    dq_conj(a, ac);
    dq_mul(ac, b, rel);
    dq_log(rel, l);
    for (int i = 0; i < 3; i++) { wb[i] = 2.0 * l[i]; g->vb[i] = 2.0 * l[3 + i]; }
    g->theta = norm3(wb);
    rotate(a, wb, g->w);
    double qa[4], ta[3], qb[4], tb[3];
    dq_to_pose(a, qa, ta);
    dq_to_pose(b, qb, tb);
    g->qa_conj[0] = a[0];
    for (int i = 1; i < 4; i++) g->qa_conj[i] = -a[i];
    for (int i = 0; i < 3; i++) { g->pa[i] = ta[i]; g->dp[i] = tb[i] - ta[i]; }
    if (mode == DQ_TRAJ_SCREW) {
        dq_sclerp_prepare(a, b, &g->pair);
        rotate(a, g->vb, g->cv0);
        rotate(b, g->vb, g->cv1);
        double wp[3];
        cross3(g->w, g->pa, wp);
        for (int i = 0; i < 3; i++) g->vs[i] = g->cv0[i] - wp[i];
        g->len = norm3(g->vb);
        g->nu = g->theta;
    } else {
        double ra[8] = {a[0], a[1], a[2], a[3], 0, 0, 0, 0}, rb[8] = {b[0], b[1], b[2], b[3], 0, 0, 0, 0};
        dq_sclerp_prepare(ra, rb, &g->pair);
        memcpy(g->cv0, g->dp, sizeof g->cv0);
        memcpy(g->cv1, g->dp, sizeof g->cv1);
        g->len = norm3(g->dp);
        g->nu = 0.0;
    }
}

/* The cruise alone: speed limits, and on a helix its centripetal acceleration and jerk. */
static void cap_of(dq_traj_seg *g, const dq_traj_limits *L)
{
    double best = INFINITY;
    int bind = DQ_BIND_LIN_VEL;
#define CAP_(value, name) do { double v_ = (value); if (v_ < best) { best = v_; bind = (name); } } while (0)
    if (g->len > 0) CAP_(L->vel[0] / g->len, DQ_BIND_LIN_VEL);
    if (g->theta > 0) CAP_(L->vel[1] / g->theta, DQ_BIND_ANG_VEL);
    if (g->nu * g->len > 0) {
        CAP_(sqrt(L->acc[0] / (g->nu * g->len)), DQ_BIND_LIN_ACC);
        if (L->jerk[0] > 0) CAP_(cbrt(L->jerk[0] / (g->nu * g->nu * g->len)), DQ_BIND_LIN_JERK);
    }
#undef CAP_
    g->cap = best;
    g->cap_bind = bind;
}

/* Timed waypoints: the cruise of the segments since the previous timed waypoint is slowed by one
 * common factor lam until the waypoint is reached on time. A blended corner couples neighbouring
 * intervals, so the sweep repeats until every time holds. */
static int meet_times(plan_ctx *c, const double *times, double *lam, size_t *bad)
{
    size_t K = c->n + 1, late = 0;
    int rc = solve(c, lam, bad);
    /* start every interval at the slowdown its free duration suggests, so each one is then
     * solved beside neighbours already near their own (a slowed neighbour changes the blend
     * into an interval, hence what that interval can reach) */
    double t_prev = 0.0, a_prev = 0.0;
    for (size_t m = 1, p = 0; !rc && m < K; m++) {
        if (!(times[m] > 0)) continue;
        double a = arrival(c, m), f = (a - a_prev) / (times[m] - t_prev);
        for (size_t k = p; k < m; k++) lam[k] = lo2(1.0, hi2(f, 1e-9));
        t_prev = times[m], a_prev = a, p = m;
    }
    for (int sweep = 0; !rc && sweep < 20; sweep++) {
        size_t p = 0;
        late = 0;
        for (size_t m = 1; m < K && !rc; m++) {
            if (!(times[m] > 0)) continue;
            double tol = 1e-9 * hi2(1.0, times[m]);
            /* after the first sweep the plan is the last one solved: an interval still on time
             * keeps its slowdown */
            if (sweep > 0 && fabs(arrival(c, m) - times[m]) <= 0.1 * tol) { p = m; continue; }
            for (size_t k = p; k < m; k++) lam[k] = 1.0;
            if ((rc = solve(c, lam, bad))) break;
            double start = p > 0 ? arrival(c, p) : 0.0, al = arrival(c, m) - times[m];
            if (al > tol) {
                /* too late even at full speed: the other intervals may still move */
                if (!late) late = m;
                p = m;
                continue;
            }
            /* The arrival rises as the interval slows, nearly in proportion to x = 1 / lam (the
             * time at each rate scales with it): secant steps in x from that proportion until
             * the time is bracketed, then regula falsi with the Illinois weighting, every third
             * step a bisection so a kink cannot stall it. */
            double xl = 1.0, xh = INFINITY, ah = 0.0, last = al, slope = al + times[m] - start;
            int kept = 0;
            for (int it = 0; it < DQ_TRAJ_BISECT && !rc && fabs(last) > 0.1 * tol; it++) {
                double x;
                if (isinf(xh)) x = slope > 0.0 ? xl - al / slope : 2.0 * xl;
                else if (it % 3 == 2) x = 0.5 * (xl + xh);
                else x = xl - al * (xh - xl) / (ah - al);
                if (!(x > xl && x < xh)) x = isinf(xh) ? 2.0 * xl : 0.5 * (xl + xh);
                for (size_t k = p; k < m; k++) lam[k] = 1.0 / x;
                rc = solve(c, lam, bad);
                last = arrival(c, m) - times[m];
                if (last > 0.0) {
                    if (kept == 1) al *= 0.5;
                    xh = x, ah = last, kept = 1;
                } else {
                    if (kept == -1) ah *= 0.5;
                    if (isinf(xh)) slope = (last - al) / (x - xl);
                    xl = x, al = last, kept = -1;
                }
            }
            p = m;
        }
        if (rc || (rc = solve(c, lam, bad))) break;
        int met = 1;
        for (size_t m = 1; m < K; m++)
            if (times[m] > 0 && fabs(arrival(c, m) - times[m]) > 1e-9 * hi2(1.0, times[m])) met = 0;
        if (met) return DQ_OK;
        if (late && sweep > 0) { *bad = late; return DQ_TRAJ_E_TIME; }
    }
    if (!rc) {
        *bad = late;
        rc = late ? DQ_TRAJ_E_TIME : DQ_TRAJ_E_STUCK;
    }
    return rc;
}

int dq_traj_plan(const double *wp, size_t K, int mode, const double *radius, const double *times,
                 const dq_traj_limits *lim, double sigma0, dq_traj_seg *seg, double *duration,
                 size_t *bad)
{
    size_t n = K - 1;
    plan_ctx c = {seg, n, mode, radius, lim, sigma0, malloc((n + 1) * sizeof *c.memo)};
    double *lam = malloc(n * sizeof *lam);
    if (!lam || !c.memo) {
        free(lam);
        free(c.memo);
        return DQ_TRAJ_E_MEMORY;
    }
    for (size_t k = 0; k <= n; k++) c.memo[k][0] = -1.0; /* no rate is negative: nothing solved */
    int timed = 0;
    for (size_t k = 0; k < n; k++) {
        geometry(wp + 8 * k, wp + 8 * (k + 1), mode, &seg[k]);
        cap_of(&seg[k], lim);
        seg[k].blend_in = k > 0 && radius[k] > 0;
        lam[k] = 1.0;
        timed |= times[k + 1] > 0;
    }
    int rc = timed ? meet_times(&c, times, lam, bad) : solve(&c, lam, bad);
    free(lam);
    free(c.memo);
    if (!rc) *duration = arrival(&c, n);
    return rc;
}
