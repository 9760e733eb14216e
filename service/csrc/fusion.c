/*
 * fusion.c — maximum-likelihood fusion of poses with full covariances (see fusion.h).
 *
 * Every measurement is whitened once by the Cholesky factor of its covariance, S_i = L_i L_i^T:
 * the cost is |L_i^-1 r_i|^2 and its information contribution B_i^T B_i with B_i = L_i^-1 A_i,
 * which is cheaper and better conditioned than forming S_i^-1. The algebra is linalg6.h's, the
 * Jacobians se3.h's.
 */
#include "fusion.h"

#include <math.h>
#include <string.h>

#include "blend.h"
#include "dq.h"
#include "gn.h"
#include "linalg6.h"
#include "se3.h"

/* The DIB start runs with dq.dib's defaults. */
#define START_TOL 1e-12
#define START_MAX_ITER 100

/* The workspace: a block of W_PER doubles per measurement (its covariance factor L, Jacobian A,
 * information B^T B, the prefix sum of the others', and r, e = L^-1 r, sin and cos of half the
 * rotation angle for the current and a trial estimate), then the DIB start's packed poses and
 * weights (10 per measurement: the pose, its weight and the normalised weight). */
enum { W_L = 0, W_A = 36, W_OWN = 72, W_PRE = 108, W_R = 144, W_E = 150, W_SC = 156,
       W_R2 = 158, W_E2 = 164, W_SC2 = 170, W_DI = 172, W_PER = 178 };

size_t dq_fuse_workspace(size_t n) { return (W_PER + 10) * n; }

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
    if (dq_chol6(A, L, di)) return DQ_OK;
    for (int j = 0; j < 6; j++) A[7 * j] = sym[7 * j] + SPD_MARGIN * fabs(sym[7 * j]);
    return dq_chol6(A, L, di) ? DQ_E_BORDERLINE : DQ_E_NOT_SPD;
}

/* Residuals, their whitened forms e = L^-1 r and the cost at X for the measurements `use`
 * selects (NULL: all), or with want = 0 the others; r, e, sc at offsets ro, eo, so of each
 * measurement's workspace. */
static double evaluate(const double *X, const double *z, double *work, size_t n,
                       const unsigned char *use, int want, int ro, int eo, int so)
{
    double xc[8], total = 0.0;
    dq_conj(X, xc);
    for (size_t i = 0; i < n; i++) {
        if (dq_selected(use, i) != want) continue;
        double *m = work + W_PER * i;
        dq_se3_residual(xc, z + 8 * i, m + ro, m + so);
        dq_lower_solve6(m + W_L, m + W_DI, m + ro, m + eo);
        const double *e = m + eo;
        total += dq_sq6(e);
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
        if (!dq_selected(use, i)) continue;
        double *m = work + W_PER * i, *A = m + W_A;
        double B[36];
        dq_jl_inv(m + ro, m[so], m[so + 1], A);
        dq_whiten_jacobian6(m + W_L, m + W_DI, A, B);
        const double *e = m + eo;
        for (int c = 0; c < 6; c++) {
            double s = 0.0;
            for (int k = 0; k < 6; k++) s += B[6 * k + c] * e[k];
            g[c] += s;
        }
        dq_add_gram_whitened6(B, H);
    }
    dq_mirror6(H);
}

/* The static fit as a Gauss-Newton problem (gn.h): the current point's r, e, sc and a trial
 * point's swap between two slots of each measurement's block. */
typedef struct {
    double *X, Xn[8];
    const double *z;
    double *work;
    size_t n;
    const unsigned char *use;
    double *H, g[6], L[36], di[6];
    int ro, eo, so, rt, et, st;
} static_fit;

static void static_linearize(void *self)
{
    static_fit *f = self;
    linearize(f->work, f->n, f->use, f->ro, f->eo, f->so, f->H, f->g);
}

static int static_step(void *self, double *delta, double *length)
{
    static_fit *f = self;
    if (!dq_chol6(f->H, f->L, f->di)) return DQ_E_SINGULAR;
    dq_lower_solve6(f->L, f->di, f->g, delta);
    dq_upper_solve6(f->L, f->di, delta, delta);
    *length = sqrt(delta[0] * delta[0] + delta[1] * delta[1] + delta[2] * delta[2] +
                   delta[3] * delta[3] + delta[4] * delta[4] + delta[5] * delta[5]);
    return DQ_OK;
}

static int static_trial(void *self, const double *delta, double *cost)
{
    static_fit *f = self;
    if (dq_retract(f->X, delta, f->Xn)) return DQ_E_OVERFLOW;
    *cost = evaluate(f->Xn, f->z, f->work, f->n, f->use, 1, f->rt, f->et, f->st);
    return DQ_OK;
}

static void static_accept(void *self)
{
    static_fit *f = self;
    for (int k = 0; k < 8; k++) f->X[k] = f->Xn[k];
    int t;
    t = f->ro; f->ro = f->rt; f->rt = t;
    t = f->eo; f->eo = f->et; f->et = t;
    t = f->so; f->so = f->st; f->st = t;
}

static const dq_gn_problem STATIC_FIT = {6, static_linearize, static_step, static_trial,
                                         static_accept};

/* Gauss-Newton from X over the selected measurements (see fusion.h); X is updated in place and
 * the selected measurements' r, e, sc at it are left in the W_R, W_E, W_SC slots. *current says
 * whether H is at the returned X (gn.h). */
static int solve(double *X, const double *z, double *work, size_t n, const unsigned char *use,
                 const dq_fuse_params *p, int *status, int *iterations, double *H, int *current)
{
    static_fit f = {X, {0}, z, work, n, use, H, {0}, {0}, {0},
                    W_R, W_E, W_SC, W_R2, W_E2, W_SC2};
    double total = evaluate(X, z, work, n, use, 1, W_R, W_E, W_SC), delta[6];
    int rc = dq_gauss_newton(&STATIC_FIT, &f, delta, p, &total, status, iterations, current);
    if (rc) return rc;
    if (f.ro != W_R)
        for (size_t i = 0; i < n; i++) {
            if (!dq_selected(use, i)) continue;
            double *m = work + W_PER * i;
            for (int k = 0; k < 6; k++) m[W_R + k] = m[f.ro + k];
            for (int k = 0; k < 6; k++) m[W_E + k] = m[f.eo + k];
            for (int k = 0; k < 2; k++) m[W_SC + k] = m[f.so + k];
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
        if (!dq_selected(use, i)) continue;
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
        if (dq_selected(use, i)) { /* own = B^T B, B = L^-1 A: the measurement's information */
            double B[36];
            dq_whiten_jacobian6(m + W_L, m + W_DI, m + W_A, B);
            for (int k = 0; k < 36; k++) m[W_OWN + k] = 0.0;
            dq_add_gram_whitened6(B, m + W_OWN);
            for (int k = 0; k < 36; k++) acc[k] += m[W_OWN + k];
        }
    }
    for (int k = 0; k < 36; k++) acc[k] = 0.0; /* now the sum after j */
    for (size_t jj = n; jj-- > 0;) {
        double *m = work + W_PER * jj;
        int in = dq_selected(use, jj);
        int t = !in || n_in > 1;
        tested[jj] = (unsigned char)t;
        if (!t) {
            nis[jj] = 0.0;
        } else {
            double Hj[36], M[36], dm[6], dn[6], At[36], G[36], K[36], Wr[6], nu[6], T[36], N[36], y[6];
            if (in) {
                for (int k = 0; k < 36; k++) Hj[k] = m[W_PRE + k] + acc[k];
                dq_mirror6(Hj);
            } else {
                for (int k = 0; k < 36; k++) Hj[k] = H[k];
            }
            if (!dq_chol6(Hj, M, dm)) return DQ_E_SINGULAR;
            const double *A = m + W_A;
            for (int r = 0; r < 6; r++)
                for (int c = 0; c < 6; c++) At[6 * r + c] = A[6 * c + r];
            dq_lower_solve_matrix6(M, dm, At, G); /* G = M^-1 A^T, K = G^T G = A Hj^-1 A^T */
            for (int k = 0; k < 36; k++) K[k] = 0.0;
            dq_add_gram6(G, K);
            dq_mirror6(K);
            for (int k = 0; k < 6; k++) nu[k] = m[W_R + k];
            if (in) {
                dq_upper_solve6(m + W_L, m + W_DI, m + W_E, Wr); /* S^-1 r = L^-T e */
                for (int r = 0; r < 6; r++) {
                    double s = 0.0;
                    for (int c = 0; c < 6; c++) s += K[6 * r + c] * Wr[c];
                    nu[r] += s;
                }
            }
            const double *S = cov + 36 * jj;
            for (int k = 0; k < 36; k++) T[k] = S[k] + K[k];
            if (!dq_chol6(T, N, dn)) return DQ_E_SINGULAR;
            dq_lower_solve6(N, dn, nu, y);
            nis[jj] = dq_sq6(y);
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
        if (!dq_chol6(cov + 36 * i, work + W_PER * i + W_L, work + W_PER * i + W_DI)) {
            *bad = i;
            return DQ_E_NOT_SPD;
        }
        if (dq_selected(inlier, i) && n_in++ == 0) first = i;
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
    if (!dq_chol6(H, L, di)) return DQ_E_SINGULAR;
    dq_chol6_inverse(L, di, out->covariance);
    double chi2 = 0.0;
    for (size_t i = 0; i < n; i++) {
        const double *m = work + W_PER * i;
        const double *e = m + W_E;
        double c = dq_sq6(e);
        if (dq_selected(inlier, i)) chi2 += c;
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
            if (dq_selected(inlier, i)) continue;
            double *m = work + W_PER * i;
            dq_jl_inv(m + W_R, m[W_SC], m[W_SC + 1], m + W_A);
        }
        if ((rc = leave_one_out(cov, work, n, inlier, n_in, H, per->nis, per->tested))) return rc;
        if (!dq_finite_n(per->nis, n)) return DQ_E_OVERFLOW;
    }
    return DQ_OK;
}

int dq_pair_distances(const double *z, const double *cov, size_t n, const long long *cand,
                      size_t m, double *d2, size_t *bad)
{
    for (size_t a = 0; a < m; a++) {
        size_t c = (size_t)cand[a];
        double zc[8], r[6], sc[2], A[36], L[36], di[6], e[6];
        dq_conj(z + 8 * c, zc);
        for (size_t j = 0; j < n; j++) {
            dq_se3_residual(zc, z + 8 * j, r, sc);
            for (int k = 0; k < 36; k++) A[k] = cov[36 * c + k] + cov[36 * j + k];
            if (!dq_chol6(A, L, di)) {
                *bad = j;
                return DQ_E_NOT_SPD;
            }
            dq_lower_solve6(L, di, r, e);
            d2[a * n + j] = dq_sq6(e);
        }
    }
    return DQ_OK;
}
