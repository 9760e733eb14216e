/*
 * linalg6.h — the dense linear algebra of the fusion, in pure C99: Cholesky factors and
 * triangular solves of symmetric positive definite matrices, 6 x 6 (SE(3) covariances and
 * informations, unrolled for the size) and dim x dim (the constant-twist fit's normal equations).
 *
 * Matrices are row-major. A factor L is lower triangular (its upper triangle is never read) and
 * comes with di = 1 / diag(L), which the solves multiply by. The "whitened" forms are L^-1 times
 * a Jacobian of the block shape of Jl^-1, [[J, 0], [M, J]] (se3.h), whose zero block is kept zero.
 * A Gram sum G += B^T B fills G's upper triangle; dq_mirror6 / dq_mirror copy it to the lower.
 */
#ifndef DQPOSE_LINALG6_H
#define DQPOSE_LINALG6_H

/* |e|^2 of a 6-vector (a whitened residual's cost, a NIS). */
static inline double dq_sq6(const double *e)
{
    return e[0] * e[0] + e[1] * e[1] + e[2] * e[2] + e[3] * e[3] + e[4] * e[4] + e[5] * e[5];
}

/* A = L L^T from the lower triangle of the m x m A (L's upper triangle is left as it was), and
 * di; 0 when a pivot is not positive (or not finite). dq_chol6: m = 6. */
int dq_chol(const double *A, double *L, double *di, int m);
int dq_chol6(const double *A, double *L, double *di);

/* x = L^-1 b and x = L^-T b, for an m x m L (dq_lower_solve6 / dq_upper_solve6: 6 x 6); x may
 * alias b. */
void dq_lower_solve(const double *L, const double *di, const double *b, double *x, int m);
void dq_upper_solve(const double *L, const double *di, const double *b, double *x, int m);
void dq_lower_solve6(const double *L, const double *di, const double *b, double *x);
void dq_upper_solve6(const double *L, const double *di, const double *b, double *x);

/* B = L^-1 M for a 6 x 6 M. */
void dq_lower_solve_matrix6(const double *L, const double *di, const double *M, double *B);
/* B = L^-1 A for A = Jl^-1 = [[J, 0], [M, J]]: B's upper-right 3 x 3 block stays zero. */
void dq_whiten_jacobian6(const double *L, const double *di, const double *A, double *B);

/* G += B^T B into G's upper triangle; the _whitened form skips the zeros of a B from
 * dq_whiten_jacobian6 (its first three rows end in zeros). */
void dq_add_gram6(const double *B, double *G);
void dq_add_gram_whitened6(const double *B, double *G);
/* G = B^T B into G's upper triangle for a B of `rows` rows stored by columns (column c at
 * B + stride c): the information of many stacked Jacobians in one pass of contiguous dot
 * products, which vectorise where a sum per measurement's 6 rows does not. The columns of
 * translations, c < se3 with c mod 6 >= 3, are zero in their first `zero` rows (the stacked
 * rows 0-2 of whitened Jacobians, dq_whiten_jacobian6's zero block) and are summed without
 * them. With g, column dim is the stacked residual e and g = B^T e over the dim columns. */
void dq_gram_columns(const double *B, int rows, int stride, int dim, int se3, int zero,
                     double *G, double *g);
/* The upper triangle copied to the lower. */
void dq_mirror6(double *G);
void dq_mirror(double *M, int dim);

/* DQ_LANES problems of one size side by side, entry k of lane l at [DQ_LANES * k + l]: A's
 * m x m lower triangle factored (L, di as dq_chol's) and y made L^-1 y in place, *yy = |y|^2
 * summed from entry 0 up, each lane the same operations in the same order as dq_chol,
 * dq_lower_solve and that sum on its own problem (so the same bits), the lanes computed together
 * (vector registers, AVX2 where the CPU has it). Returns 0 when a lane's A is not positive
 * definite (its outputs are then not meaningful). */
#define DQ_LANES 4
int dq_chol_solve_lanes(const double *A, int m, double *L, double *di, double *y, double *yy);
/* dq_whiten_jacobian6 of DQ_LANES problems side by side, laid out as above (where DQ_V4). */
void dq_whiten_jacobian6_lanes(const double *L, const double *di, const double *A, double *B);

/* P = A^-1 = L^-T L^-1 from A's 6 x 6 Cholesky factor, symmetric by construction. */
void dq_chol6_inverse(const double *L, const double *di, double *P);

/* P = H^-1 for a symmetric positive definite dim x dim H (its lower triangle read), from its
 * Cholesky factor, exactly symmetric; 0 when H is not positive definite. work: dim^2 + 2 dim. */
int dq_spd_inverse(const double *H, int dim, double *work, double *P);

#endif
