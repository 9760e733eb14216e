/*
 * linalg6.c — the Cholesky factors, triangular solves and Gram sums of linalg6.h.
 *
 * The general-size loops are static inline and called with a constant m = 6 by the 6 x 6 entry
 * points, so the compiler unrolls them there.
 */
#include "linalg6.h"

#include <math.h>
#include <stddef.h>

#include "vecmath.h"

static inline int chol_m(const double *A, double *L, double *di, int m)
{
    for (int j = 0; j < m; j++) {
        double d = A[m * j + j];
        for (int k = 0; k < j; k++) d -= L[m * j + k] * L[m * j + k];
        if (!(d > 0.0)) return 0; /* also NaN; an infinite pivot makes the result non-finite */
        double ljj = sqrt(d), inv = 1.0 / ljj;
        L[m * j + j] = ljj;
        di[j] = inv;
        for (int i = j + 1; i < m; i++) {
            double s = A[m * i + j];
            for (int k = 0; k < j; k++) s -= L[m * i + k] * L[m * j + k];
            L[m * i + j] = s * inv;
        }
    }
    return 1;
}

static inline void lower_solve_m(const double *L, const double *di, const double *b, double *x,
                                 int m)
{
    for (int i = 0; i < m; i++) {
        double s = b[i];
        for (int k = 0; k < i; k++) s -= L[m * i + k] * x[k];
        x[i] = s * di[i];
    }
}

static inline void upper_solve_m(const double *L, const double *di, const double *b, double *x,
                                 int m)
{
    for (int i = m - 1; i >= 0; i--) {
        double s = b[i];
        for (int k = i + 1; k < m; k++) s -= L[m * k + i] * x[k];
        x[i] = s * di[i];
    }
}

int dq_chol(const double *A, double *L, double *di, int m) { return chol_m(A, L, di, m); }
int dq_chol6(const double *A, double *L, double *di) { return chol_m(A, L, di, 6); }

void dq_lower_solve(const double *L, const double *di, const double *b, double *x, int m)
{
    lower_solve_m(L, di, b, x, m);
}

void dq_upper_solve(const double *L, const double *di, const double *b, double *x, int m)
{
    upper_solve_m(L, di, b, x, m);
}

void dq_lower_solve6(const double *L, const double *di, const double *b, double *x)
{
    lower_solve_m(L, di, b, x, 6);
}

void dq_upper_solve6(const double *L, const double *di, const double *b, double *x)
{
    upper_solve_m(L, di, b, x, 6);
}

/* Rows first..5 of B = D^-1 L^-1 M (rows before first already in B), row by row, each row a
 * whole 6-vector, which vectorises. */
static void lower_rows6(const double *L, const double *di, const double *M, double *restrict B,
                        int first)
{
    for (int i = first; i < 6; i++) {
        double row[6];
        for (int c = 0; c < 6; c++) row[c] = M[6 * i + c];
        for (int k = 0; k < i; k++) {
            double l = L[6 * i + k];
            for (int c = 0; c < 6; c++) row[c] -= l * B[6 * k + c];
        }
        for (int c = 0; c < 6; c++) B[6 * i + c] = row[c] * di[i];
    }
}

void dq_lower_solve_matrix6(const double *L, const double *di, const double *M,
                            double *restrict B)
{
    lower_rows6(L, di, M, B, 0);
}

void dq_whiten_jacobian6(const double *L, const double *di, const double *A, double *restrict B)
{
    for (int i = 0; i < 3; i++) {
        double row[3] = {A[6 * i], A[6 * i + 1], A[6 * i + 2]};
        for (int k = 0; k < i; k++) {
            double l = L[6 * i + k];
            for (int c = 0; c < 3; c++) row[c] -= l * B[6 * k + c];
        }
        for (int c = 0; c < 3; c++) B[6 * i + c] = row[c] * di[i];
        B[6 * i + 3] = B[6 * i + 4] = B[6 * i + 5] = 0.0;
    }
    lower_rows6(L, di, A, B, 3);
}

void dq_add_gram_whitened6(const double *restrict B, double *restrict G)
{
    for (int k = 0; k < 3; k++)
        for (int i = 0; i < 3; i++) {
            double b = B[6 * k + i];
            for (int j = i; j < 3; j++) G[6 * i + j] += b * B[6 * k + j];
        }
    for (int k = 3; k < 6; k++)
        for (int i = 0; i < 6; i++) {
            double b = B[6 * k + i];
            for (int j = i; j < 6; j++) G[6 * i + j] += b * B[6 * k + j];
        }
}

void dq_add_gram6(const double *restrict B, double *restrict G)
{
    for (int k = 0; k < 6; k++)
        for (int i = 0; i < 6; i++) {
            double b = B[6 * k + i];
            for (int j = i; j < 6; j++) G[6 * i + j] += b * B[6 * k + j];
        }
}

#if defined(__GNUC__)
typedef double dq_v2d __attribute__((vector_size(16), aligned(8)));
#endif

/* G[a][b], G[a][b+1] = x . y0, x . y1 over n rows: two columns share x's loads, and two partial
 * sums each (pairs of rows in a vector register where the compiler offers them) hide the
 * additions' latency; no -ffast-math, so a single running sum would stay scalar. */
static void dot_columns2(const double *restrict x, const double *restrict y0,
                         const double *restrict y1, int n, double *out)
{
    int r = 0;
    double s0 = 0.0, s1 = 0.0;
#if defined(__GNUC__)
    dq_v2d a0 = {0.0, 0.0}, a1 = {0.0, 0.0}, b0 = {0.0, 0.0}, b1 = {0.0, 0.0};
    for (; r + 4 <= n; r += 4) {
        dq_v2d xa = *(const dq_v2d *)(x + r), xb = *(const dq_v2d *)(x + r + 2);
        a0 += xa * *(const dq_v2d *)(y0 + r);
        a1 += xb * *(const dq_v2d *)(y0 + r + 2);
        b0 += xa * *(const dq_v2d *)(y1 + r);
        b1 += xb * *(const dq_v2d *)(y1 + r + 2);
    }
    a0 += a1;
    b0 += b1;
    s0 = a0[0] + a0[1];
    s1 = b0[0] + b0[1];
#endif
    for (; r < n; r++) {
        s0 += x[r] * y0[r];
        s1 += x[r] * y1[r];
    }
    out[0] = s0;
    out[1] = s1;
}

void dq_gram_columns(const double *B, int rows, int stride, int dim, int se3, int zero,
                     double *G, double *g)
{
#define DQ_FROM(c) ((c) < se3 && (c) % 6 >= 3 ? zero : 0)
    const int last = g ? dim : dim - 1;     /* column dim: the residual, for g */
    for (int a = 0; a < dim; a++) {
        for (int b = a; b <= last; b += 2) {
            int two = b + 1 <= last, c = two ? b + 1 : b;
            int from = DQ_FROM(a), fb = DQ_FROM(b), fc = DQ_FROM(c);
            if (fb < fc) fc = fb;
            if (fc > from) from = fc;
            double out[2];
            dot_columns2(B + (size_t)stride * a + from, B + (size_t)stride * b + from,
                         B + (size_t)stride * c + from, rows - from, out);
            if (b < dim) G[dim * a + b] = out[0];
            else g[a] = out[0];
            if (two) {
                if (c < dim) G[dim * a + c] = out[1];
                else g[a] = out[1];
            }
        }
    }
#undef DQ_FROM
}

/* Lane loops innermost, of constant length: the compiler makes each a vector operation. */
DQ_INLINE int chol_solve_lanes(const double *restrict A, int m, double *restrict L,
                               double *restrict di, double *restrict y, double *restrict yy)
{
    enum { W = DQ_LANES };
    int ok = 1;
    for (int j = 0; j < m; j++) {
        double d[W], inv[W];
        for (int l = 0; l < W; l++) d[l] = A[W * (m * j + j) + l];
        for (int k = 0; k < j; k++)
            for (int l = 0; l < W; l++) d[l] -= L[W * (m * j + k) + l] * L[W * (m * j + k) + l];
        for (int l = 0; l < W; l++) ok &= d[l] > 0.0;
        for (int l = 0; l < W; l++) {
            double ljj = sqrt(d[l]);
            inv[l] = 1.0 / ljj;
            L[W * (m * j + j) + l] = ljj;
            di[W * j + l] = inv[l];
        }
        for (int i = j + 1; i < m; i++) {
            double s[W];
            for (int l = 0; l < W; l++) s[l] = A[W * (m * i + j) + l];
            for (int k = 0; k < j; k++)
                for (int l = 0; l < W; l++) s[l] -= L[W * (m * i + k) + l] * L[W * (m * j + k) + l];
            for (int l = 0; l < W; l++) L[W * (m * i + j) + l] = s[l] * inv[l];
        }
    }
    double q[W] = {0.0, 0.0, 0.0, 0.0};
    for (int i = 0; i < m; i++) {
        double s[W];
        for (int l = 0; l < W; l++) s[l] = y[W * i + l];
        for (int k = 0; k < i; k++)
            for (int l = 0; l < W; l++) s[l] -= L[W * (m * i + k) + l] * y[W * k + l];
        for (int l = 0; l < W; l++) {
            y[W * i + l] = s[l] * di[W * i + l];
            q[l] += y[W * i + l] * y[W * i + l];
        }
    }
    for (int l = 0; l < W; l++) yy[l] = q[l];
    return ok;
}

DQ_CLONES int dq_chol_solve_lanes(const double *A, int m, double *L, double *di, double *y,
                                  double *yy)
{
    return m == 12 ? chol_solve_lanes(A, 12, L, di, y, yy) : chol_solve_lanes(A, m, L, di, y, yy);
}

#if DQ_V4
DQ_CLONES void dq_whiten_jacobian6_lanes(const double *L, const double *di, const double *A,
                                         double *B)
{
    /* dq_whiten_jacobian6's operations, four problems a vector */
    dq_v4 Lv[36], Bv[36];
    for (int k = 0; k < 36; k++) Lv[k] = dq_v4_load(L + 4 * k);
    for (int i = 0; i < 3; i++) {
        dq_v4 row[3] = {dq_v4_load(A + 4 * (6 * i)), dq_v4_load(A + 4 * (6 * i + 1)),
                        dq_v4_load(A + 4 * (6 * i + 2))};
        for (int k = 0; k < i; k++) {
            dq_v4 l = Lv[6 * i + k];
            for (int c = 0; c < 3; c++) row[c] -= l * Bv[6 * k + c];
        }
        dq_v4 d = dq_v4_load(di + 4 * i);
        for (int c = 0; c < 3; c++) Bv[6 * i + c] = row[c] * d;
        Bv[6 * i + 3] = Bv[6 * i + 4] = Bv[6 * i + 5] = dq_v4_of(0.0);
    }
    for (int i = 3; i < 6; i++) {
        dq_v4 row[6];
        for (int c = 0; c < 6; c++) row[c] = dq_v4_load(A + 4 * (6 * i + c));
        for (int k = 0; k < i; k++) {
            dq_v4 l = Lv[6 * i + k];
            for (int c = 0; c < 6; c++) row[c] -= l * Bv[6 * k + c];
        }
        dq_v4 d = dq_v4_load(di + 4 * i);
        for (int c = 0; c < 6; c++) Bv[6 * i + c] = row[c] * d;
    }
    for (int k = 0; k < 36; k++) dq_v4_store(B + 4 * k, Bv[k]);
}
#endif

void dq_mirror6(double *G)
{
    for (int i = 0; i < 6; i++)
        for (int j = 0; j < i; j++) G[6 * i + j] = G[6 * j + i];
}

void dq_mirror(double *M, int dim)
{
    for (int i = 0; i < dim; i++)
        for (int j = 0; j < i; j++) M[dim * i + j] = M[dim * j + i];
}

void dq_chol6_inverse(const double *L, const double *di, double *P)
{
    double Li[36];
    for (int c = 0; c < 6; c++) {
        double e[6] = {0, 0, 0, 0, 0, 0};
        e[c] = 1.0;
        lower_solve_m(L, di, e, e, 6);
        for (int r = 0; r < 6; r++) Li[6 * r + c] = e[r];
    }
    for (int i = 0; i < 36; i++) P[i] = 0.0;
    dq_add_gram6(Li, P);
    dq_mirror6(P);
}

int dq_spd_inverse(const double *H, int dim, double *work, double *P)
{
    double *L = work, *di = L + dim * dim, *e = di + dim;
    if (!chol_m(H, L, di, dim)) return 0;
    for (int c = 0; c < dim; c++) { /* column c of L^-T L^-1 */
        for (int r = 0; r < dim; r++) e[r] = r == c ? 1.0 : 0.0;
        lower_solve_m(L, di, e, e, dim);
        upper_solve_m(L, di, e, e, dim);
        for (int r = 0; r < dim; r++) P[dim * r + c] = e[r];
    }
    for (int a = 0; a < dim; a++) /* the two triangles' rounding differs: their mean */
        for (int b = 0; b < a; b++)
            P[dim * a + b] = P[dim * b + a] = 0.5 * (P[dim * a + b] + P[dim * b + a]);
    return 1;
}
