/*
 * fusion.c — maximum-likelihood fusion of poses with full covariances (see fusion.h).
 *
 * Every measurement is whitened once by the Cholesky factor of its covariance, S_i = L_i L_i^T:
 * the cost is |L_i^-1 r_i|^2 and its information contribution B_i^T B_i with B_i = L_i^-1 A_i,
 * which is cheaper and better conditioned than forming S_i^-1.
 */
#include "fusion.h"

#include <math.h>
#include <string.h>

#include "blend.h"
#include "dq.h"

/* A step that raises the cost by more than this (relative) is halved, at most MAX_HALVINGS
 * times (service/fusion.py's reference uses the same values). */
#define COST_SLACK 1e-12
#define MAX_HALVINGS 30
/* The DIB start runs with dq.dib's defaults. */
#define START_TOL 1e-12
#define START_MAX_ITER 100
/* Below this rotation angle the Jacobian coefficients come from their Taylor series (the closed
 * forms divide cancelling differences by up to t^5); service/lie.py uses the same. */
#define SERIES_ANGLE 0.5

/* The workspace: a block of W_PER doubles per measurement (its covariance factor L, Jacobian A,
 * information B^T B, the prefix sum of the others', and r, e = L^-1 r, sin and cos of half the
 * rotation angle for the current and a trial estimate), then the DIB start's packed poses and
 * weights (10 per measurement: the pose, its weight and the normalised weight). */
enum { W_L = 0, W_A = 36, W_OWN = 72, W_PRE = 108, W_R = 144, W_E = 150, W_SC = 156,
       W_R2 = 158, W_E2 = 164, W_SC2 = 170, W_DI = 172, W_PER = 178 };

size_t dq_fuse_workspace(size_t n) { return (W_PER + 10) * n; }

/* ---- 6x6 linear algebra --------------------------------------------------------------------- */

/* A = L L^T from the lower triangle of the m x m A (L's upper triangle is left as it was:
 * nothing reads it), di the inverse of L's diagonal (the solves multiply by it); 0 when a pivot
 * is not positive (or not finite). Inlined with a constant m for the 6 x 6 blocks. */
static inline int chol(const double *A, double *L, double *di, int m)
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

/* x = L^-1 b for an m x m L; x may alias b. */
static inline void lower_solve_m(const double *L, const double *di, const double *b, double *x,
                                 int m)
{
    for (int i = 0; i < m; i++) {
        double s = b[i];
        for (int k = 0; k < i; k++) s -= L[m * i + k] * x[k];
        x[i] = s * di[i];
    }
}

/* x = L^-T b for an m x m L; x may alias b. */
static inline void upper_solve_m(const double *L, const double *di, const double *b, double *x,
                                 int m)
{
    for (int i = m - 1; i >= 0; i--) {
        double s = b[i];
        for (int k = i + 1; k < m; k++) s -= L[m * k + i] * x[k];
        x[i] = s * di[i];
    }
}

static int chol6(const double *A, double *L, double *di) { return chol(A, L, di, 6); }

/* A diagonal shift, relative to each diagonal entry, well beyond the rounding of any 6x6
 * Cholesky (~1e-15): a matrix that factors when shifted down by it is positive definite to
 * LAPACK too, one that fails shifted up by it is not; in between the two may differ. */
#define SPD_MARGIN 1e-8
/* Entries outside this range (but zero) could underflow or overflow in the products. */
#define SPD_SMALL 1e-100
#define SPD_LARGE 1e100

int dq_covariance_check(const double *S, double sym_tol, double *sym)
{
    if (!dq_finite_n(S, 36)) return DQ_E_NONFINITE;
    double scale = 0.0, asym = 0.0;
    int extreme = 0;
    for (int i = 0; i < 6; i++) {
        for (int j = 0; j < 6; j++) {
            double a = fabs(S[6 * i + j]), d = fabs(S[6 * i + j] - S[6 * j + i]);
            if (a > scale) scale = a;
            if (d > asym) asym = d;
            if (a != 0.0 && (a < SPD_SMALL || a > SPD_LARGE)) extreme = 1;
        }
    }
    if (!(asym <= sym_tol * scale)) return DQ_E_ASYMMETRIC;
    for (int j = 0; j < 6; j++)
        if (S[7 * j] > 0.0 && !(S[7 * j] >= DQ_MIN_VARIANCE && S[7 * j] <= DQ_MAX_VARIANCE))
            return DQ_E_SCALE; /* one not positive is not positive definite: said so below */
    if (extreme) return DQ_E_BORDERLINE;
    for (int i = 0; i < 6; i++)
        for (int j = 0; j < 6; j++) sym[6 * i + j] = 0.5 * (S[6 * i + j] + S[6 * j + i]);
    double A[36], L[36], di[6];
    memcpy(A, sym, sizeof A);
    for (int j = 0; j < 6; j++) A[7 * j] = sym[7 * j] - SPD_MARGIN * fabs(sym[7 * j]);
    if (chol6(A, L, di)) return DQ_OK;
    for (int j = 0; j < 6; j++) A[7 * j] = sym[7 * j] + SPD_MARGIN * fabs(sym[7 * j]);
    return chol6(A, L, di) ? DQ_E_BORDERLINE : DQ_E_NOT_SPD;
}

static void lower_solve(const double *L, const double *di, const double *b, double *x)
{
    lower_solve_m(L, di, b, x, 6);
}

static void upper_solve(const double *L, const double *di, const double *b, double *x)
{
    upper_solve_m(L, di, b, x, 6);
}

/* B = L^-1 M for a 6x6 M, row by row (each row a whole 6-vector, which vectorises). */
static void lower_solve_matrix(const double *L, const double *di, const double *M,
                               double *restrict B)
{
    for (int i = 0; i < 6; i++) {
        double row[6];
        for (int c = 0; c < 6; c++) row[c] = M[6 * i + c];
        for (int k = 0; k < i; k++) {
            double l = L[6 * i + k];
            for (int c = 0; c < 6; c++) row[c] -= l * B[6 * k + c];
        }
        for (int c = 0; c < 6; c++) B[6 * i + c] = row[c] * di[i];
    }
}

/* B = L^-1 A for A = Jl^-1 = [[J, 0], [M, J]]: B's upper-right 3x3 block stays zero. */
static void whiten_jacobian(const double *L, const double *di, const double *A,
                            double *restrict B)
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
    for (int i = 3; i < 6; i++) {
        double row[6];
        for (int c = 0; c < 6; c++) row[c] = A[6 * i + c];
        for (int k = 0; k < i; k++) {
            double l = L[6 * i + k];
            for (int c = 0; c < 6; c++) row[c] -= l * B[6 * k + c];
        }
        for (int c = 0; c < 6; c++) B[6 * i + c] = row[c] * di[i];
    }
}

/* G += B^T B (upper triangle) for B from whiten_jacobian: its first three rows end in zeros. */
static void add_gram_whitened(const double *restrict B, double *restrict G)
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

/* G += B^T B (symmetric: the upper triangle, then mirrored by the caller via mirror6). */
static void add_gram(const double *restrict B, double *restrict G)
{
    for (int k = 0; k < 6; k++)
        for (int i = 0; i < 6; i++) {
            double b = B[6 * k + i];
            for (int j = i; j < 6; j++) G[6 * i + j] += b * B[6 * k + j];
        }
}

static void mirror6(double *G)
{
    for (int i = 0; i < 6; i++)
        for (int j = 0; j < i; j++) G[6 * i + j] = G[6 * j + i];
}

/* P = A^-1 from A's Cholesky factor L: (L^-1)^T L^-1, symmetric by construction. */
static void chol6_inverse(const double *L, const double *di, double *P)
{
    double Li[36];
    for (int c = 0; c < 6; c++) {
        double e[6] = {0, 0, 0, 0, 0, 0};
        e[c] = 1.0;
        lower_solve(L, di, e, e);
        for (int r = 0; r < 6; r++) Li[6 * r + c] = e[r];
    }
    for (int i = 0; i < 36; i++) P[i] = 0.0;
    add_gram(Li, P);
    mirror6(P);
}

/* ---- SE(3) ----------------------------------------------------------------------------------- */

static double series8(const double *c, double t2)
{
    double s = 0.0;
    for (int k = 7; k >= 0; k--) s = s * t2 + c[k];
    return s;
}

static const double B_SERIES[8] = {1.0 / 2, -1.0 / 24, 1.0 / 720, -1.0 / 40320, 1.0 / 3628800,
                                   -1.0 / 479001600, 1.0 / 87178291200.0,
                                   -1.0 / 20922789888000.0};
static const double C_SERIES[8] = {1.0 / 6, -1.0 / 120, 1.0 / 5040, -1.0 / 362880, 1.0 / 39916800,
                                   -1.0 / 6227020800.0, 1.0 / 1307674368000.0,
                                   -1.0 / 355687428096000.0};
static const double C2_SERIES[8] = {1.0 / 24, -1.0 / 720, 1.0 / 40320, -1.0 / 3628800,
                                    1.0 / 479001600, -1.0 / 87178291200.0,
                                    1.0 / 20922789888000.0, -1.0 / 6402373705728000.0};
static const double C3_SERIES[8] = {1.0 / 120, -1.0 / 2520, 1.0 / 120960, -1.0 / 9979200,
                                    1.0 / 1245404160, -1.0 / 217945728000.0,
                                    1.0 / 50812489728000.0, -1.0 / 15205637551104000.0};
static const double D_SERIES[8] = {1.0 / 12, 1.0 / 720, 1.0 / 30240, 1.0 / 1209600,
                                   1.0 / 47900160, 691.0 / 1307674368000.0,
                                   1.0 / 74724249600.0, 3617.0 / 10670622842880000.0};

static inline void mul3(const double *a, const double *b, double *restrict c)
{
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            c[3 * i + j] = a[3 * i] * b[j] + a[3 * i + 1] * b[3 + j] + a[3 * i + 2] * b[6 + j];
}

static inline void hat3(const double *w, double *K)
{
    K[0] = 0.0;   K[1] = -w[2]; K[2] = w[1];
    K[3] = w[2];  K[4] = 0.0;   K[5] = -w[0];
    K[6] = -w[1]; K[7] = w[0];  K[8] = 0.0;
}

/* The coefficients of the SE(3) Jacobians at a rotation of squared angle t2: B = (1 - cos t)/t^2
 * and C = (t - sin t)/t^3 of Jl = I + B w^ + C w^2, c2, c3 of Q (Barfoot's eq. 7.86) and
 * D = (1 - (t/2) cot(t/2))/t^2 of Jl^-1 = I - w^/2 + D w^2 (the formulas of service/lie.py). s2, ch
 * are the squared sine and the cosine of half the angle, from the quaternion the rotation came
 * from, so no trigonometric call is needed. */
typedef struct { double B, C, c2, c3, D; } jac_coef;

static inline jac_coef jacobian_coefficients(double t2, double s2, double ch)
{
    jac_coef k;
    if (t2 < SERIES_ANGLE * SERIES_ANGLE) {
        k.B = series8(B_SERIES, t2);
        k.C = series8(C_SERIES, t2);
        k.c2 = series8(C2_SERIES, t2);
        k.c3 = series8(C3_SERIES, t2);
        k.D = series8(D_SERIES, t2);
    } else {
        double t = sqrt(t2), sh = sqrt(s2), it2 = 1.0 / t2, it3 = it2 / t;
        double st = 2.0 * sh * ch, ct = 1.0 - 2.0 * s2;
        k.B = 2.0 * s2 * it2;
        k.C = (t - st) * it3;
        k.c2 = 0.5 * (t2 - 4.0 * s2) * it2 * it2;
        k.c3 = 0.5 * (2.0 * t - 3.0 * st + t * ct) * it3 * it2;
        k.D = (1.0 - 0.5 * t * ch / sh) * it2;
    }
    return k;
}

/* Q(w, v), the lower-left block of Jl(xi). Its products of w^ and v^ collapse to rank-one terms
 * (a^ b^ = b a^T - (a.b) I, w^ w = 0): w^ v^ w^ = -(w.v) w^, w^ w^ = w w^T - t^2 I,
 * w^ w^ v^ + v^ w^ w^ = w u^T - u w^T - 2 t^2 v^ with u = w x v; so Q = v^/2
 * + C (v w^T + w v^T - 2(w.v) I - (w.v) w^) + c2 (w u^T - u w^T - 2 t^2 v^ + 3 (w.v) w^)
 * - 2 c3 (w.v) (w w^T - t^2 I). */
static inline void q_block(const double *w, const double *v, double t2, const jac_coef *k,
                           double *restrict Q)
{
    double wv = w[0] * v[0] + w[1] * v[1] + w[2] * v[2];
    double u[3] = {w[1] * v[2] - w[2] * v[1], w[2] * v[0] - w[0] * v[2], w[0] * v[1] - w[1] * v[0]};
    double W[9], V[9];
    hat3(w, W);
    hat3(v, V);
    double kv = 0.5 - 2.0 * k->c2 * t2, kw = 3.0 * k->c2 * wv - k->C * wv, kww = -2.0 * k->c3 * wv;
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            double ww = w[i] * w[j] - (i == j ? t2 : 0.0);
            Q[3 * i + j] = kv * V[3 * i + j] + kw * W[3 * i + j] +
                           k->C * (v[i] * w[j] + w[i] * v[j] - (i == j ? 2.0 * wv : 0.0)) +
                           k->c2 * (w[i] * u[j] - u[i] * w[j]) + kww * ww;
        }
}

/* Jl^-1(xi) = [[Ji, 0], [-Ji Q Ji, Ji]] with Ji = I - w^/2 + D w^2; s2, ch as for
 * jacobian_coefficients. */
static inline void jl_inv(const double *xi, double s2, double ch, double *restrict J)
{
    const double *w = xi, *v = xi + 3;
    double t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2];
    jac_coef k = jacobian_coefficients(t2, s2, ch);
    double W[9], Q[9], Ji[9], T[9], M[9];
    q_block(w, v, t2, &k, Q);
    hat3(w, W);
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            double ww = w[i] * w[j] - (i == j ? t2 : 0.0);
            Ji[3 * i + j] = (i == j ? 1.0 : 0.0) - 0.5 * W[3 * i + j] + k.D * ww;
        }
    mul3(Ji, Q, T);
    mul3(T, Ji, M);
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            double a = Ji[3 * i + j];
            J[6 * i + j] = a;
            J[6 * i + 3 + j] = 0.0;
            J[6 * (i + 3) + j] = -M[3 * i + j];
            J[6 * (i + 3) + 3 + j] = a;
        }
}

/* s Jr(xi) = s Jl(-xi) = s [[Jl(w), 0], [Q(w, v), Jl(w)]] at (w, v) = -xi, written into the
 * 6 x 6 block of the ld-strided J at its top left; s2, ch as for jacobian_coefficients. */
static inline void jr_scaled(const double *xi, double s2, double ch, double s, double *J, int ld)
{
    double w[3] = {-xi[0], -xi[1], -xi[2]}, v[3] = {-xi[3], -xi[4], -xi[5]};
    double t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2];
    jac_coef k = jacobian_coefficients(t2, s2, ch);
    double W[9], Q[9];
    q_block(w, v, t2, &k, Q);
    hat3(w, W);
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            double ww = w[i] * w[j] - (i == j ? t2 : 0.0);
            double a = s * ((i == j ? 1.0 : 0.0) + k.B * W[3 * i + j] + k.C * ww);
            J[ld * i + j] = a;
            J[ld * i + 3 + j] = 0.0;
            J[ld * (i + 3) + j] = s * Q[3 * i + j];
            J[ld * (i + 3) + 3 + j] = a;
        }
}

/* r = Log(xc z) (xc the inverse of the estimate), and the squared sine and the cosine of half
 * its rotation angle. */
static inline void residual(const double *xc, const double *z, double *r, double *sc)
{
    double p[8], l[6];
    dq_mul(xc, z, p);
    if (p[0] < 0.0)
        for (int k = 0; k < 8; k++) p[k] = -p[k];
    dq_log(p, l);
    for (int k = 0; k < 6; k++) r[k] = 2.0 * l[k];
    sc[0] = p[1] * p[1] + p[2] * p[2] + p[3] * p[3];
    sc[1] = p[0];
}

static inline int selected(const unsigned char *inlier, size_t i) { return !inlier || inlier[i]; }

/* Residuals, their whitened forms e = L^-1 r and the cost at X for the measurements `use`
 * selects (NULL: all), or with want = 0 the others; r, e, sc at offsets ro, eo, so of each
 * measurement's workspace. */
static double evaluate(const double *X, const double *z, double *work, size_t n,
                       const unsigned char *use, int want, int ro, int eo, int so)
{
    double xc[8], total = 0.0;
    dq_conj(X, xc);
    for (size_t i = 0; i < n; i++) {
        if (selected(use, i) != want) continue;
        double *m = work + W_PER * i;
        residual(xc, z + 8 * i, m + ro, m + so);
        lower_solve(m + W_L, m + W_DI, m + ro, m + eo);
        const double *e = m + eo;
        total += e[0] * e[0] + e[1] * e[1] + e[2] * e[2] + e[3] * e[3] + e[4] * e[4] + e[5] * e[5];
    }
    return total;
}

/* The information H (full) and the gradient g = sum B^T e over `use`, from r, e, sc at ro, eo,
 * so; each measurement's A = Jl^-1(r) is kept in its workspace (the leave-one-out statistics
 * need it at the optimum, and which linearisation is the last one is known only after its step
 * is solved). */
static void linearize(double *work, size_t n, const unsigned char *use, int ro, int eo, int so,
                      double *H, double *g)
{
    for (int k = 0; k < 36; k++) H[k] = 0.0;
    for (int k = 0; k < 6; k++) g[k] = 0.0;
    for (size_t i = 0; i < n; i++) {
        if (!selected(use, i)) continue;
        double *m = work + W_PER * i, *A = m + W_A;
        double B[36];
        jl_inv(m + ro, m[so], m[so + 1], A);
        whiten_jacobian(m + W_L, m + W_DI, A, B);
        const double *e = m + eo;
        for (int c = 0; c < 6; c++) {
            double s = 0.0;
            for (int k = 0; k < 6; k++) s += B[6 * k + c] * e[k];
            g[c] += s;
        }
        add_gram_whitened(B, H);
    }
    mirror6(H);
}

/* Gauss-Newton from X over the selected measurements (see fusion.h); X is updated in place and
 * the selected measurements' r, e, sc at it are left in the W_R, W_E, W_SC slots. A step shorter
 * than tol is not taken: the point it was computed at is the optimum to within tol, and its
 * linearisation (H, and each measurement's A) is the one at X. *current says whether H
 * is at the returned X (not so when the step limit or a line search ended the loop). */
static int solve(double *X, const double *z, double *work, size_t n, const unsigned char *use,
                 const dq_fuse_params *p, int *status, int *iterations, double *H, int *current)
{
    /* The current point's r, e, sc and a trial point's swap between two slots. */
    int ro = W_R, eo = W_E, so = W_SC, rt = W_R2, et = W_E2, st = W_SC2;
    double total = evaluate(X, z, work, n, use, 1, ro, eo, so);
    *current = 0;
    *status = DQ_FUSE_MAX_ITERATIONS;
    *iterations = p->max_iter;
    for (int it = 1; it <= p->max_iter; it++) {
        double g[6], L[36], di[6], delta[6], Xn[8];
        linearize(work, n, use, ro, eo, so, H, g);
        if (!chol6(H, L, di)) return DQ_E_SINGULAR;
        lower_solve(L, di, g, delta);
        upper_solve(L, di, delta, delta);
        double step = sqrt(delta[0] * delta[0] + delta[1] * delta[1] + delta[2] * delta[2] +
                           delta[3] * delta[3] + delta[4] * delta[4] + delta[5] * delta[5]);
        if (step < p->tol) {
            *status = DQ_FUSE_CONVERGED;
            *iterations = it;
            *current = 1;
            break;
        }
        double total_new = total;
        for (int h = 0; h < MAX_HALVINGS; h++) {
            double half[6], E[8], P[8];
            for (int k = 0; k < 6; k++) half[k] = 0.5 * delta[k];
            dq_exp(half, E);
            dq_mul(X, E, P);
            if (dq_normalize(P, Xn)) return DQ_E_OVERFLOW;
            total_new = evaluate(Xn, z, work, n, use, 1, rt, et, st);
            if (total_new <= total * (1.0 + COST_SLACK) || step < p->tol) break;
            for (int k = 0; k < 6; k++) delta[k] *= 0.5;
            step *= 0.5;
        }
        for (int k = 0; k < 8; k++) X[k] = Xn[k];
        int t;
        t = ro; ro = rt; rt = t;
        t = eo; eo = et; et = t;
        t = so; so = st; st = t;
        total = total_new;
        if (step < p->tol) { /* halved below tol: the line search found no lower cost */
            *status = DQ_FUSE_CONVERGED;
            *iterations = it;
            break;
        }
    }
    if (ro != W_R)
        for (size_t i = 0; i < n; i++) {
            if (!selected(use, i)) continue;
            double *m = work + W_PER * i;
            for (int k = 0; k < 6; k++) m[W_R + k] = m[ro + k];
            for (int k = 0; k < 6; k++) m[W_E + k] = m[eo + k];
            for (int k = 0; k < 2; k++) m[W_SC + k] = m[so + k];
        }
    return DQ_OK;
}

/* The start: DIB of the selected poses weighted by det(S_i^-1)^(1/6) = (prod diag L_i)^(-1/3),
 * a scalar that scales with the information. */
static int start(const double *z, double *work, size_t n, const unsigned char *use, double *X)
{
    double *q = work + W_PER * n, *w = q + 8 * n, *wn = w + n;
    size_t m = 0;
    double big = 0.0;
    for (size_t i = 0; i < n; i++) {
        if (!selected(use, i)) continue;
        const double *L = work + W_PER * i + W_L;
        double prod = L[0] * L[7] * L[14] * L[21] * L[28] * L[35], wi;
        if (prod > 1e-290 && prod < 1e290) {
            wi = 1.0 / cbrt(prod);
        } else { /* the product under- or overflows: the same through logarithms */
            double s = log(L[0]) + log(L[7]) + log(L[14]) + log(L[21]) + log(L[28]) + log(L[35]);
            wi = exp(-s / 3.0);
        }
        for (int k = 0; k < 8; k++) q[8 * m + k] = z[8 * i + k];
        w[m] = wi;
        if (wi > big) big = wi;
        m++;
    }
    for (size_t i = 0; i < m; i++) w[i] /= big;
    size_t bad;
    if (dq_weights(w, m, wn, &bad)) return DQ_E_OVERFLOW;
    int iters;
    double res;
    dq_dib(q, wn, m, START_TOL, START_MAX_ITER, X, &iters, &res);
    return dq_finite8(X) ? DQ_OK : DQ_E_OVERFLOW;
}

/* NIS of every measurement against the fit of the other inliers (fusion.h), from the A, r, e
 * kept by the final linearisation and the information H of all inliers. */
static int leave_one_out(const double *cov, double *work, size_t n, const unsigned char *use,
                         size_t n_in, const double *H, double *nis, unsigned char *tested)
{
    /* Hj = (sum of the inliers before j) + (sum after j): no subtraction, so a dominant
     * measurement does not cancel the others' information away. */
    double acc[36];
    for (int k = 0; k < 36; k++) acc[k] = 0.0;
    for (size_t i = 0; i < n; i++) {
        double *m = work + W_PER * i;
        for (int k = 0; k < 36; k++) m[W_PRE + k] = acc[k];
        if (selected(use, i)) { /* own = B^T B, B = L^-1 A: the measurement's information */
            double B[36];
            whiten_jacobian(m + W_L, m + W_DI, m + W_A, B);
            for (int k = 0; k < 36; k++) m[W_OWN + k] = 0.0;
            add_gram_whitened(B, m + W_OWN);
            for (int k = 0; k < 36; k++) acc[k] += m[W_OWN + k];
        }
    }
    for (int k = 0; k < 36; k++) acc[k] = 0.0; /* now the sum after j */
    for (size_t jj = n; jj-- > 0;) {
        double *m = work + W_PER * jj;
        int in = selected(use, jj);
        int t = !in || n_in > 1;
        tested[jj] = (unsigned char)t;
        if (!t) {
            nis[jj] = 0.0;
        } else {
            double Hj[36], M[36], dm[6], dn[6], At[36], G[36], K[36], Wr[6], nu[6], T[36], N[36], y[6];
            if (in) {
                for (int k = 0; k < 36; k++) Hj[k] = m[W_PRE + k] + acc[k];
                mirror6(Hj);
            } else {
                for (int k = 0; k < 36; k++) Hj[k] = H[k];
            }
            if (!chol6(Hj, M, dm)) return DQ_E_SINGULAR;
            const double *A = m + W_A;
            for (int r = 0; r < 6; r++)
                for (int c = 0; c < 6; c++) At[6 * r + c] = A[6 * c + r];
            lower_solve_matrix(M, dm, At, G); /* G = M^-1 A^T, K = G^T G = A Hj^-1 A^T */
            for (int k = 0; k < 36; k++) K[k] = 0.0;
            add_gram(G, K);
            mirror6(K);
            for (int k = 0; k < 6; k++) nu[k] = m[W_R + k];
            if (in) {
                upper_solve(m + W_L, m + W_DI, m + W_E, Wr); /* S^-1 r = L^-T e */
                for (int r = 0; r < 6; r++) {
                    double s = 0.0;
                    for (int c = 0; c < 6; c++) s += K[6 * r + c] * Wr[c];
                    nu[r] += s;
                }
            }
            const double *S = cov + 36 * jj;
            for (int k = 0; k < 36; k++) T[k] = S[k] + K[k];
            if (!chol6(T, N, dn)) return DQ_E_SINGULAR;
            lower_solve(N, dn, nu, y);
            nis[jj] = y[0] * y[0] + y[1] * y[1] + y[2] * y[2] + y[3] * y[3] + y[4] * y[4] +
                      y[5] * y[5];
        }
        if (in)
            for (int k = 0; k < 36; k++) acc[k] += m[W_OWN + k];
    }
    return DQ_OK;
}

int dq_fuse(const double *z, const double *cov, const unsigned char *inlier, size_t n,
            const dq_fuse_params *p, double *work, dq_fused *out, const dq_fuse_outputs *per,
            size_t *bad)
{
    size_t n_in = 0, first = 0;
    for (size_t i = 0; i < n; i++) {
        if (!chol6(cov + 36 * i, work + W_PER * i + W_L, work + W_PER * i + W_DI)) {
            *bad = i;
            return DQ_E_NOT_SPD;
        }
        if (selected(inlier, i) && n_in++ == 0) first = i;
    }
    if (n_in == 0) return DQ_E_NO_INLIERS;
    int rc, current = 0;
    double H[36], g[6], L[36], di[6];
    if (n_in == 1) { /* its own estimate: no step to take */
        for (int k = 0; k < 8; k++) out->mean[k] = z[8 * first + k];
        out->status = DQ_FUSE_CONVERGED;
        out->iterations = 0;
    } else {
        if ((rc = start(z, work, n, inlier, out->mean))) return rc;
        if ((rc = solve(out->mean, z, work, n, inlier, p, &out->status, &out->iterations, H,
                        &current)))
            return rc;
    }
    /* Everything at the returned mean: residuals of all (the inliers' are there after solve),
     * information of the inliers (already there when solve's last linearisation was at it). */
    if (n_in == 1)
        evaluate(out->mean, z, work, n, NULL, 1, W_R, W_E, W_SC);
    else
        evaluate(out->mean, z, work, n, inlier, 0, W_R, W_E, W_SC);
    if (!current) linearize(work, n, inlier, W_R, W_E, W_SC, H, g);
    if (!chol6(H, L, di)) return DQ_E_SINGULAR;
    chol6_inverse(L, di, out->covariance);
    double chi2 = 0.0;
    for (size_t i = 0; i < n; i++) {
        const double *m = work + W_PER * i;
        const double *e = m + W_E;
        double c = e[0] * e[0] + e[1] * e[1] + e[2] * e[2] + e[3] * e[3] + e[4] * e[4] + e[5] * e[5];
        if (selected(inlier, i)) chi2 += c;
        if (per->distances) per->distances[i] = sqrt(c);
        if (per->residuals)
            for (int k = 0; k < 6; k++) per->residuals[6 * i + k] = m[W_R + k];
    }
    out->chi2 = chi2;
    if (!dq_finite8(out->mean) || !dq_finite_n(out->covariance, 36) || !(chi2 * 0.0 == 0.0))
        return DQ_E_OVERFLOW;
    if (per->nis && per->tested) {
        /* A of the outliers too: linearize kept only the inliers'. */
        for (size_t i = 0; i < n; i++) {
            if (selected(inlier, i)) continue;
            double *m = work + W_PER * i;
            jl_inv(m + W_R, m[W_SC], m[W_SC + 1], m + W_A);
        }
        if ((rc = leave_one_out(cov, work, n, inlier, n_in, H, per->nis, per->tested))) return rc;
        if (!dq_finite_n(per->nis, n)) return DQ_E_OVERFLOW;
    }
    return DQ_OK;
}

/* ---- time alignment: the constant-twist motion model (fusion.h) ------------------------------ */

/* A measurement's Jacobian is kept compact: MC columns, the pose's 6, the twist's 6 and its own
 * latency's 1 (zero columns when the twist or the latency is not estimated). */
#define MC 13

/* The motion workspace: a block per measurement (its covariance factor L and DI, its whitened
 * compact Jacobian L^-1 G, two slots of r, e = L^-1 r, sin^2 and cos of half r's angle,
 * Exp(dt V) and dt, for the current and a trial estimate; then the prefix sum of the earlier
 * inliers' information, dim x dim), then the solver's dim-sized arrays. */
enum { M_L = 0, M_DI = 36, M_G = 42, M_S0 = 120, M_S1 = 143, M_PER = 166 };
enum { S_R = 0, S_E = 6, S_SC = 12, S_EXP = 14, S_DT = 22 };

size_t dq_motion_dim(const dq_motion_model *m) { return (m->twist ? 12 : 6) + m->k; }

size_t dq_motion_workspace(size_t n, const dq_motion_model *m)
{
    size_t dim = dq_motion_dim(m);
    return (M_PER + dim * dim) * n + 5 * dim * dim + 7 * dim;
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

/* Residuals and whitened residuals at (X, V, ell) of the measurements `use` selects (want = 1)
 * or the others (want = 0), into slot so of their blocks; returns their cost. */
static double motion_evaluate(const double *X, const double *V, const double *ell,
                              const double *z, const dq_motion_model *m, double *work,
                              size_t stride, size_t n, const unsigned char *use, int want, int so)
{
    double total = 0.0;
    for (size_t i = 0; i < n; i++) {
        if (selected(use, i) != want) continue;
        double *blk = work + stride * i, *s = blk + so;
        double dt = m->stamp[i] - (m->slot[i] >= 0 ? ell[m->slot[i]] : m->latency[i]);
        double h[6], P[8], Pc[8];
        for (int k = 0; k < 6; k++) h[k] = 0.5 * (dt * V[k]);
        dq_exp(h, s + S_EXP);
        dq_mul(X, s + S_EXP, P);
        dq_conj(P, Pc);
        residual(Pc, z + 8 * i, s + S_R, s + S_SC);
        lower_solve(blk + M_L, blk + M_DI, s + S_R, s + S_E);
        const double *e = s + S_E;
        total += e[0] * e[0] + e[1] * e[1] + e[2] * e[2] + e[3] * e[3] + e[4] * e[4] + e[5] * e[5];
        s[S_DT] = dt;
    }
    return total;
}

/* Measurement i's Jacobian from slot so: L^-1 G_i compact into its block, and G_i itself
 * (6 x dim) into Gout when not NULL. */
static void motion_jacobian(const dq_motion_model *m, const double *V, size_t i, double *blk,
                            int so, int dim, double *Gout)
{
    const double *s = blk + so, *E = s + S_EXP;
    double dt = s[S_DT];
    double A[36], Aw[36], Bc[6 * MC], Ei[8], T[16];
    jl_inv(s + S_R, s[S_SC], s[S_SC + 1], A);
    whiten_jacobian(blk + M_L, blk + M_DI, A, Aw);
    /* Ad(Exp(-dt V)) = [[R, 0], [t^ R, R]] of the inverse of Exp(dt V) */
    dq_conj(E, Ei);
    dq_to_matrix(Ei, T);
    double t[3] = {T[3], T[7], T[11]};
    for (int a = 0; a < 3; a++)
        for (int b = 0; b < 3; b++) {
            double R = T[4 * a + b];
            double tR = (a == 0 ? -t[2] * T[4 + b] + t[1] * T[8 + b]
                         : a == 1 ? t[2] * T[b] - t[0] * T[8 + b]
                                  : -t[1] * T[b] + t[0] * T[4 + b]);
            Bc[MC * a + b] = R;
            Bc[MC * a + 3 + b] = 0.0;
            Bc[MC * (a + 3) + b] = tR;
            Bc[MC * (a + 3) + 3 + b] = R;
        }
    if (m->twist) {
        double x[6];
        for (int k = 0; k < 6; k++) x[k] = dt * V[k];
        jr_scaled(x, E[1] * E[1] + E[2] * E[2] + E[3] * E[3], E[0], dt, Bc + 6, MC);
    } else {
        for (int a = 0; a < 6; a++)
            for (int b = 6; b < 12; b++) Bc[MC * a + b] = 0.0;
    }
    for (int a = 0; a < 6; a++) Bc[MC * a + 12] = m->slot[i] >= 0 ? -V[a] : 0.0;
    double *Gw = blk + M_G;
    for (int a = 0; a < 6; a++)
        for (int c = 0; c < MC; c++) {
            double sw = 0.0;
            for (int k = 0; k < 6; k++) sw += Aw[6 * a + k] * Bc[MC * k + c];
            Gw[MC * a + c] = sw;
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

/* M += (L^-1 G_i)^T (L^-1 G_i) of measurement i into the upper triangle of the dim x dim M. */
static void motion_add_information(const dq_motion_model *m, size_t i, const double *Gw, int dim,
                                   double *M)
{
    if (m->twist && m->slot[i] < 0) {
        /* the common case, the pose's and the twist's columns as they are: fixed bounds the
         * compiler unrolls (the same sums in the same order as below) */
        for (int a = 0; a < 12; a++)
            for (int b = a; b < 12; b++) {
                double s = 0.0;
                for (int k = 0; k < 6; k++) s += Gw[MC * k + a] * Gw[MC * k + b];
                M[dim * a + b] += s;
            }
        return;
    }
    int cols[MC], map[MC], nc = 0;
    for (int c = 0; c < MC; c++) {
        int col = motion_column(m, i, c);
        if (col >= 0) { cols[nc] = c; map[nc++] = col; }
    }
    for (int a = 0; a < nc; a++)
        for (int b = a; b < nc; b++) {
            double s = 0.0;
            for (int k = 0; k < 6; k++) s += Gw[MC * k + cols[a]] * Gw[MC * k + cols[b]];
            M[dim * map[a] + map[b]] += s;
        }
}

static void mirror(double *M, int dim)
{
    for (int i = 0; i < dim; i++)
        for (int j = 0; j < i; j++) M[dim * i + j] = M[dim * j + i];
}

/* The data's information H (upper triangle) and gradient g = sum (L^-1 G)^T e over `use`, from
 * slot so; every measurement's compact Jacobian is kept in its block (with all = 1 the others'
 * too, not added), G_i written to G when not NULL. */
static void motion_linearize(const dq_motion_model *m, const double *V, double *work,
                             size_t stride, size_t n, const unsigned char *use, int all, int so,
                             int dim, double *H, double *g, double *G)
{
    for (int k = 0; k < dim * dim; k++) H[k] = 0.0;
    for (int k = 0; k < dim; k++) g[k] = 0.0;
    for (size_t i = 0; i < n; i++) {
        int in = selected(use, i);
        if (!in && !all) continue;
        double *blk = work + stride * i;
        motion_jacobian(m, V, i, blk, so, dim, G ? G + 6 * dim * i : NULL);
        if (!in) continue;
        const double *Gw = blk + M_G, *e = blk + so + S_E;
        for (int c = 0; c < MC; c++) {
            int col = motion_column(m, i, c);
            if (col < 0) continue;
            double s = 0.0;
            for (int k = 0; k < 6; k++) s += Gw[MC * k + c] * e[k];
            g[col] += s;
        }
        motion_add_information(m, i, Gw, dim, H);
    }
}

/* Leave-one-out NIS (fusion.h) from the compact Jacobians and whitened residuals in slot so:
 * whitened, K_i = L G Hj^-1 G^T L^T, so an inlier's NIS is |e|^2 + |Lh^-1 (L^-1 G)^T e|^2 and an
 * outlier's e^T (I + (L^-1 G) H^-1 (L^-1 G)^T)^-1 e. Hj sums the priors and the other inliers'
 * information (earlier ones kept as prefix sums, later ones accumulated backwards), so a
 * dominant measurement does not cancel the others away. */
static int motion_leave_one_out(const dq_motion_model *m, const double *V, const double *ell,
                                double *work, size_t stride, size_t n, const unsigned char *use,
                                const unsigned char *tested, int so, int dim, const double *H,
                                double *scratch, double *nis)
{
    double *acc = scratch, *Hj = acc + dim * dim, *Lh = Hj + dim * dim, *dh = Lh + dim * dim;
    double *y = dh + dim, *gz = y + dim;
    for (int k = 0; k < dim * dim; k++) acc[k] = 0.0;
    for (int k = 0; k < dim; k++) gz[k] = 0.0;
    motion_prior_terms(m, V, ell, dim, acc, gz);
    for (size_t i = 0; i < n; i++) {
        double *blk = work + stride * i;
        for (int k = 0; k < dim * dim; k++) blk[M_PER + k] = acc[k];
        if (selected(use, i)) motion_add_information(m, i, blk + M_G, dim, acc);
    }
    for (int k = 0; k < dim * dim; k++) acc[k] = 0.0; /* now the later inliers' */
    for (size_t jj = n; jj-- > 0;) {
        double *blk = work + stride * jj;
        int in = selected(use, jj);
        const double *Gw = blk + M_G, *e = blk + so + S_E;
        double ee = e[0] * e[0] + e[1] * e[1] + e[2] * e[2] + e[3] * e[3] + e[4] * e[4] + e[5] * e[5];
        if (!tested[jj]) {
            nis[jj] = 0.0;
        } else {
            if (in) {
                for (int k = 0; k < dim * dim; k++) Hj[k] = blk[M_PER + k] + acc[k];
            } else {
                for (int k = 0; k < dim * dim; k++) Hj[k] = H[k];
            }
            mirror(Hj, dim);
            if (!chol(Hj, Lh, dh, dim)) return DQ_E_SINGULAR;
            if (in) {
                for (int k = 0; k < dim; k++) y[k] = 0.0;
                for (int c = 0; c < MC; c++) {
                    int col = motion_column(m, jj, c);
                    if (col < 0) continue;
                    double s = 0.0;
                    for (int k = 0; k < 6; k++) s += Gw[MC * k + c] * e[k];
                    y[col] = s;
                }
                lower_solve_m(Lh, dh, y, y, dim);
                double yy = 0.0;
                for (int k = 0; k < dim; k++) yy += y[k] * y[k];
                nis[jj] = ee + yy;
            } else {
                double K[36], N[36], dn[6], u[6];
                double *Yc = Hj; /* Y = Lh^-1 (L^-1 G)^T, 6 columns: Hj is spent */
                for (int a = 0; a < 6; a++) {
                    double *col = Yc + dim * a;
                    for (int k = 0; k < dim; k++) col[k] = 0.0;
                    for (int c = 0; c < MC; c++) {
                        int s = motion_column(m, jj, c);
                        if (s >= 0) col[s] = Gw[MC * a + c];
                    }
                    lower_solve_m(Lh, dh, col, col, dim);
                }
                for (int a = 0; a < 6; a++)
                    for (int b = 0; b < 6; b++) {
                        double s = 0.0;
                        for (int k = 0; k < dim; k++) s += Yc[dim * a + k] * Yc[dim * b + k];
                        K[6 * a + b] = s + (a == b ? 1.0 : 0.0);
                    }
                if (!chol6(K, N, dn)) return DQ_E_SINGULAR;
                lower_solve(N, dn, e, u);
                nis[jj] = u[0] * u[0] + u[1] * u[1] + u[2] * u[2] + u[3] * u[3] + u[4] * u[4] +
                          u[5] * u[5];
            }
        }
        if (in) motion_add_information(m, jj, Gw, dim, acc);
    }
    return DQ_OK;
}

int dq_motion_fit(const double *z, const double *cov, const unsigned char *inlier, size_t n,
                  const dq_motion_model *m, const double *start, const unsigned char *tested,
                  const dq_fuse_params *p, double *work, dq_motion_fitted *out,
                  const dq_motion_outputs *per, size_t *bad)
{
    const int dim = (int)dq_motion_dim(m), off = m->twist ? 12 : 6, k = (int)m->k;
    const size_t stride = M_PER + (size_t)dim * dim;
    size_t n_in = 0;
    for (size_t i = 0; i < n; i++) {
        double *blk = work + stride * i;
        if (!chol6(cov + 36 * i, blk + M_L, blk + M_DI)) {
            *bad = i;
            return DQ_E_NOT_SPD;
        }
        if (selected(inlier, i)) n_in++;
    }
    if (n_in == 0) return DQ_E_NO_INLIERS;
    double *H = work + stride * n, *Lh = H + dim * dim, *g = Lh + dim * dim, *delta = g + dim;
    double *dh = delta + dim, *elln = dh + dim, *scratch = elln + dim;
    double *X = out->mean, *V = out->twist, *ell = out->ell;
    for (int j = 0; j < 8; j++) X[j] = start[j];
    for (int j = 0; j < 6; j++) V[j] = 0.0;
    for (int j = 0; j < k; j++) ell[j] = m->prior[j];
    /* The current point's slot and a trial point's swap. */
    int ro = M_S0, rt = M_S1;
    double total = motion_evaluate(X, V, ell, z, m, work, stride, n, inlier, 1, ro) +
                   motion_prior_cost(m, V, ell);
    out->status = DQ_FUSE_MAX_ITERATIONS;
    out->iterations = p->max_iter;
    for (int it = 1; it <= p->max_iter; it++) {
        motion_linearize(m, V, work, stride, n, inlier, 0, ro, dim, H, g, NULL);
        motion_prior_terms(m, V, ell, dim, H, g);
        mirror(H, dim);
        if (!chol(H, Lh, dh, dim)) return DQ_E_SINGULAR;
        lower_solve_m(Lh, dh, g, delta, dim);
        upper_solve_m(Lh, dh, delta, delta, dim);
        double step = 0.0;
        for (int j = 0; j < dim; j++) step += delta[j] * delta[j];
        step = sqrt(step);
        double Xn[8], Vn[6], total_new = total;
        for (int h = 0; h < MAX_HALVINGS; h++) {
            double half[6], E[8], P[8];
            for (int j = 0; j < 6; j++) half[j] = 0.5 * delta[j];
            dq_exp(half, E);
            dq_mul(X, E, P);
            if (dq_normalize(P, Xn)) return DQ_E_OVERFLOW;
            for (int j = 0; j < 6; j++) Vn[j] = m->twist ? V[j] + delta[6 + j] : V[j];
            for (int j = 0; j < k; j++) elln[j] = ell[j] + delta[off + j];
            total_new = motion_evaluate(Xn, Vn, elln, z, m, work, stride, n, inlier, 1, rt) +
                        motion_prior_cost(m, Vn, elln);
            if (total_new <= total * (1.0 + COST_SLACK) || step < p->tol) break;
            for (int j = 0; j < dim; j++) delta[j] *= 0.5;
            step *= 0.5;
        }
        for (int j = 0; j < 8; j++) X[j] = Xn[j];
        for (int j = 0; j < 6; j++) V[j] = Vn[j];
        for (int j = 0; j < k; j++) ell[j] = elln[j];
        int t = ro; ro = rt; rt = t;
        total = total_new;
        if (step < p->tol) {
            out->status = DQ_FUSE_CONVERGED;
            out->iterations = it;
            break;
        }
    }
    /* Everything at the estimate: the others' residuals (the inliers' are in slot ro), every
     * Jacobian, the inliers' information with the priors'. */
    motion_evaluate(X, V, ell, z, m, work, stride, n, inlier, 0, ro);
    motion_linearize(m, V, work, stride, n, inlier, 1, ro, dim, H, g, per->G);
    motion_prior_terms(m, V, ell, dim, H, g);
    mirror(H, dim);
    double chi2 = motion_prior_cost(m, V, ell);
    for (size_t i = 0; i < n; i++) {
        const double *s = work + stride * i + ro, *e = s + S_E;
        double c = e[0] * e[0] + e[1] * e[1] + e[2] * e[2] + e[3] * e[3] + e[4] * e[4] + e[5] * e[5];
        if (selected(inlier, i)) chi2 += c;
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
        int rc = motion_leave_one_out(m, V, ell, work, stride, n, inlier, tested, ro, dim, H,
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
        if (!selected(inlier, i)) continue;
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
        if (selected(inlier, i)) {
            work[k].t = m->stamp[i] - m->latency[i];
            work[k++].i = i;
        }
    if (!m->twist || m->twist_w) {
        for (size_t i = 0; i < n; i++) det[i] = k - (selected(inlier, i) ? 1 : 0) >= 1;
        return;
    }
    /* Sorted by the time taken, equal times are runs; an inlier alone in its run is the only
     * one of its instant, and leaving it out loses that instant. */
    qsort(work, k, sizeof *work, by_taken);
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

int dq_spd_inverse(const double *H, int dim, double *work, double *P)
{
    double *L = work, *di = L + dim * dim, *e = di + dim;
    if (!chol(H, L, di, dim)) return 0;
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

int dq_pair_distances(const double *z, const double *cov, size_t n, const long long *cand,
                      size_t m, double *d2, size_t *bad)
{
    for (size_t a = 0; a < m; a++) {
        size_t c = (size_t)cand[a];
        double zc[8], r[6], sc[2], A[36], L[36], di[6], e[6];
        dq_conj(z + 8 * c, zc);
        for (size_t j = 0; j < n; j++) {
            residual(zc, z + 8 * j, r, sc);
            for (int k = 0; k < 36; k++) A[k] = cov[36 * c + k] + cov[36 * j + k];
            if (!chol6(A, L, di)) {
                *bad = j;
                return DQ_E_NOT_SPD;
            }
            lower_solve(L, di, r, e);
            d2[a * n + j] = e[0] * e[0] + e[1] * e[1] + e[2] * e[2] + e[3] * e[3] + e[4] * e[4] +
                            e[5] * e[5];
        }
    }
    return DQ_OK;
}
