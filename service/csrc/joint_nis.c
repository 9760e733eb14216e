/*
 * joint_nis.c — the leave-one-out NIS of the joint fit (joint.h): each tested measurement's
 * residual against the fit of the priors and the other inliers, from the whitened compact
 * Jacobians and residuals joint.c leaves in the workspace at the estimate.
 */
#include <string.h>

#include "dq.h"
#include "joint_ctx.h"
#include "linalg6.h"

/* M += measurement i's information (L^-1 G)^T (L^-1 G), upper triangle. */
static void joint_add_information(const joint_ctx *c, size_t i, int off, int twist, double *M)
{
    int map[JC], cols[JC], at[JC];
    joint_map(c, i, off, twist, map);
    const int nc = joint_present(map, cols, at), dim = c->dim;
    const double *Gw = c->blocks + J_PER * i + J_G;
    for (int a = 0; a < nc; a++)
        for (int bb = a; bb < nc; bb++) {
            double t = 0.0;
            for (int k = 0; k < 6; k++) t += Gw[JC * k + cols[a]] * Gw[JC * k + cols[bb]];
            M[dim * at[a] + at[bb]] += t;
        }
}

/* Each tested measurement's leave-one-out NIS (joint.h) from its whitened compact Jacobian and
 * residual, P and Pg = P g, at the estimate (V, L). An inlier's (I - K)^-1 is
 * I + (L^-1 G) Hj^-1 (L^-1 G)^T, Hj the information of the priors and the other inliers summed
 * (earlier ones kept as prefix sums in pre, N x dim^2, later ones accumulated backwards, as in
 * motion.c), so a measurement far surer than the rest does not cancel the others away; so its
 * NIS is |u|^2 + |Lh^-1 (L^-1 G)^T u|^2. scratch: 3 dim^2 + 2 dim. */
int joint_leave_one_out(const joint_ctx *c, const double *V, const double *L,
                        const double *P, const double *Pg, double *scratch, double *pre,
                        dq_taken *taken, const dq_joint_outputs *per)
{
    const dq_joint_model *m = c->m;
    const int dim = c->dim;
    const size_t D2 = (size_t)dim * dim;
    double *acc = scratch, *Hj = acc + D2, *Lh = Hj + D2, *dh = Lh + D2, *y = dh + dim;
    for (size_t k = 0; k < D2; k++) acc[k] = 0.0;
    for (int k = 0; k < dim; k++) y[k] = 0.0;
    joint_prior_terms(c, V, L, acc, y);
    size_t i = 0;
    int off = 0;
    for (size_t p = 0; p < m->parts; p++) {
        const dq_joint_part *pt = m->part + p;
        const dq_motion_model mm = {m->stamp + i, m->latency + i, NULL, 0, NULL, NULL,
                                    pt->twist, pt->twist_w};
        dq_motion_determined(&mm, c->inlier ? c->inlier + i : NULL, pt->n, taken,
                             per->tested + i);
        for (size_t j = 0; j < pt->n; j++, i++) {
            const int in = dq_selected(c->inlier, i);
            if (!in) per->tested[i] = 1;
            if (in && per->tested[i]) memcpy(pre + D2 * i, acc, D2 * sizeof(double));
            if (in) joint_add_information(c, i, off, pt->twist, acc);
        }
        off += pt->twist ? 12 : 6;
    }
    for (size_t k = 0; k < D2; k++) acc[k] = 0.0;   /* now the later inliers' */
    for (size_t p = m->parts; p-- > 0;) {
        const dq_joint_part *pt = m->part + p;
        off -= pt->twist ? 12 : 6;
        for (size_t j = pt->n; j-- > 0;) {
            i--;
            const int in = dq_selected(c->inlier, i);
            int map[JC], cols[JC], at[JC];
            joint_map(c, i, off, pt->twist, map);
            const int nc = joint_present(map, cols, at);
            const double *b = c->blocks + J_PER * i, *Gw = b + J_G, *e = b + J_E;
            if (!per->tested[i]) {
                per->nis[i] = 0.0;
            } else if (in) {
                double u[6];
                for (int a = 0; a < 6; a++) {
                    double s = 0.0;
                    for (int q = 0; q < nc; q++) s += Gw[JC * a + cols[q]] * Pg[at[q]];
                    u[a] = e[a] - s;
                }
                for (size_t k = 0; k < D2; k++) Hj[k] = pre[D2 * i + k] + acc[k];
                dq_mirror(Hj, dim);
                if (!dq_chol(Hj, Lh, dh, dim)) return DQ_E_SINGULAR;
                for (int k = 0; k < dim; k++) y[k] = 0.0;
                for (int q = 0; q < nc; q++) {
                    double s = 0.0;
                    for (int k = 0; k < 6; k++) s += Gw[JC * k + cols[q]] * u[k];
                    y[at[q]] = s;
                }
                dq_lower_solve(Lh, dh, y, y, dim);
                double nis = dq_sq6(u);
                for (int k = 0; k < dim; k++) nis += y[k] * y[k];
                per->nis[i] = nis;
            } else {   /* e^T (I + (L^-1 G) P (L^-1 G)^T)^-1 e */
                double T[6 * JC], M[36], N[36], dn[6], x[6];
                for (int a = 0; a < 6; a++)
                    for (int q = 0; q < nc; q++) {
                        double s = 0.0;
                        for (int k = 0; k < nc; k++)
                            s += Gw[JC * a + cols[k]] * P[dim * at[k] + at[q]];
                        T[JC * a + q] = s;
                    }
                for (int a = 0; a < 6; a++)
                    for (int bb = 0; bb < 6; bb++) {
                        double s = 0.0;
                        for (int q = 0; q < nc; q++) s += T[JC * a + q] * Gw[JC * bb + cols[q]];
                        M[6 * a + bb] = (a == bb ? 1.0 : 0.0) + s;
                    }
                if (!dq_chol6(M, N, dn)) return DQ_E_SINGULAR;
                dq_lower_solve6(N, dn, e, x);
                per->nis[i] = dq_sq6(x);
            }
            if (in) joint_add_information(c, i, off, pt->twist, acc);
        }
    }
    return DQ_OK;
}
