/*
 * traj_law.c — the time laws of the planned segments (traj_law.h): the ramp between two
 * rates sized by the bounds below, and the 1-D time-optimal S-curves of a split segment.
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
#include "traj_law.h"

#include <math.h>
#include <string.h>

#include "vecmath.h"

/* With no jerk limit the ramps still get jerk phases, so the acceleration stays continuous (C2
 * position); this fraction of the ramp costs at most 5 % of its time. */
#define BETA_FREE 0.05

/* Largest x = 1/T with c2 x^2 + c1 x + c0 <= lim; -1 when c0 leaves no room, INFINITY when
 * nothing depends on x. */
static double x_max(double c2, double c1, double c0, double lim)
{
    double r = lim - c0;
    if (!(r > 0.0)) return -1.0;
    double den = c1 + sqrt(c1 * c1 + 4.0 * c2 * r);
    return den > 0.0 ? 2.0 * r / den : INFINITY;
}

int dq_traj_ramp(const dq_traj_side *A, const dq_traj_side *B, const dq_traj_limits *L, double *T,
                 double *beta, int *bind)
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
        for (int it = 0; it < 2 * DQ_TRAJ_BISECT; it++) {
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

void dq_traj_law_finish(dq_traj_law *law)
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

void dq_traj_split_laws(dq_traj_seg *g, const dq_traj_limits *L, double lam)
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
    dq_traj_law_finish(&g->law);
    if (g->split) dq_traj_law_finish(&g->turn);
    g->sigma = g->law.rate[2];
    g->bind = lam < 1.0 ? DQ_BIND_TIME : bind[slow];
}
