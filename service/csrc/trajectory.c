/*
 * trajectory.c — the planner and the dense evaluation of trajectory.h.
 *
 * Why the limits hold (the bounds every ramp is sized by; tau = (t - t0) / T, |g'| <= h =
 * 1 / (1 - beta), |g''| <= h / beta, g(1 - g) <= 1/4):
 *   velocity   (1 - g) V_A + g V_B: a convex combination, so never above the larger cruise.
 *   linear     a = (g'/T) (V_B(t) - V_A(t)) + centripetal terms (SCREW only: the tool point is on
 *              a helix, its velocity turns at rate nu * ds/dt). |V_B(t) - V_A(t)| is at most the
 *              difference at the corner plus how far each turned during the ramp, which gives
 *              |a| <= (h/T) D + (h/2)(kA + kB) + max(kA, kB), k = nu sigma |V| (0 on lines);
 *              |j| <= (h/(beta T^2)) D + (h/T)(3 + 1/(2 beta))(kA + kB) + max(nu sigma k).
 *   angular    the blend rotation is E_B(s_B) E_A(s_A) q with E_B a rotation about w_B, which
 *              keeps the angle between w_B and the rotated w_A, so with the cross product
 *              X = |w_A x w_B| of the two cruise angular velocities:
 *              |alpha| <= (h/T) |w_B - w_A| + X/4,
 *              |j| <= (h/(beta T^2)) |w_B - w_A| + 2 (h/T) X + (4/27) X max(|w_A|, |w_B|).
 *   radius     the tool point is within max(|V_A|, |V_B|) T / 2 of the corner (the distance
 *              along each path left to travel, a convex function of tau, so largest at the ends).
 * The shortest T meeting all of them is solved in closed form for the beta of the leading
 * (1/T) terms — exactly the 1-D time-optimal S-curve on straight lines — and the cruise rates are
 * lowered (bisection on a common factor) wherever a ramp cannot meet its radius, a constant term
 * leaves no room, or the ramps do not fit in their segment.
 *
 * A split segment (LINEAR, at rest at both ends) needs none of these bounds: the tool point
 * moves by dp s(t) and the tool turns about one fixed axis by theta s'(t), so each of the two
 * 1-D laws within (limit / distance) is exactly within its limits. Each law is the 1-D
 * time-optimal rest-to-rest S-curve (its cruise rate the velocity limit, or the largest whose
 * ramps fit: closed form), and the faster is stretched to the slower one's duration by lowering
 * its cruise rate (bisection, the duration falling as the rate rises), which lowers every peak.
 */
/* As in blend.c: GCC if-converts the ramp shape's selects (a division in one arm) only without
 * FP traps, and only then vectorises the evaluation loops; no value changes. */
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC optimize("no-trapping-math")
#endif

#include "trajectory.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "dq.h"
#include "vecmath.h"

/* With no jerk limit the ramps still get jerk phases, so the acceleration stays continuous (C2
 * position); this fraction of the ramp costs at most 5 % of its time. */
#define BETA_FREE 0.05
#define BISECT 60
#define SWEEPS 100

/* fmin/fmax are library calls under -std=c99; nothing here is NaN (the input is checked). */
static inline double lo2(double a, double b) { return a < b ? a : b; }
static inline double hi2(double a, double b) { return a > b ? a : b; }

static double norm3(const double *v) { return sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]); }

DQ_INLINE void cross3(const double *a, const double *b, double *c)
{
    c[0] = a[1] * b[2] - a[2] * b[1];
    c[1] = a[2] * b[0] - a[0] * b[2];
    c[2] = a[0] * b[1] - a[1] * b[0];
}

/* R(q) v for a unit quaternion q = (w, u): v + 2w (u x v) + 2 u x (u x v) */
DQ_INLINE void rotate(const double *q, const double *v, double *out)
{
    double t[3], tt[3];
    cross3(q + 1, v, t);
    for (int i = 0; i < 3; i++) t[i] *= 2.0;
    cross3(q + 1, t, tt);
    for (int i = 0; i < 3; i++) out[i] = v[i] + q[0] * t[i] + tt[i];
}

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

/* ---- ramps ----------------------------------------------------------------------------------- */

/* The motion on one side of a ramp: its velocities at the corner and what bounds the rest. */
typedef struct {
    double v[3], w[3];  /* tool-point and angular velocity at the junction */
    double speed, spin; /* |v|, |w| (constant along a segment) */
    double nus, kappa;  /* rate at which v turns; centripetal acceleration = nus * speed */
} side;

static side side_of(const dq_traj_seg *g, double sigma, int at_end)
{
    side s;
    const double *cv = at_end ? g->cv1 : g->cv0;
    for (int i = 0; i < 3; i++) { s.v[i] = sigma * cv[i]; s.w[i] = sigma * g->w[i]; }
    s.speed = sigma * g->len;
    s.spin = sigma * g->theta;
    s.nus = sigma * g->nu;
    s.kappa = s.nus * s.speed;
    return s;
}

/* Largest x = 1/T with c2 x^2 + c1 x + c0 <= lim; -1 when c0 leaves no room, INFINITY when
 * nothing depends on x. */
static double x_max(double c2, double c1, double c0, double lim)
{
    double r = lim - c0;
    if (!(r > 0.0)) return -1.0;
    double den = c1 + sqrt(c1 * c1 + 4.0 * c2 * r);
    return den > 0.0 ? 2.0 * r / den : INFINITY;
}

/* The shortest ramp from A to B within the limits: its duration, beta and the limit that
 * decides it. Returns 0, or -1 when no duration will do (a constant term is over its limit). */
static int ramp(const side *A, const side *B, const dq_traj_limits *L, double *T, double *beta,
                int *bind)
{
    double dv[3], dw[3], x[3];
    for (int i = 0; i < 3; i++) { dv[i] = B->v[i] - A->v[i]; dw[i] = B->w[i] - A->w[i]; }
    double Dl = norm3(dv), Da = norm3(dw);
    cross3(A->w, B->w, x);
    double X = norm3(x);
    /* beta of the time-optimal S-curve for the leading terms: (1 - beta) T >= Acc,
     * beta (1 - beta) T^2 >= Jrk */
    double Acc = hi2(Dl / L->acc[0], Da / L->acc[1]);
    double Jrk = hi2(L->jerk[0] > 0 ? Dl / L->jerk[0] : 0.0, L->jerk[1] > 0 ? Da / L->jerk[1] : 0.0);
    double b;
    if (L->jerk[0] <= 0 && L->jerk[1] <= 0) b = BETA_FREE;
    else if (Acc * Acc >= Jrk) b = Acc > 0 ? (Jrk / Acc) / (Acc + Jrk / Acc) : 0.5;
    else b = 0.5;
    b = lo2(0.5, hi2(b, 1e-3));
    double h = 1.0 / (1.0 - b);
    double kA = A->kappa, kB = B->kappa;
    double xs[4] = {
        x_max(0.0, h * Dl, 0.5 * h * (kA + kB) + hi2(kA, kB), L->acc[0]),
        x_max(0.0, h * Da, 0.25 * X, L->acc[1]),
        L->jerk[0] > 0 ? x_max(h / b * Dl, h * (3.0 + 0.5 / b) * (kA + kB),
                               hi2(A->nus * kA, B->nus * kB), L->jerk[0]) : INFINITY,
        L->jerk[1] > 0 ? x_max(h / b * Da, 2.0 * h * X, 4.0 / 27.0 * X * hi2(A->spin, B->spin),
                               L->jerk[1]) : INFINITY,
    };
    static const int names[4] = {DQ_BIND_LIN_ACC, DQ_BIND_ANG_ACC, DQ_BIND_LIN_JERK,
                                 DQ_BIND_ANG_JERK};
    double xm = INFINITY;
    int k = 0;
    for (int i = 0; i < 4; i++) {
        if (xs[i] < 0) return -1;
        if (xs[i] < xm) { xm = xs[i]; k = i; }
    }
    *T = isinf(xm) ? 0.0 : 1.0 / xm;
    *beta = b;
    *bind = names[k];
    return 0;
}

/* ---- the planner ----------------------------------------------------------------------------- */

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
        side A = side_of(&c->seg[k - 1], sa, 1), B = side_of(&c->seg[k], sb, 0);
        int bd = 0, rc = ramp(&A, &B, c->L, &m[2], &m[3], &bd);
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
    side S0 = side_of(g, si, 0), S1 = side_of(g, s, 0), S2 = side_of(g, s, 1), S3 = side_of(g, so, 1);
    if (ramp(&S0, &S1, c->L, &T[1], &B[1], &b1) < 0) return -1;
    if (ramp(&S2, &S3, c->L, &T[3], &B[3], &b3) < 0) return -1;
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
    for (int it = 0; it < BISECT && hi - lo > 1e-9 && glo < -1e-9; it++) {
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

/* ---- split segments: translation and rotation on their own time laws ----------------------- */

/* The ramp of a rest-to-rest 1-D S-curve from rate 0 to V under acceleration a and jerk j
 * (0: none; the ramp then keeps jerk phases of BETA_FREE): its duration T and jerk fraction
 * beta, with peak acceleration h V / T <= a and jerk h V / (beta T^2) <= j, time-optimal. */
static void rest_ramp(double V, double a, double j, double *T, double *beta)
{
    if (!(j > 0.0)) { *beta = BETA_FREE; *T = V / (a * (1.0 - BETA_FREE)); }
    else if (V * j >= a * a) { *T = V / a + a / j; *beta = (a / j) / *T; }
    else { *T = 2.0 * sqrt(V / j); *beta = 0.5; }
}

/* A rest-to-rest law over s in [0, 1] ramping to cruise rate V: its duration (ramp, cruise,
 * ramp; the ramps cover V T_ramp of s). */
static double rest_duration(double V, double a, double j)
{
    double T, b;
    rest_ramp(V, a, j, &T, &b);
    return T + 1.0 / V;
}

/* The 1-D time-optimal rest-to-rest law over s in [0, 1] under v, a, j (per unit s): its cruise
 * rate (v, or the largest whose two ramps fit in s = 1) and the limit that decides it. */
static double rest_top(double v, double a, double j, const int names[3], int *bind)
{
    double V;
    if (!(j > 0.0)) V = sqrt(a * (1.0 - BETA_FREE));          /* V T_ramp(V) = 1 */
    else if (cbrt(j / 4.0) * j <= a * a) V = cbrt(j / 4.0); /* triangular acceleration */
    else { double q = a * a / j; V = 0.5 * (sqrt(q * q + 4.0 * a) - q); }
    *bind = v <= V ? names[0] : (j > 0.0 && V * j < a * a) ? names[2] : names[1];
    return lo2(v, V);
}

/* law: s from 0 to 1 at rest at both ends in exactly Tgoal (>= rest_duration(Vtop)), each
 * ramp time-optimal for its cruise rate: the cruise rate is lowered (bisection; the duration
 * falls as it rises) to the largest whose law is no longer than Tgoal, then the cruise is
 * lengthened to Tgoal, so the rate, hence every peak, is at most that law's. */
static void rest_law(double Vtop, double a, double j, double Tgoal, dq_traj_law *law)
{
    double V = Vtop;
    if (rest_duration(V, a, j) < Tgoal) {
        double lo = 1.0 / Tgoal; /* rest_duration(lo) >= Tgoal */
        for (int it = 0; it < 2 * BISECT; it++) {
            double mid = 0.5 * (lo + V);
            if (rest_duration(mid, a, j) <= Tgoal) V = mid; else lo = mid;
        }
    }
    double Tr, b;
    rest_ramp(V, a, j, &Tr, &b);
    double cruise = hi2(0.0, Tgoal - 2.0 * Tr), r = 1.0 / (Tr + cruise);
    const double T[5] = {0.0, Tr, cruise, Tr, 0.0}, rate[6] = {0.0, 0.0, r, r, 0.0, 0.0};
    for (int i = 0; i < 5; i++) { law->T[i] = T[i]; law->beta[i] = i == 1 || i == 3 ? b : 0.5; }
    memcpy(law->rate, rate, sizeof rate);
}

/* What evaluating a law needs: phase starts in t and s, and what the ramp shape divides by. */
static void law_finish(dq_traj_law *law)
{
    law->t_at[0] = law->s_at[0] = 0.0;
    for (int i = 0; i < 5; i++) {
        law->h[i] = 1.0 / (1.0 - law->beta[i]);
        law->inv_beta[i] = 1.0 / law->beta[i];
        law->inv_T[i] = law->T[i] > 0 ? 1.0 / law->T[i] : 0.0;
        law->t_at[i + 1] = law->t_at[i] + law->T[i];
        law->s_at[i + 1] = law->s_at[i] + 0.5 * (law->rate[i] + law->rate[i + 1]) * law->T[i];
    }
}

/* A split segment's two laws, both as long as the slower one at full speed over lam (lam < 1:
 * slowed for a waypoint time). On the line the tool point's velocity is dp ds/dt and the tool's
 * theta axis ds'/dt, so each 1-D law within its own limits (per unit s: the limit over the
 * distance) is exactly within them. */
static void split_laws(dq_traj_seg *g, const dq_traj_limits *L, double lam)
{
    static const int lin[3] = {DQ_BIND_LIN_VEL, DQ_BIND_LIN_ACC, DQ_BIND_LIN_JERK};
    static const int ang[3] = {DQ_BIND_ANG_VEL, DQ_BIND_ANG_ACC, DQ_BIND_ANG_JERK};
    double D[2] = {g->len, g->theta}, V[2] = {0.0, 0.0}, Tmin[2] = {0.0, 0.0};
    int bind[2] = {DQ_BIND_LIN_VEL, DQ_BIND_ANG_VEL};
    for (int m = 0; m < 2; m++) {
        if (!(D[m] > 0.0)) continue;
        V[m] = rest_top(L->vel[m] / D[m], L->acc[m] / D[m], L->jerk[m] / D[m], m ? ang : lin, &bind[m]);
        Tmin[m] = rest_duration(V[m], L->acc[m] / D[m], L->jerk[m] / D[m]);
    }
    int slow = Tmin[1] > Tmin[0];
    double T = Tmin[slow] / lam;
    dq_traj_law *out[2] = {&g->law, &g->turn};
    for (int m = 0; m < 2; m++)
        if (D[m] > 0.0) rest_law(V[m], L->acc[m] / D[m], L->jerk[m] / D[m], T, out[m]);
    /* no distance to go: that part is still, the one law serves both (evaluated once) */
    if (!(D[0] > 0.0)) g->law = g->turn;
    g->split = D[0] > 0.0 && D[1] > 0.0;
    law_finish(&g->law);
    if (g->split) law_finish(&g->turn);
    g->sigma = g->law.rate[2];
    g->bind = lam < 1.0 ? DQ_BIND_TIME : bind[slow];
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
            split_laws(g, c->L, lam[k]);
        } else {
            double covered = phases(c, k, g->sigma, g->sig_in, g->sig_out, g->law.T, g->law.beta,
                                    g->law.rate, &bind);
            g->law.T[2] = hi2(0.0, (1.0 - covered) / g->sigma);
            law_finish(&g->law);
        }
        if (k > 0) {
            const dq_traj_seg *p = &c->seg[k - 1];
            t = p->start + (g->blend_in ? p->law.t_at[4] : p->law.t_at[5]); /* a blend overlaps phase 4 */
        }
        g->start = t;
    }
    return DQ_OK;
}

static double seg_duration(const dq_traj_seg *g) { return g->law.t_at[5]; }

/* When waypoint m (>= 1) is reached: the end of a stop, the middle of a blend. */
static double arrival(const plan_ctx *c, size_t m)
{
    if (m == c->n) return c->seg[m - 1].start + seg_duration(&c->seg[m - 1]);
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
            for (int it = 0; it < BISECT && !rc && fabs(last) > 0.1 * tol; it++) {
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

/* ---- dense evaluation ------------------------------------------------------------------------
 * Sorted times fall in runs that share a segment, a blend state and a phase of each time law,
 * so everything but the times is a loop invariant: a run's poses are evaluated side by side
 * (each law's s, then the poses with the vector sin/cos of vecmath.h), which GCC vectorises,
 * instead of a search, a branchy law and two libm calls per pose and segment. Unsorted times
 * make runs of one pose and the same answers. */

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
            double qend = blend_in ? seg[k - 1].start + seg_duration(&seg[k - 1]) : 0.0;
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
