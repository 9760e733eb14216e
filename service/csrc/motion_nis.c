/*
 * motion_nis.c — the constant-twist fit's leave-one-out NIS (fusion.h), each measurement's
 * without its own information, four measurements side by side (motion_work.h).
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
int motion_leave_one_out(const dq_motion_model *m, const double *V, const double *ell,
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
