/*
 * motion_work.h — what motion.c, motion_rows.c and motion_nis.c share of the constant-twist fit
 * (motion.h): the workspace's layout and the functions over its per-measurement blocks.
 */
#ifndef DQPOSE_MOTION_WORK_H
#define DQPOSE_MOTION_WORK_H

#include <stddef.h>

#include "motion.h"

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

/* Where the selected measurements' L^-1 G_i are stacked by state column (6 n rows a column,
 * motion_linearize): after the blocks and the solver's arrays. */
static inline double *motion_columns(double *work, size_t stride, size_t n, int dim)
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

/* Where the upper triangle's (a, b), a <= b, of a dim x dim matrix is packed by rows. */
static inline int motion_packed(int dim, int a, int b) { return a * dim - a * (a - 1) / 2 + b - a; }

double motion_prior_cost(const dq_motion_model *m, const double *V, const double *ell);
void motion_prior_terms(const dq_motion_model *m, const double *V, const double *ell,
                        int dim, double *H, double *g);
double motion_evaluate(const double *X, const double *V, const double *ell,
                       const double *z, const dq_motion_model *m, double *work,
                       size_t stride, size_t n, const unsigned char *use, int want, int so);
void motion_jacobian(const dq_motion_model *m, const double *V, size_t i, double *blk,
                     int so, int dim, double *Gout, double *top, double *bottom,
                     size_t cs);
void motion_information(const dq_motion_model *m, size_t i, const double *Gw, double *t);
void motion_add_information(const dq_motion_model *m, size_t i,
                            const double *restrict t, int dim, double *restrict M);
void motion_linearize(const dq_motion_model *m, const double *V, double *work,
                      size_t stride, size_t n, const unsigned char *use, int all, int so,
                      int dim, double *H, double *g, double *G);
int motion_leave_one_out(const dq_motion_model *m, const double *V, const double *ell,
                         double *work, size_t stride, size_t n, const unsigned char *use,
                         const unsigned char *tested, int so, int dim, const double *H,
                         double *scratch, double *nis);

#endif
