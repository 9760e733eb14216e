/*
 * traj_eval.c — the dense evaluation of trajectory.h's planned segments: pose, tool-point and
 * angular velocity at any times.
 *
 * Sorted times fall in runs that share a segment, a blend state and a phase of each time law,
 * so everything but the times is a loop invariant: a run's poses are evaluated side by side
 * (each law's s, then the poses with the vector sin/cos of vecmath.h), which GCC vectorises,
 * instead of a search, a branchy law and two libm calls per pose and segment. Unsorted times
 * make runs of one pose and the same answers.
 */
/* As in blend.c: GCC if-converts the ramp shape's selects (a division in one arm) only without
 * FP traps, and only then vectorises the evaluation loops; no value changes. */
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC optimize("no-trapping-math")
#endif

#include "trajectory.h"

#include <math.h>
#include <string.h>

#include "dq.h"
#include "vecmath.h"

/* ---- the ramp shape ------------------------------------------------------------------------ */

/* g(tau) and its integral G(tau), each piece computed and one selected, so the evaluation loops
 * that inline them vectorise. ib = 1 / beta, h = 1 / (1 - beta). */
DQ_INLINE double shape_g(double tau, double beta, double h, double ib)
{
    double c = 0.5 * h * ib, w = 1.0 - tau;
    double rise = c * tau * tau, fall = 1.0 - c * w * w, mid = h * (tau - 0.5 * beta);
    return tau <= beta ? rise : tau >= 1.0 - beta ? fall : mid;
}

/* g is point-symmetric about (1/2, 1/2), so G(tau) = tau - 1/2 + G(1 - tau). */
DQ_INLINE double shape_G(double tau, double beta, double h, double ib)
{
    int left = tau <= 0.5;
    double x = left ? tau : 1.0 - tau, u = x - beta;
    double cubic = h * ib * x * x * x / 6.0;
    double quad = h * (beta * beta / 6.0 + 0.5 * beta * u + 0.5 * u * u);
    double G = x <= beta ? cubic : quad;
    return left ? G : tau - 0.5 + G;
}

/* Poses evaluated side by side at most (the stack arrays of a run). */
#define RUN 64

enum { PH_RAMP, PH_CRUISE, PH_CONST };

/* One phase of a law: where it holds (lo <= time since the segment's start < hi) and what s and
 * ds/dt there need. PH_CONST: s and ds/dt fixed (past the end of the law, or an end pose). */
typedef struct {
    double lo, hi, t0, s0, T, x, y, beta, h, ib, inv_T;
    int kind;
} law_phase;

/* The phase of law L at time tl since its segment's start: each phase takes the rate from
 * rate[i] to rate[i+1] with the ramp shape (the cruise: equal rates, no shape to evaluate). */
static void phase_at(const dq_traj_law *L, double tl, law_phase *P)
{
    int i = 0;
    while (i < 5 && tl >= L->t_at[i + 1]) i++;
    memset(P, 0, sizeof *P);
    P->lo = i > 0 ? L->t_at[i] : -INFINITY;
    if (i == 5) {
        P->hi = INFINITY;
        P->s0 = 1.0;
        P->kind = PH_CONST;
        return;
    }
    P->hi = L->t_at[i + 1];
    P->t0 = L->t_at[i], P->s0 = L->s_at[i], P->T = L->T[i];
    P->x = L->rate[i], P->y = L->rate[i + 1];
    P->beta = L->beta[i], P->h = L->h[i], P->ib = L->inv_beta[i], P->inv_T = L->inv_T[i];
    P->kind = P->x == P->y ? PH_CRUISE : PH_RAMP;
}

static void phase_fixed(double s, double sd, law_phase *P)
{
    memset(P, 0, sizeof *P);
    P->lo = -INFINITY, P->hi = INFINITY, P->s0 = s, P->x = sd, P->kind = PH_CONST;
}

static int in_phase(const law_phase *P, double tl) { return tl >= P->lo && tl < P->hi; }

/* s and ds/dt at the m times t (since the segment's start: t - start) of one phase. */
DQ_INLINE void phase_s(const law_phase *restrict P, const double *restrict t, double start, size_t m,
                       double *restrict s, double *restrict sd)
{
    const double t0 = P->t0, s0 = P->s0, T = P->T, x = P->x, y = P->y;
    if (P->kind == PH_CONST) {
        for (size_t j = 0; j < m; j++) { s[j] = s0; sd[j] = x; }
    } else if (P->kind == PH_CRUISE) {
        for (size_t j = 0; j < m; j++) {
            double u = (t[j] - start) - t0;
            s[j] = lo2(1.0, hi2(0.0, s0 + x * u));
            sd[j] = x;
        }
    } else {
        const double b = P->beta, h = P->h, ib = P->ib, iT = P->inv_T;
        for (size_t j = 0; j < m; j++) {
            double tau = ((t[j] - start) - t0) * iT;
            double G = shape_G(tau, b, h, ib), gg = shape_g(tau, b, h, ib);
            s[j] = lo2(1.0, hi2(0.0, s0 + T * (x * (tau - G) + y * G)));
            sd[j] = x * (1.0 - gg) + y * gg;
        }
    }
}

/* ScLERP of the pair at s with C, S = cos, sin(s phi): dq_sclerp_eval, the pure translation
 * folded in (then p1 = q = 0, h = 0, and cos/sin of the tiny phi are 1 and below rounding). */
DQ_INLINE void sclerp_cs(const dq_sclerp_pair *restrict p, double s, double C, double S, double *out)
{
    double th = s * p->h;
    for (int i = 0; i < 4; i++) {
        out[i] = C * p->p0[i] + S * p->p1[i];
        out[4 + i] = C * p->p3[i] + S * p->q[i] + th * (C * p->p1[i] - S * p->p0[i]) + s * p->p2[i];
    }
}

DQ_INLINE void from_rp(const double *r, const double *p, double *out)
{
    double tq[4] = {0.0, 0.5 * p[0], 0.5 * p[1], 0.5 * p[2]};
    for (int i = 0; i < 4; i++) out[i] = r[i];
    dq_qmul(tq, r, out + 4);
}

/* Rotation r, tool point p and their rates of segment g: the tool point (SCREW: the whole pose)
 * at s with rate sd, the orientation of a LINEAR segment at sr with rate sdr (a split segment's
 * second law, else s). */
DQ_INLINE void seg_at(const dq_traj_seg *restrict g, int screw, double s, double sd, double sr,
                      double sdr, double *r, double *p, double *v, double *w)
{
    double C, S;
    sincos_v((screw ? s : sr) * g->pair.phi, &S, &C);
    if (screw) {
        double out[8], t[4];
        sclerp_cs(&g->pair, s, C, S, out);
        double rc[4] = {out[0], -out[1], -out[2], -out[3]};
        for (int i = 0; i < 4; i++) r[i] = out[i];
        dq_qmul(out + 4, rc, t);
        for (int i = 0; i < 3; i++) p[i] = 2.0 * t[1 + i];
        /* the spatial twist is constant along a screw: v = w x p + vs */
        cross3(g->w, p, v);
        for (int i = 0; i < 3; i++) { v[i] = sd * (v[i] + g->vs[i]); w[i] = sd * g->w[i]; }
    } else {
        for (int i = 0; i < 4; i++) r[i] = C * g->pair.p0[i] + S * g->pair.p1[i];
        for (int i = 0; i < 3; i++) {
            p[i] = g->pa[i] + s * g->dp[i];
            v[i] = sd * g->dp[i];
            w[i] = sdr * g->w[i];
        }
    }
}

/* The m poses of a run on segment g alone. */
DQ_INLINE void run_plain(const dq_traj_seg *restrict g, int screw, size_t m, const double *restrict s,
                         const double *restrict sd, const double *restrict sr,
                         const double *restrict sdr, double *restrict pose, double *restrict lin,
                         double *restrict ang)
{
    for (size_t j = 0; j < m; j++) {
        double *o = pose + 8 * j, *v = lin + 3 * j, *w = ang + 3 * j;
        if (screw) {
            double C, S, vv[3];
            sincos_v(s[j] * g->pair.phi, &S, &C);
            sclerp_cs(&g->pair, s[j], C, S, o); /* ScLERP itself, not a rebuilt pose */
            rotate(o, g->vb, vv);
            for (int i = 0; i < 3; i++) { v[i] = sd[j] * vv[i]; w[i] = sd[j] * g->w[i]; }
        } else {
            double r[4], p[3];
            seg_at(g, 0, s[j], sd[j], sr[j], sdr[j], r, p, v, w);
            from_rp(r, p, o);
        }
    }
}

/* The m poses of a run in the blend from segment q into g: g's progress applied on top of q's. */
DQ_INLINE void run_blend(const dq_traj_seg *restrict g, const dq_traj_seg *restrict q, int screw,
                         size_t m, const double *restrict s, const double *restrict sd,
                         const double *restrict s0, const double *restrict sd0,
                         double *restrict pose, double *restrict lin, double *restrict ang)
{
    for (size_t j = 0; j < m; j++) {
        double r[4], p[3], v[3], w[3], r0[4], p0[3], v0[3], w0[3], e[4], rr[4], w0r[3], pp[3];
        seg_at(g, screw, s[j], sd[j], s[j], sd[j], r, p, v, w);
        seg_at(q, screw, s0[j], sd0[j], s0[j], sd0[j], r0, p0, v0, w0);
        dq_qmul(r, g->qa_conj, e);
        dq_qmul(e, r0, rr);
        rotate(e, w0, w0r);
        for (int i = 0; i < 3; i++) {
            pp[i] = p0[i] + p[i] - g->pa[i];
            lin[3 * j + i] = v[i] + v0[i];
            ang[3 * j + i] = w[i] + w0r[i];
        }
        from_rp(rr, pp, pose + 8 * j);
    }
}

DQ_CLONES void dq_traj_eval(const dq_traj_seg *seg, size_t nseg, int mode, double duration,
                            const double *t, size_t n, double *pose, double *lin, double *ang)
{
    const int screw = mode == DQ_TRAJ_SCREW;
    double s[RUN], sd[RUN], sr[RUN], sdr[RUN], s0[RUN], sd0[RUN];
    size_t k = 0;
    for (size_t i = 0; i < n;) {
        double ti = t[i];
        const dq_traj_seg *g, *q = NULL;
        law_phase P, R, Q;
        size_t m = 1;
        int end = ti <= 0.0 || ti >= duration, split = 0;
        if (end) {
            /* the ends exactly (below); the start moves at the start rate, the end is at rest */
            g = ti <= 0.0 ? &seg[0] : &seg[nseg - 1];
            phase_fixed(ti <= 0.0 ? 0.0 : 1.0, ti <= 0.0 ? g->law.rate[1] : 0.0, &P);
        } else {
            /* the last segment started by ti; sorted times keep the previous one as the guess */
            if (!(seg[k].start <= ti && (k + 1 == nseg || seg[k + 1].start > ti))) {
                size_t lo = 0, hi = nseg;
                while (hi - lo > 1) {
                    size_t mid = (lo + hi) / 2;
                    if (seg[mid].start <= ti) lo = mid; else hi = mid;
                }
                k = lo;
            }
            g = &seg[k];
            double next = k + 1 < nseg ? seg[k + 1].start : INFINITY;
            int blend_in = k > 0 && g->blend_in;
            double qend = blend_in ? seg[k - 1].start + dq_traj_seg_duration(&seg[k - 1]) : 0.0;
            if (blend_in && ti < qend) q = &seg[k - 1];
            split = !screw && g->split;
            phase_at(&g->law, ti - g->start, &P);
            if (split) phase_at(&g->turn, ti - g->start, &R);
            if (q) phase_at(&q->law, ti - q->start, &Q);
            /* the run: the following times in the same segment, blend state and phases */
            while (i + m < n && m < RUN) {
                double tj = t[i + m];
                if (!(tj > 0.0 && tj < duration && tj >= g->start && tj < next)) break;
                if (blend_in && (tj < qend) != (q != NULL)) break;
                if (!in_phase(&P, tj - g->start) || (split && !in_phase(&R, tj - g->start))) break;
                if (q && !in_phase(&Q, tj - q->start)) break;
                m++;
            }
        }
        double *o = pose + 8 * i, *v = lin + 3 * i, *w = ang + 3 * i;
        phase_s(&P, t + i, g->start, m, s, sd);
        if (q) {
            phase_s(&Q, t + i, q->start, m, s0, sd0);
            if (screw) run_blend(g, q, 1, m, s, sd, s0, sd0, o, v, w);
            else run_blend(g, q, 0, m, s, sd, s0, sd0, o, v, w);
        } else {
            const double *rs = s, *rsd = sd;
            if (split) {
                phase_s(&R, t + i, g->start, m, sr, sdr);
                rs = sr, rsd = sdr;
            }
            if (screw) run_plain(g, 1, m, s, sd, rs, rsd, o, v, w);
            else run_plain(g, 0, m, s, sd, rs, rsd, o, v, w);
        }
        if (end) memcpy(o, ti <= 0.0 ? g->a : g->b, 8 * sizeof(double));
        i += m;
    }
}
