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
#include "se3.h"
#include "vecmath.h"

/* A measurement's Jacobian is kept compact: MC columns, the pose's 6, the twist's 6 and its own
 * latency's 1 (zero columns when the twist or the latency is not estimated). */
#define MC 13

/* The motion workspace: a block per measurement (its covariance factor L and DI, its whitened
 * compact Jacobian L^-1 G, two slots of r, e = L^-1 r, sin^2 and cos of half r's angle,
 * Exp(dt V) and dt, for the current and a trial estimate), then the solver's dim-sized arrays. */
enum { M_L = 0, M_DI = 36, M_G = 42, M_S0 = 120, M_S1 = 143, M_PER = 166 };
/* With the leave-one-out NIS a block goes on: its information's terms (MI at most, the upper
 * triangle of MC columns), then the prefix sum of the earlier inliers' information (its upper
 * triangle packed by rows, dim (dim + 1) / 2). */
enum { MI = MC * (MC + 1) / 2, M_INFO = M_PER, M_HJ = M_PER + MI };
enum { S_R = 0, S_E = 6, S_SC = 12, S_EXP = 14, S_DT = 22 };

size_t dq_motion_dim(const dq_motion_model *m) { return (m->twist ? 12 : 6) + m->k; }

size_t dq_motion_workspace(size_t n, const dq_motion_model *m)
{
    size_t dim = dq_motion_dim(m);
    return (M_HJ + dim * (dim + 1) / 2) * n + 5 * dim * dim + 7 * dim + 6 * (dim + 1) * n +
           (2 * dim * dim + 2 * dim) * DQ_LANES;
}

/* Where the selected measurements' L^-1 G_i are stacked by state column (6 n rows a column,
 * motion_linearize): after the blocks and the solver's arrays. */
static double *motion_columns(double *work, size_t stride, size_t n, int dim)
{
    return work + stride * n + 5 * (size_t)dim * dim + 7 * (size_t)dim;
}

/* The state index of compact column c of measurement i (-1: not in the state). */
static inline int motion_column(const dq_motion_model *m, size_t i, int c)
{
    if (c < 6) return c;
    if (c < 12) return m->twist ? c : -1;
    return m->slot[i] >= 0 ? (m->twist ? 12 : 6) + (int)m->slot[i] : -1;
}

static double motion_prior_cost(const dq_motion_model *m, const double *V, const double *ell)
{
    double c = 0.0;
    for (size_t j = 0; j < m->k; j++) c += m->prior_w[j] * (ell[j] - m->prior[j]) * (ell[j] - m->prior[j]);
    if (m->twist && m->twist_w) {
        double q = 0.0;
        for (int a = 0; a < 6; a++) {
            double s = 0.0;
            for (int b = 0; b < 6; b++) s += m->twist_w[6 * a + b] * V[b];
            q += V[a] * s;
        }
        c += q;
    }
    return c;
}

/* H += the priors' information, g += their part of the descent direction. */
static void motion_prior_terms(const dq_motion_model *m, const double *V, const double *ell,
                               int dim, double *H, double *g)
{
    if (m->twist && m->twist_w)
        for (int a = 0; a < 6; a++) {
            double s = 0.0;
            for (int b = 0; b < 6; b++) {
                H[dim * (6 + a) + 6 + b] += m->twist_w[6 * a + b];
                s += m->twist_w[6 * a + b] * V[b];
            }
            g[6 + a] -= s;
        }
    int off = m->twist ? 12 : 6;
    for (size_t j = 0; j < m->k; j++) {
        H[dim * (off + (int)j) + off + (int)j] += m->prior_w[j];
        g[off + (int)j] -= m->prior_w[j] * (ell[j] - m->prior[j]);
    }
}

/* One measurement's evaluation (motion_evaluate) at (X, V) and its dt, into slot so of blk. */
static void motion_evaluate_one(const double *X, const double *V, double dt, const double *z,
                                double *blk, int so)
{
    double *s = blk + so;
    double h[6], P[8], Pc[8];
    for (int k = 0; k < 6; k++) h[k] = 0.5 * (dt * V[k]);
    dq_exp(h, s + S_EXP);
    dq_mul(X, s + S_EXP, P);
    dq_conj(P, Pc);
    dq_se3_residual(Pc, z, s + S_R, s + S_SC);
    dq_lower_solve6(blk + M_L, blk + M_DI, s + S_R, s + S_E);
    s[S_DT] = dt;
}

#if DQ_V4
/* motion_evaluate_one of the measurements rows[0..DQ_LANES) side by side, each lane the same
 * operations (dq.h's lanes, then dq_se3_residual's and dq_lower_solve6's), so the same bits; 0,
 * nothing written, when a rotation is beyond the lanes' series. */
DQ_CLONES static int motion_evaluate_lanes(const double *X, const double *V, const double *dt,
                                           const double *z, const size_t *rows, double *work,
                                           size_t stride, int so)
{
    enum { W = DQ_LANES };
    double h[6 * W], E[8 * W], Xl[8 * W], P[8 * W], zl[8 * W], p[8 * W], lg[6 * W];
    for (int l = 0; l < W; l++) {
        for (int k = 0; k < 6; k++) h[W * k + l] = 0.5 * (dt[l] * V[k]);
        for (int k = 0; k < 8; k++) {
            Xl[W * k + l] = X[k];
            zl[W * k + l] = z[8 * rows[l] + k];
        }
    }
    if (!dq_exp_lanes(h, E)) return 0;
    dq_mul_lanes(Xl, E, P);
    for (int k = 0; k < 8 * W; k++)   /* dq_conj */
        if (k / W != 0 && k / W != 4) P[k] = -P[k];
    dq_mul_lanes(P, zl, p);
    for (int l = 0; l < W; l++)   /* dq_se3_residual's */
        if (p[l] < 0.0)
            for (int k = 0; k < 8; k++) p[W * k + l] = -p[W * k + l];
    if (!dq_log_lanes(p, lg)) return 0;
    dq_v4 r[6], e[6];
    for (int k = 0; k < 6; k++) r[k] = 2.0 * dq_v4_load(lg + W * k);
    for (int i = 0; i < 6; i++) {   /* dq_lower_solve6's */
        double Li[6 * W], di[W];
        for (int l = 0; l < W; l++) {
            const double *blk = work + stride * rows[l];
            for (int k = 0; k < i; k++) Li[W * k + l] = blk[M_L + 6 * i + k];
            di[l] = blk[M_DI + i];
        }
        dq_v4 acc = r[i];
        for (int k = 0; k < i; k++) acc -= dq_v4_load(Li + W * k) * e[k];
        e[i] = acc * dq_v4_load(di);
    }
    for (int l = 0; l < W; l++) {
        double *s = work + stride * rows[l] + so;
        for (int k = 0; k < 8; k++) s[S_EXP + k] = E[W * k + l];
        for (int k = 0; k < 6; k++) {
            s[S_R + k] = r[k][l];
            s[S_E + k] = e[k][l];
        }
        s[S_SC] = p[W + l] * p[W + l] + p[2 * W + l] * p[2 * W + l] + p[3 * W + l] * p[3 * W + l];
        s[S_SC + 1] = p[l];
        s[S_DT] = dt[l];
    }
    return 1;
}
#endif

/* Residuals and whitened residuals at (X, V, ell) of the measurements `use` selects (want = 1)
 * or the others (want = 0), into slot so of their blocks (DQ_LANES at a time where they can
 * be); returns their cost. */
static double motion_evaluate(const double *X, const double *V, const double *ell,
                              const double *z, const dq_motion_model *m, double *work,
                              size_t stride, size_t n, const unsigned char *use, int want, int so)
{
    size_t rows[DQ_LANES];
    double dts[DQ_LANES];
    int count = 0;
    for (size_t i = 0; i < n; i++) {
        if (dq_selected(use, i) != want) continue;
        double dt = m->stamp[i] - (m->slot[i] >= 0 ? ell[m->slot[i]] : m->latency[i]);
        rows[count] = i;
        dts[count++] = dt;
        if (count < DQ_LANES) continue;
#if DQ_V4
        if (motion_evaluate_lanes(X, V, dts, z, rows, work, stride, so)) {
            count = 0;
            continue;
        }
#endif
        for (int l = 0; l < DQ_LANES; l++)
            motion_evaluate_one(X, V, dts[l], z + 8 * rows[l], work + stride * rows[l], so);
        count = 0;
    }
    for (int l = 0; l < count; l++)
        motion_evaluate_one(X, V, dts[l], z + 8 * rows[l], work + stride * rows[l], so);
    double total = 0.0;
    for (size_t i = 0; i < n; i++)
        if (dq_selected(use, i) == want) total += dq_sq6(work + stride * i + so + S_E);
    return total;
}

/* Measurement i's Jacobian from slot so: L^-1 G_i compact into its block, or with top its
 * pose's and twist's columns into the stacked columns of motion_linearize instead (rows 0-2
 * from top, rows 3-5 from bottom, column c at c * cs: for a measurement whose latency is not
 * estimated, when the block is not read again), and G_i itself (6 x dim) into Gout when not
 * NULL. */
static void motion_jacobian(const dq_motion_model *m, const double *V, size_t i, double *blk,
                            int so, int dim, double *Gout, double *top, double *bottom,
                            size_t cs)
{
    const double *s = blk + so, *E = s + S_EXP;
    double dt = s[S_DT];
    double A[36], Aw[36], Bc[6 * MC], Ei[8], Ad[36];
    dq_jl_inv(s + S_R, s[S_SC], s[S_SC + 1], A);
    dq_whiten_jacobian6(blk + M_L, blk + M_DI, A, Aw);
    dq_conj(E, Ei);
    dq_adjoint(Ei, Ad);   /* Ad(Exp(-dt V)) */
    for (int a = 0; a < 6; a++)
        for (int b = 0; b < 6; b++) Bc[MC * a + b] = Ad[6 * a + b];
    if (m->twist) {
        double x[6];
        for (int k = 0; k < 6; k++) x[k] = dt * V[k];
        dq_jr_scaled(x, E[1] * E[1] + E[2] * E[2] + E[3] * E[3], E[0], dt, Bc + 6, MC);
    } else {
        for (int a = 0; a < 6; a++)
            for (int b = 6; b < 12; b++) Bc[MC * a + b] = 0.0;
    }
    for (int a = 0; a < 6; a++) Bc[MC * a + 12] = m->slot[i] >= 0 ? -V[a] : 0.0;
    /* Aw and the pose's and twist's blocks of Bc are [[., 0], [., .]] by 3 x 3 blocks (exact
     * zeros): the sums leave out the products that are zero, so they are the full sums to the
     * bit at half the cost. */
    double *Gw = blk + M_G;
    size_t rs = 1;
    if (!top) {
        top = Gw;
        bottom = Gw + 3 * MC;
        rs = MC;
        cs = 1;
        for (int a = 0; a < 6; a++) {
            double sw = 0.0;
            if (m->slot[i] >= 0)
                for (int k = 0; k < 6; k++) sw += Aw[6 * a + k] * Bc[MC * k + 12];
            Gw[MC * a + 12] = sw;
        }
    }
    for (int b = 0; b < 12; b += 6) {
        for (int c = b; c < b + 3; c++) {
            for (int a = 0; a < 3; a++) {   /* Aw's rows 0-2: zero beyond column 2 */
                double sw = 0.0;
                for (int k = 0; k < 3; k++) sw += Aw[6 * a + k] * Bc[MC * k + c];
                top[rs * a + cs * c] = sw;
            }
            for (int a = 3; a < 6; a++) {
                double sw = 0.0;
                for (int k = 0; k < 6; k++) sw += Aw[6 * a + k] * Bc[MC * k + c];
                bottom[rs * (a - 3) + cs * c] = sw;
            }
        }
        for (int c = b + 3; c < b + 6; c++) {   /* zero in Bc's rows 0-2 */
            for (int a = 0; a < 3; a++) top[rs * a + cs * c] = 0.0;
            for (int a = 3; a < 6; a++) {
                double sw = 0.0;
                for (int k = 3; k < 6; k++) sw += Aw[6 * a + k] * Bc[MC * k + c];
                bottom[rs * (a - 3) + cs * c] = sw;
            }
        }
    }
    if (Gout) {
        for (int a = 0; a < 6 * dim; a++) Gout[a] = 0.0;
        for (int c = 0; c < MC; c++) {
            int col = motion_column(m, i, c);
            if (col < 0) continue;
            for (int a = 0; a < 6; a++) {
                double sg = 0.0;
                for (int k = 0; k < 6; k++) sg += A[6 * a + k] * Bc[MC * k + c];
                Gout[dim * a + col] = sg;
            }
        }
    }
}

#if DQ_V4
/* motion_jacobian's L^-1 G_i of the measurements rows[0..DQ_LANES), all of the common case (a
 * twist, no latency estimated), side by side, into the stacked columns of motion_linearize (rows
 * 0-2 at cols + at[l], rows 3-5 at cols + half + at[l], column c at c R): each the same operations
 * in the same order (se3.h's and linalg6.h's lane kernels, then motion_jacobian's products), so
 * the same bits. 0, nothing written, when a rotation is beyond the kernels' series. */
DQ_CLONES static int motion_jacobian_lanes(const double *V, const size_t *rows, const size_t *at,
                                           const double *work, size_t stride, int so,
                                           double *cols, size_t R, size_t half)
{
    enum { W = DQ_LANES };
    double r[6 * W], x[6 * W], dt[W], q[8 * W], A[36 * W], Aw[36 * W], L[36 * W], di[6 * W];
    double Ad[36 * W], Jr[36 * W];
    for (int l = 0; l < W; l++) {
        const double *blk = work + stride * rows[l], *s = blk + so, *E = s + S_EXP;
        dt[l] = s[S_DT];
        for (int k = 0; k < 6; k++) {
            r[W * k + l] = s[S_R + k];
            x[W * k + l] = dt[l] * V[k];
            di[W * k + l] = blk[M_DI + k];
        }
        for (int k = 0; k < 36; k++) L[W * k + l] = blk[M_L + k];
        for (int k = 0; k < 8; k++) q[W * k + l] = k == 0 || k == 4 ? E[k] : -E[k]; /* dq_conj */
    }
    if (!dq_jl_inv_lanes(r, A) || !dq_jr_scaled_lanes(x, dt, Jr)) return 0;
    dq_whiten_jacobian6_lanes(L, di, A, Aw);
    dq_adjoint_lanes(q, Ad);
#define AW(a, k) dq_v4_load(Aw + W * (6 * (a) + (k)))
#define BC(k, c) dq_v4_load(Bc + W * (6 * (k) + (c)))
    for (int b = 0; b < 12; b += 6) {
        const double *Bc = b ? Jr : Ad;   /* the columns b .. b + 5 of motion_jacobian's Bc */
        for (int c = 0; c < 6; c++) {
            dq_v4 top[3], bottom[3];
            for (int a = 0; a < 3; a++) {
                dq_v4 sw = dq_v4_of(0.0);
                if (c < 3)
                    for (int k = 0; k < 3; k++) sw += AW(a, k) * BC(k, c);
                top[a] = sw;   /* zero in Bc's rows 0-2 beyond column 2: the sum's +0 */
                sw = dq_v4_of(0.0);
                for (int k = c < 3 ? 0 : 3; k < 6; k++) sw += AW(a + 3, k) * BC(k, c);
                bottom[a] = sw;
            }
            double *to = cols + R * (size_t)(b + c);
            for (int l = 0; l < W; l++)
                for (int a = 0; a < 3; a++) {
                    to[at[l] + a] = top[a][l];
                    to[half + at[l] + a] = bottom[a][l];
                }
        }
    }
#undef AW
#undef BC
    return 1;
}
#endif

/* The terms of measurement i's information (L^-1 G_i)^T (L^-1 G_i), its upper triangle in the
 * state's columns, into t (at most MI) in the order motion_add_information adds them: computed
 * once for the two sums of the leave-one-out NIS. */
static void motion_information(const dq_motion_model *m, size_t i, const double *Gw, double *t)
{
    if (m->twist && m->slot[i] < 0) {
        /* the common case, the pose's and the twist's columns as they are: fixed bounds the
         * compiler unrolls (the same sums in the same order as below) */
        for (int a = 0, q = 0; a < 12; a++)
            for (int b = a; b < 12; b++) {
                double s = 0.0;
                for (int k = 0; k < 6; k++) s += Gw[MC * k + a] * Gw[MC * k + b];
                t[q++] = s;
            }
        return;
    }
    int cols[MC], nc = 0;
    for (int c = 0; c < MC; c++)
        if (motion_column(m, i, c) >= 0) cols[nc++] = c;
    for (int a = 0, q = 0; a < nc; a++)
        for (int b = a; b < nc; b++) {
            double s = 0.0;
            for (int k = 0; k < 6; k++) s += Gw[MC * k + cols[a]] * Gw[MC * k + cols[b]];
            t[q++] = s;
        }
}

/* Where the upper triangle's (a, b), a <= b, of a dim x dim matrix is packed by rows. */
static inline int motion_packed(int dim, int a, int b) { return a * dim - a * (a - 1) / 2 + b - a; }

/* M += measurement i's information from its terms t (motion_information), M the upper triangle
 * packed by rows. */
static void motion_add_information(const dq_motion_model *m, size_t i,
                                   const double *restrict t, int dim, double *restrict M)
{
    if (dim == 12 && m->twist && m->slot[i] < 0) {   /* the terms in M's packed order */
        for (int q = 0; q < 78; q++) M[q] += t[q];
        return;
    }
    int map[MC], nc = 0;
    for (int c = 0; c < MC; c++) {
        int col = motion_column(m, i, c);
        if (col >= 0) map[nc++] = col;
    }
    for (int a = 0, q = 0; a < nc; a++)
        for (int b = a; b < nc; b++) M[motion_packed(dim, map[a], map[b])] += t[q++];
}

/* The data's information H (upper triangle) and gradient g = sum (L^-1 G)^T e over `use`, from
 * slot so; the selected measurements' whitened Jacobians stacked by state column (below), the
 * others' (with all = 1) compact in their blocks, G_i written to G when not NULL. H and g come from one Gram pass over the
 * selected L^-1 G_i and e stacked by state column, e last (summed one measurement at a time,
 * the 6 x 12 products took a quarter of the fit's time): first every measurement's rows 0-2,
 * then its rows 3-5, so that the translations' columns, zero in rows 0-2, are summed over the
 * second half only. */
static void motion_linearize(const dq_motion_model *m, const double *V, double *work,
                             size_t stride, size_t n, const unsigned char *use, int all, int so,
                             int dim, double *H, double *g, double *G)
{
    double *cols = motion_columns(work, stride, n, dim);
    const size_t R = 6 * n;
    size_t half = 0, j = 0;
    for (size_t i = 0; i < n; i++) half += dq_selected(use, i) ? 3 : 0;
    /* the common case's inliers DQ_LANES at a time into their blocks, the first `done` of them */
    const int lanes = DQ_V4 && !G && m->twist;
    size_t done = 0, common = 0;
#if DQ_V4
    size_t rows[DQ_LANES], at[DQ_LANES], sel = 0;
    int count = 0;
    for (size_t i = 0; lanes && i < n; i++) {
        if (!dq_selected(use, i)) continue;
        sel += 3;
        if (m->slot[i] >= 0) continue;
        rows[count] = i;
        at[count++] = sel - 3;
        if (count < DQ_LANES) continue;
        if (!motion_jacobian_lanes(V, rows, at, work, stride, so, cols, R, half))
            for (int l = 0; l < DQ_LANES; l++)
                motion_jacobian(m, V, rows[l], work + stride * rows[l], so, dim, NULL,
                                cols + at[l], cols + half + at[l], R);
        done += DQ_LANES;
        count = 0;
    }
#endif
    for (size_t i = 0; i < n; i++) {
        int in = dq_selected(use, i);
        if (!in && !all) continue;
        double *blk = work + stride * i;
        /* taken: stacked by the lanes above; direct: straight into the stack (the
         * leave-one-out NIS read them there) */
        const int taken = lanes && in && m->slot[i] < 0 && common++ < done;
        const int direct = in && m->twist && m->slot[i] < 0 && !taken;
        if (!taken)
            motion_jacobian(m, V, i, blk, so, dim, G ? G + 6 * dim * i : NULL,
                            direct ? cols + j : NULL, direct ? cols + half + j : NULL, R);
        if (!in) continue;
        const double *Gw = blk + M_G, *e = blk + so + S_E;
        double *eto = cols + R * (size_t)dim + j;
        for (int k = 0; k < 3; k++) {
            eto[k] = e[k];
            eto[half + k] = e[k + 3];
        }
        for (int c = m->twist ? 12 : 6; c < dim; c++)    /* the latencies' columns */
            for (int k = 0; k < 3; k++)
                cols[R * (size_t)c + j + k] = cols[R * (size_t)c + half + j + k] = 0.0;
        if (!direct && !taken) {      /* from the block, through its column map */
            for (int c = 0; c < MC; c++) {
                int col = motion_column(m, i, c);
                if (col < 0) continue;
                double *at = cols + R * (size_t)col + j;
                for (int k = 0; k < 3; k++) {
                    at[k] = Gw[MC * k + c];
                    at[half + k] = Gw[MC * (k + 3) + c];
                }
            }
        }
        j += 3;
    }
    dq_gram_columns(cols, (int)(2 * half), (int)R, dim, m->twist ? 12 : 6, (int)half, H, g);
}

/* An inlier's L^-1 G_i compact (6 x MC, the columns in the state) from where motion_linearize
 * stacked it: rows 0-2 at j, rows 3-5 at half + j of each state column (R rows a column). */
static void motion_stacked(const dq_motion_model *m, size_t i, const double *cols, size_t R,
                           size_t half, size_t j, double *Gw)
{
    for (int c = 0; c < MC; c++) {
        int col = motion_column(m, i, c);
        if (col < 0) continue;
        const double *at = cols + R * (size_t)col + j;
        for (int k = 0; k < 3; k++) {
            Gw[MC * k + c] = at[k];
            Gw[MC * (k + 3) + c] = at[half + k];
        }
    }
}

/* Lane l of the inliers' Hj factored side by side (dq_chol_solve_lanes): measurement i's Hj, the
 * sum of its earlier inliers' information pre (the upper triangle, packed by rows) and its later
 * ones' acc (dim x dim, upper triangle), in its lower triangle (dq_mirror's copy of the upper),
 * its y = (L^-1 G_i)^T e and |e|^2 into ee. lanes: (2 dim^2 + 2 dim) DQ_LANES. */
static void motion_lane_load(const dq_motion_model *m, const double *blk, const double *Gw,
                             size_t i, int so, int dim, const double *acc, int l, double *lanes,
                             double *ee)
{
    enum { W = DQ_LANES };
    double *A = lanes, *y = lanes + W * (2 * dim * dim + dim);
    const double *pre = blk + M_HJ, *e = blk + so + S_E;
    for (int j = 0, q = 0; j < dim; j++)
        for (int k = j; k < dim; k++, q++) A[W * (dim * k + j) + l] = pre[q] + acc[q];
    ee[l] = dq_sq6(e);
    for (int k = 0; k < dim; k++) y[W * k + l] = 0.0;
    for (int c = 0; c < MC; c++) {
        int col = motion_column(m, i, c);
        if (col < 0) continue;
        double s = 0.0;
        for (int k = 0; k < 6; k++) s += Gw[MC * k + c] * e[k];
        y[W * col + l] = s;
    }
}

/* The NIS of the measurements rows[0..count) loaded into lanes 0..count-1 (a lane left over
 * solves the identity). */
static int motion_lanes_nis(const size_t *rows, int count, int dim, double *lanes,
                            const double *ee, double *nis)
{
    enum { W = DQ_LANES };
    double *A = lanes, *L = A + W * dim * dim, *di = L + W * dim * dim, *y = di + W * dim;
    double yy[W];
    for (int l = count; l < W; l++)
        for (int i = 0; i < dim; i++) {
            for (int j = 0; j <= i; j++) A[W * (dim * i + j) + l] = i == j ? 1.0 : 0.0;
            y[W * i + l] = 0.0;
        }
    if (!dq_chol_solve_lanes(A, dim, L, di, y, yy)) return DQ_E_SINGULAR;
    for (int l = 0; l < count; l++) nis[rows[l]] = ee[l] + yy[l];
    return DQ_OK;
}

/* Leave-one-out NIS (fusion.h) from the compact Jacobians and whitened residuals in slot so:
 * whitened, K_i = L G Hj^-1 G^T L^T, so an inlier's NIS is |e|^2 + |Lh^-1 (L^-1 G)^T e|^2 and an
 * outlier's e^T (I + (L^-1 G) H^-1 (L^-1 G)^T)^-1 e. Hj sums the priors and the other inliers'
 * information (earlier ones kept as prefix sums, later ones accumulated backwards), so a
 * dominant measurement does not cancel the others away. Each inlier's information is computed
 * once (motion_information) for both sums, and the inliers' Hj are factored DQ_LANES at a time;
 * H's factor, the same for every outlier, once. */
static int motion_leave_one_out(const dq_motion_model *m, const double *V, const double *ell,
                                double *work, size_t stride, size_t n, const unsigned char *use,
                                const unsigned char *tested, int so, int dim, const double *H,
                                double *scratch, double *nis)
{
    double *acc = scratch, *Hj = acc + dim * dim, *Lh = Hj + dim * dim, *dh = Lh + dim * dim;
    double *gz = dh + 2 * dim, Gw[6 * MC];
    const double *cols = motion_columns(work, stride, n, dim);
    const size_t R = 6 * n;
    double *lanes = motion_columns(work, stride, n, dim) + R * (size_t)(dim + 1);
    size_t half = 0, j = 0;
    for (size_t i = 0; i < n; i++) half += dq_selected(use, i) ? 3 : 0;
    const int np = dim * (dim + 1) / 2;   /* acc: the upper triangle packed by rows */
    for (int k = 0; k < dim * dim; k++) Hj[k] = 0.0;
    for (int k = 0; k < dim; k++) gz[k] = 0.0;
    motion_prior_terms(m, V, ell, dim, Hj, gz);
    for (int a = 0, q = 0; a < dim; a++)
        for (int b = a; b < dim; b++, q++) acc[q] = Hj[dim * a + b];
    for (size_t i = 0; i < n; i++) {
        double *blk = work + stride * i;
        memcpy(blk + M_HJ, acc, sizeof(double) * (size_t)np);
        if (dq_selected(use, i)) {
            motion_stacked(m, i, cols, R, half, j, Gw);
            j += 3;
            motion_information(m, i, Gw, blk + M_INFO);
            motion_add_information(m, i, blk + M_INFO, dim, acc);
        }
    }
    for (int k = 0; k < np; k++) acc[k] = 0.0; /* now the later inliers' */
    size_t pending[DQ_LANES];
    double ee[DQ_LANES];
    int count = 0, factored = 0;
    for (size_t jj = n; jj-- > 0;) {
        double *blk = work + stride * jj;
        int in = dq_selected(use, jj);
        const double *e = blk + so + S_E;
        if (in) {
            j -= 3;
            motion_stacked(m, jj, cols, R, half, j, Gw);
        }
        if (!tested[jj]) {
            nis[jj] = 0.0;
        } else if (in) {
            motion_lane_load(m, blk, Gw, jj, so, dim, acc, count, lanes, ee);
            pending[count++] = jj;
            if (count == DQ_LANES) {
                int rc = motion_lanes_nis(pending, count, dim, lanes, ee, nis);
                if (rc) return rc;
                count = 0;
            }
        } else {
            if (!factored) {
                for (int k = 0; k < dim * dim; k++) Hj[k] = H[k];
                dq_mirror(Hj, dim);
                if (!dq_chol(Hj, Lh, dh, dim)) return DQ_E_SINGULAR;
                factored = 1;
            }
            const double *Go = blk + M_G;   /* an outlier's, in its block */
            double K[36], N[36], dn[6], u[6];
            double *Yc = Hj; /* Y = Lh^-1 (L^-1 G)^T, 6 columns: Hj is spent */
            for (int a = 0; a < 6; a++) {
                double *col = Yc + dim * a;
                for (int k = 0; k < dim; k++) col[k] = 0.0;
                for (int c = 0; c < MC; c++) {
                    int s = motion_column(m, jj, c);
                    if (s >= 0) col[s] = Go[MC * a + c];
                }
                dq_lower_solve(Lh, dh, col, col, dim);
            }
            for (int a = 0; a < 6; a++)
                for (int b = 0; b < 6; b++) {
                    double s = 0.0;
                    for (int k = 0; k < dim; k++) s += Yc[dim * a + k] * Yc[dim * b + k];
                    K[6 * a + b] = s + (a == b ? 1.0 : 0.0);
                }
            if (!dq_chol6(K, N, dn)) return DQ_E_SINGULAR;
            dq_lower_solve6(N, dn, e, u);
            nis[jj] = dq_sq6(u);
        }
        if (in) motion_add_information(m, jj, blk + M_INFO, dim, acc);
    }
    return count ? motion_lanes_nis(pending, count, dim, lanes, ee, nis) : DQ_OK;
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
