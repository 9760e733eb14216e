/*
 * motion_rows.c — the constant-twist fit's per-measurement terms (motion_work.h): the priors'
 * cost and information, each measurement's residual, whitened residual and compact Jacobian,
 * four at a time where they can be, and the information and gradient they sum to.
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "dq.h"
#include "gn.h"
#include "linalg6.h"
#include "motion_work.h"
#include "se3.h"
#include "vecmath.h"

double motion_prior_cost(const dq_motion_model *m, const double *V, const double *ell)
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
void motion_prior_terms(const dq_motion_model *m, const double *V, const double *ell,
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
double motion_evaluate(const double *X, const double *V, const double *ell,
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
void motion_jacobian(const dq_motion_model *m, const double *V, size_t i, double *blk,
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
void motion_information(const dq_motion_model *m, size_t i, const double *Gw, double *t)
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

/* M += measurement i's information from its terms t (motion_information), M the upper triangle
 * packed by rows. */
void motion_add_information(const dq_motion_model *m, size_t i,
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
void motion_linearize(const dq_motion_model *m, const double *V, double *work,
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
