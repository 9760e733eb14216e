/*
 * joint.c — the joint fit of joint.h: Gauss-Newton over the parts' poses and twists, the shared
 * latencies and the extrinsic errors, each measurement whitened by its covariance's Cholesky
 * factor as in motion.c, its Jacobian kept compact (the JC columns it can touch) and scattered
 * into the dense normal equations; then the covariance (the leave-one-out NIS: joint_nis.c).
 */
#include "joint.h"
#include "joint_ctx.h"

#include <math.h>
#include <string.h>

#include "dq.h"
#include "gn.h"
#include "linalg6.h"
#include "se3.h"

size_t dq_joint_dim(const dq_joint_model *m)
{
    size_t d = 0;
    for (size_t p = 0; p < m->parts; p++) d += m->part[p].twist ? 12 : 6;
    return d + m->k + 6 * m->m;
}

/* The groups of the measurements (G_PER above): each measurement's (J_GRP) and each group's
 * measurement, offset and twist; returns their count. */
static size_t joint_groups(const dq_joint_model *m, double *blocks, double *groups)
{
    size_t count = 0, i = 0, off = 0;
    for (size_t p = 0; p < m->parts; p++) {
        const size_t first = count;
        for (size_t j = 0; j < m->part[p].n; j++, i++) {
            size_t g = first;
            while (g < count) {
                const size_t rep = (size_t)groups[G_PER * g + G_REP];
                if (m->lat_slot[rep] == m->lat_slot[i] && m->ext_slot[rep] == m->ext_slot[i]) break;
                g++;
            }
            if (g == count) {
                double *G = groups + G_PER * count++;
                G[G_REP] = (double)i;
                G[G_OFF] = (double)off;
                G[G_TWIST] = m->part[p].twist;
            }
            blocks[J_PER * i + J_GRP] = (double)g;
        }
        off += m->part[p].twist ? 12 : 6;
    }
    return count;
}

/* At most this many groups: per part, its measurements or the (latency, extrinsic) pairs. */
static size_t joint_max_groups(const dq_joint_model *m)
{
    size_t pairs = (m->k + 1) * (m->m + 1), total = 0;
    for (size_t p = 0; p < m->parts; p++) total += m->part[p].n < pairs ? m->part[p].n : pairs;
    return total;
}

size_t dq_joint_workspace(size_t N, const dq_joint_model *m, int nis)
{
    size_t D = dq_joint_dim(m);
    return J_PER * N + G_PER * joint_max_groups(m) + 3 * D * D + 6 * D + 14 * m->parts + m->k +
           (16 + E_PER) * m->m + (nis ? N * D * D : 0);
}

/* The state columns of measurement i's compact columns, for its part's offset and twist. */
void joint_map(const joint_ctx *c, size_t i, int off, int twist, int *map)
{
    const long long s = c->m->ext_slot[i], l = c->m->lat_slot[i];
    for (int a = 0; a < 6; a++) {
        map[a] = off + a;
        map[6 + a] = twist ? off + 6 + a : -1;
        map[13 + a] = s >= 0 ? c->ext + 6 * (int)s + a : -1;
    }
    map[12] = l >= 0 ? c->lat + (int)l : -1;
}

/* Shift = Ehat E^-1 and the extrinsics' prior residuals at Ehat; returns their prior cost. */
static double joint_extrinsics(const joint_ctx *c, const double *Ehat)
{
    const dq_joint_model *m = c->m;
    double total = 0.0;
    for (size_t s = 0; s < m->m; s++) {
        double Ec[8], *pr = c->eres + E_PER * s;
        const double *I = m->E_info + 36 * s;
        dq_conj(m->E + 8 * s, Ec);
        dq_mul(Ehat + 8 * s, Ec, c->shift + 8 * s);
        dq_se3_residual(Ec, Ehat + 8 * s, pr + E_R, pr + E_SC);
        for (int a = 0; a < 6; a++) {
            double t = 0.0;
            for (int b = 0; b < 6; b++) t += I[6 * a + b] * pr[b];
            total += pr[a] * t;
        }
    }
    return total;
}

/* The latencies' and twists' prior cost. */
static double joint_prior_cost(const joint_ctx *c, const double *V, const double *L)
{
    const dq_joint_model *m = c->m;
    double total = 0.0;
    for (size_t j = 0; j < m->k; j++)
        total += m->prior_w[j] * (L[j] - m->prior[j]) * (L[j] - m->prior[j]);
    for (size_t p = 0; p < m->parts; p++) {
        const double *Tw = m->part[p].twist_w, *Vp = V + 6 * p;
        if (!m->part[p].twist || !Tw) continue;
        for (int a = 0; a < 6; a++) {
            double t = 0.0;
            for (int b = 0; b < 6; b++) t += Tw[6 * a + b] * Vp[b];
            total += Vp[a] * t;
        }
    }
    return total;
}

/* Residuals and whitened residuals at (X, V, L) and the shift of joint_extrinsics of the
 * inliers (want = 1) or the others (want = 0); returns their cost. */
static double joint_evaluate(const joint_ctx *c, const double *X, const double *V,
                             const double *L, int want)
{
    const dq_joint_model *m = c->m;
    double total = 0.0;
    size_t i = 0;
    for (size_t p = 0; p < m->parts; p++) {
        const double *Xp = X + 8 * p, *Vp = V + 6 * p;
        for (size_t j = 0; j < m->part[p].n; j++, i++) {
            if (dq_selected(c->inlier, i) != want) continue;
            double *b = c->blocks + J_PER * i;
            double dt = m->stamp[i] - (m->lat_slot[i] >= 0 ? L[m->lat_slot[i]] : m->latency[i]);
            double h[6], P[8], Pc[8], W[8];
            for (int a = 0; a < 6; a++) h[a] = 0.5 * (dt * Vp[a]);
            dq_exp(h, b + J_EXP);
            dq_mul(Xp, b + J_EXP, P);
            dq_conj(P, Pc);
            const double *w = c->z + 8 * i;
            if (m->ext_slot[i] >= 0) {
                double M[8];
                dq_mul(c->shift + 8 * m->ext_slot[i], w, M);
                dq_normalize(M, W);
                w = W;
            }
            dq_se3_residual(Pc, w, b + J_R, b + J_SC);
            dq_lower_solve6(b + J_L, b + J_DI, b + J_R, b + J_E);
            total += dq_sq6(b + J_E);
            b[J_DT] = dt;
        }
    }
    return total;
}

/* C = s A B for 6 x 6 A and B (B's rows ldb apart, C's ldc) whose upper-right 3 x 3 blocks
 * are zero (Jl^-1, its whitened form, adjoints, Jr), as C's is: the zeros' products skipped. */
static inline void mul_lower6(const double *restrict A, const double *restrict B, int ldb,
                              double s, double *restrict C, int ldc)
{
    for (int a = 0; a < 6; a++) {
        const int rot = a < 3 ? 3 : 6;   /* A's row a is zero from column rot on */
        for (int col = 0; col < 3; col++) {
            double t = 0.0;
            for (int k = 0; k < rot; k++) t += A[6 * a + k] * B[ldb * k + col];
            C[ldc * a + col] = s * t;
        }
        for (int col = 3; col < 6; col++) {
            double t = 0.0;
            for (int k = 3; k < rot; k++) t += A[6 * a + k] * B[ldb * k + col];
            C[ldc * a + col] = s * t;
        }
    }
}

/* Measurement i's whitened compact Jacobian L^-1 G into its block, and G itself (6 x dim,
 * through map) into Gout when not NULL. */
static void joint_jacobian(const joint_ctx *c, size_t i, const double *Vp, int twist,
                           const int *map, double *Gout)
{
    double *b = c->blocks + J_PER * i, *Gw = b + J_G;
    const double dt = b[J_DT], *E = b + J_EXP, *r = b + J_R;
    double A[36], Aw[36], Ad[36], Ei[8], Bc[6 * 13];
    dq_jl_inv(r, b[J_SC], b[J_SC + 1], A);
    dq_whiten_jacobian6(b + J_L, b + J_DI, A, Aw);
    dq_conj(E, Ei);
    dq_adjoint(Ei, Ad);   /* Ad(Exp(-dt V)) */
    for (int a = 0; a < 6; a++)
        for (int k = 0; k < 6; k++) Bc[13 * a + k] = Ad[6 * a + k];
    if (twist) {
        double x[6];
        for (int k = 0; k < 6; k++) x[k] = dt * Vp[k];
        dq_jr_scaled(x, E[1] * E[1] + E[2] * E[2] + E[3] * E[3], E[0], dt, Bc + 6, 13);
    } else {
        for (int a = 0; a < 6; a++)
            for (int k = 6; k < 12; k++) Bc[13 * a + k] = 0.0;
    }
    const int lat = c->m->lat_slot[i] >= 0;
    for (int a = 0; a < 6; a++) Bc[13 * a + 12] = lat ? -Vp[a] : 0.0;
    mul_lower6(Aw, Ad, 6, 1.0, Gw, JC);
    if (twist) mul_lower6(Aw, Bc + 6, 13, 1.0, Gw + 6, JC);
    for (int a = 0; a < 6; a++) {
        double s = 0.0;
        if (lat)
            for (int k = 0; k < 6; k++) s += Aw[6 * a + k] * Bc[13 * k + 12];
        Gw[JC * a + 12] = s;
        if (!twist)
            for (int col = 6; col < 12; col++) Gw[JC * a + col] = 0.0;
    }
    double Ar[36], Arw[36], mr[6];
    const int ext = c->m->ext_slot[i] >= 0;
    if (ext) {   /* -Jr^-1(r) A, Jr^-1(r) = Jl^-1(-r) */
        for (int k = 0; k < 6; k++) mr[k] = -r[k];
        dq_jl_inv(mr, b[J_SC], b[J_SC + 1], Ar);
        dq_whiten_jacobian6(b + J_L, b + J_DI, Ar, Arw);
        mul_lower6(Arw, b + J_A, 6, -1.0, Gw + 13, JC);
    } else {
        for (int a = 0; a < 6; a++)
            for (int col = 13; col < JC; col++) Gw[JC * a + col] = 0.0;
    }
    if (!Gout) return;
    const int dim = c->dim;
    for (int a = 0; a < 6 * dim; a++) Gout[a] = 0.0;
    for (int col = 0; col < JC; col++) {
        if (map[col] < 0) continue;
        for (int a = 0; a < 6; a++) {
            double s = 0.0;
            if (col < 13)
                for (int k = 0; k < 6; k++) s += A[6 * a + k] * Bc[13 * k + col];
            else
                for (int k = 0; k < 6; k++) s -= Ar[6 * a + k] * b[J_A + 6 * k + col - 13];
            Gout[dim * a + map[col]] = s;
        }
    }
}

/* The columns of map that are in the state: their compact indices and state columns,
 * ascending in both. */
int joint_present(const int *map, int *cols, int *at)
{
    int nc = 0;
    for (int col = 0; col < JC; col++)
        if (map[col] >= 0) {
            cols[nc] = col;
            at[nc++] = map[col];
        }
    return nc;
}

/* M += B^T B (upper triangle, JC x JC) and M's gradient += B^T e of a whitened compact
 * Jacobian B whose columns from w on are zero; w is a constant where this is inlined. */
static inline void gram(const double *restrict B, const double *restrict e, double *restrict M,
                        const int w)
{
    /* B's first three rows are zero in the translation columns (mul_lower6's blocks) */
    static const int rot[10] = {0, 1, 2, 6, 7, 8, 12, 13, 14, 15};
    const int nr = w == JC ? 10 : w == 13 ? 7 : 6;
    for (int k = 0; k < 3; k++) {
        const double *row = B + JC * k;
        for (int a = 0; a < nr; a++) {
            const double ra = row[rot[a]];
            M[G_G + rot[a]] += ra * e[k];
            for (int bb = a; bb < nr; bb++) M[JC * rot[a] + rot[bb]] += ra * row[rot[bb]];
        }
    }
    for (int k = 3; k < 6; k++) {
        const double *row = B + JC * k;
        for (int a = 0; a < w; a++) {
            const double ra = row[a];
            M[G_G + a] += ra * e[k];
            for (int bb = a; bb < w; bb++) M[JC * a + bb] += ra * row[bb];
        }
    }
}

/* The information H (mirrored) and gradient g of the inliers and the priors at the point last
 * evaluated, the inliers' Jacobians kept in their blocks. */
static void joint_linearize(const joint_ctx *c, const double *V, const double *L, double *H,
                            double *g)
{
    const dq_joint_model *m = c->m;
    const int dim = c->dim;
    for (int k = 0; k < dim * dim; k++) H[k] = 0.0;
    for (int k = 0; k < dim; k++) g[k] = 0.0;
    for (size_t q = 0; q < c->ngroups; q++)
        for (int k = 0; k < G_REP; k++) c->groups[G_PER * q + k] = 0.0;
    size_t i = 0;
    for (size_t p = 0; p < m->parts; p++) {
        const int twist = m->part[p].twist;
        for (size_t j = 0; j < m->part[p].n; j++, i++) {
            if (!dq_selected(c->inlier, i)) continue;
            joint_jacobian(c, i, V + 6 * p, twist, NULL, NULL);
            const double *b = c->blocks + J_PER * i;
            double *G = c->groups + G_PER * (size_t)b[J_GRP];
            if (m->ext_slot[i] >= 0) gram(b + J_G, b + J_E, G, JC);
            else if (m->lat_slot[i] >= 0) gram(b + J_G, b + J_E, G, 13);
            else gram(b + J_G, b + J_E, G, 12);   /* no latency: column 12 is zero */
        }
    }
    for (size_t q = 0; q < c->ngroups; q++) {
        const double *G = c->groups + G_PER * q;
        int map[JC], cols[JC], at[JC];
        joint_map(c, (size_t)G[G_REP], (int)G[G_OFF], (int)G[G_TWIST], map);
        const int nc = joint_present(map, cols, at);
        for (int a = 0; a < nc; a++) {
            g[at[a]] += G[G_G + cols[a]];
            for (int bb = a; bb < nc; bb++) H[dim * at[a] + at[bb]] += G[JC * cols[a] + cols[bb]];
        }
    }
    joint_prior_terms(c, V, L, H, g);
    dq_mirror(H, dim);
}

/* H += the priors' information (upper triangle at least), g += their part of the descent
 * direction: the latencies', the twists', the extrinsics' at the point last evaluated. */
void joint_prior_terms(const joint_ctx *c, const double *V, const double *L, double *H,
                       double *g)
{
    const dq_joint_model *m = c->m;
    const int dim = c->dim;
    int off = 0;
    for (size_t p = 0; p < m->parts; p++) {
        const int twist = m->part[p].twist;
        const double *Tw = m->part[p].twist_w, *Vp = V + 6 * p;
        if (twist && Tw)
            for (int a = 0; a < 6; a++) {
                double s = 0.0;
                for (int bb = 0; bb < 6; bb++) {
                    H[dim * (off + 6 + a) + off + 6 + bb] += Tw[6 * a + bb];
                    s += Tw[6 * a + bb] * Vp[bb];
                }
                g[off + 6 + a] -= s;
            }
        off += twist ? 12 : 6;
    }
    for (size_t j = 0; j < m->k; j++) {
        const int col = c->lat + (int)j;
        H[dim * col + col] += m->prior_w[j];
        g[col] -= m->prior_w[j] * (L[j] - m->prior[j]);
    }
    for (size_t s = 0; s < m->m; s++) {
        const double *pr = c->eres + E_PER * s, *I = m->E_info + 36 * s;
        double Jp[36], JtI[36], mp[6];
        for (int k = 0; k < 6; k++) mp[k] = -pr[E_R + k];
        dq_jl_inv(mp, pr[E_SC], pr[E_SC + 1], Jp);   /* Jr^-1(p_s) */
        for (int a = 0; a < 6; a++)
            for (int bb = 0; bb < 6; bb++) {
                double t = 0.0;
                for (int k = 0; k < 6; k++) t += Jp[6 * k + a] * I[6 * k + bb];
                JtI[6 * a + bb] = t;
            }
        const int e0 = c->ext + 6 * (int)s;
        for (int a = 0; a < 6; a++) {
            double t = 0.0;
            for (int k = 0; k < 6; k++) t += JtI[6 * a + k] * pr[E_R + k];
            g[e0 + a] -= t;
            for (int bb = 0; bb < 6; bb++) {
                double h = 0.0;
                for (int k = 0; k < 6; k++) h += JtI[6 * a + k] * Jp[6 * k + bb];
                H[dim * (e0 + a) + e0 + bb] += h;
            }
        }
    }
}

/* The joint fit as a Gauss-Newton problem (gn.h): every part's pose and twist, the latencies
 * and the extrinsics, and a trial point's Xn, Vn, Ln, En. */
typedef struct {
    const joint_ctx *c;
    int ext;
    double *X, *V, *L, *Ehat;
    double *Xn, *Vn, *Ln, *En;
    double *H, *g, *Lh, *dh;
} joint_fit;

static void joint_fit_linearize(void *self)
{
    joint_fit *f = self;
    joint_linearize(f->c, f->V, f->L, f->H, f->g);
}

static int joint_fit_step(void *self, double *delta, double *length)
{
    joint_fit *f = self;
    return dq_newton_step(f->H, f->g, f->c->dim, f->Lh, f->dh, delta, length);
}

static int joint_fit_trial(void *self, const double *delta, double *cost)
{
    const joint_fit *t = self;
    const joint_ctx *c = t->c;
    const dq_joint_model *m = c->m;
    int off = 0;
    for (size_t q = 0; q < m->parts; q++) {
        if (dq_retract(t->X + 8 * q, delta + off, t->Xn + 8 * q)) return DQ_E_OVERFLOW;
        for (int j = 0; j < 6; j++)
            t->Vn[6 * q + j] = t->V[6 * q + j] + (m->part[q].twist ? delta[off + 6 + j] : 0.0);
        off += m->part[q].twist ? 12 : 6;
    }
    for (int j = 0; j < (int)m->k; j++) t->Ln[j] = t->L[j] + delta[c->lat + j];
    for (size_t s = 0; s < m->m; s++)
        if (dq_retract(t->Ehat + 8 * s, delta + t->ext + 6 * (int)s, t->En + 8 * s))
            return DQ_E_OVERFLOW;
    *cost = joint_extrinsics(c, t->En) + joint_evaluate(c, t->Xn, t->Vn, t->Ln, 1) +
            joint_prior_cost(c, t->Vn, t->Ln);
    return DQ_OK;
}

static void joint_fit_accept(void *self)
{
    joint_fit *f = self;
    const dq_joint_model *m = f->c->m;
    memcpy(f->X, f->Xn, sizeof(double) * 8 * m->parts);
    memcpy(f->V, f->Vn, sizeof(double) * 6 * m->parts);
    memcpy(f->L, f->Ln, sizeof(double) * m->k);
    memcpy(f->Ehat, f->En, sizeof(double) * 8 * m->m);
}

/* Each measurement's covariance factor and, seen through an uncertain extrinsic, its adjoint
 * A = Ad(W^-1 E_s) into its block (both fixed for the whole fit); the index of a covariance
 * that is not positive definite in *bad, DQ_E_NO_INLIERS when no measurement is an inlier. */
static int joint_blocks(const joint_ctx *c, const double *cov, size_t *bad)
{
    const dq_joint_model *m = c->m;
    size_t n_in = 0;
    for (size_t i = 0; i < c->N; i++) {
        double *b = c->blocks + J_PER * i;
        if (!dq_chol6(cov + 36 * i, b + J_L, b + J_DI)) {
            *bad = i;
            return DQ_E_NOT_SPD;
        }
        if (m->ext_slot[i] >= 0) {
            double zc[8], T[8];
            dq_conj(c->z + 8 * i, zc);
            dq_mul(zc, m->E + 8 * m->ext_slot[i], T);
            dq_adjoint(T, b + J_A);
        }
        if (dq_selected(c->inlier, i)) n_in++;
    }
    return n_in == 0 ? DQ_E_NO_INLIERS : DQ_OK;
}

/* Everything at the estimate the solver left: the others' residuals, the Jacobians asked for
 * (G, or the others' for the leave-one-out NIS: the inliers' are the last linearisation's) and
 * each measurement's cost, dt and residual. */
static void joint_at_estimate(const joint_ctx *c, const double *X, const double *V,
                              const double *L, const dq_joint_outputs *per, int want_nis)
{
    const dq_joint_model *m = c->m;
    joint_evaluate(c, X, V, L, 0);
    if (per->G || want_nis) {
        size_t i = 0;
        int off = 0;
        for (int q = 0; q < (int)m->parts; q++) {
            const int twist = m->part[q].twist;
            for (size_t j = 0; j < m->part[q].n; j++, i++) {
                if (!per->G && dq_selected(c->inlier, i)) continue;   /* theirs are current */
                int map[JC];
                joint_map(c, i, off, twist, map);
                joint_jacobian(c, i, V + 6 * q, twist, map,
                               per->G ? per->G + 6 * (size_t)c->dim * i : NULL);
            }
            off += twist ? 12 : 6;
        }
    }
    for (size_t i = 0; i < c->N; i++) {
        const double *b = c->blocks + J_PER * i;
        if (per->cost) per->cost[i] = dq_sq6(b + J_E);
        if (per->dt) per->dt[i] = b[J_DT];
        if (per->residuals) memcpy(per->residuals + 6 * i, b + J_R, 6 * sizeof(double));
    }
}

int dq_joint_fit(const double *z, const double *cov, const unsigned char *inlier, size_t N,
                 const dq_joint_model *m, const dq_fuse_params *p, double *work,
                 dq_taken *taken, dq_joint_state *st, const dq_joint_outputs *per, size_t *bad)
{
    const int dim = (int)dq_joint_dim(m), k = (int)m->k, K = (int)m->parts;
    const int ext = dim - 6 * (int)m->m;
    double *groups = work + J_PER * N;
    double *H = groups + G_PER * joint_max_groups(m), *Lh = H + dim * dim, *inv = Lh + dim * dim;
    double *g = inv + dim * dim + 2 * dim, *delta = g + dim, *dh = delta + dim, *Pg = dh + dim;
    double *Xn = Pg + dim, *Vn = Xn + 8 * K, *Ln = Vn + 6 * K, *En = Ln + k;
    double *shift = En + 8 * m->m, *eres = shift + 8 * m->m, *pre = eres + E_PER * m->m;
    joint_ctx c = {m, z, inlier, N, dim, ext - k, ext, work, groups,
                   joint_groups(m, work, groups), shift, eres};
    int rc = joint_blocks(&c, cov, bad);
    if (rc) return rc;
    double *X = st->X, *V = st->V, *L = st->L, *Ehat = st->Ehat;
    if (!st->ehat_given) memcpy(Ehat, m->E, sizeof(double) * 8 * m->m);
    double total = joint_extrinsics(&c, Ehat) + joint_evaluate(&c, X, V, L, 1) +
                   joint_prior_cost(&c, V, L);
    joint_fit f = {&c, ext, X, V, L, Ehat, Xn, Vn, Ln, En, H, g, Lh, dh};
    const dq_gn_problem problem = {dim, joint_fit_linearize, joint_fit_step, joint_fit_trial,
                                   joint_fit_accept};
    int current;
    rc = dq_gauss_newton(&problem, &f, delta, p, &total, &st->status, &st->iterations, &current);
    if (rc) return rc;
    if (!current) joint_linearize(&c, V, L, H, g);   /* H and g at the estimate, always */
    const int want_nis = per->nis && per->tested;
    joint_at_estimate(&c, X, V, L, per, want_nis);
    st->chi2 = total;
    memcpy(st->H, H, sizeof(double) * dim * dim);
    memcpy(st->g, g, sizeof(double) * dim);
    if (!dq_finite_n(X, 8 * (size_t)K) || !dq_finite_n(V, 6 * (size_t)K) ||
        !dq_finite_n(L, (size_t)k) || !dq_finite_n(Ehat, 8 * m->m) ||
        !dq_finite_n(H, (size_t)dim * dim) || !dq_finite_n(g, (size_t)dim) ||
        !(total * 0.0 == 0.0))
        return DQ_E_OVERFLOW;
    if (!dq_spd_inverse(H, dim, inv, st->P)) return DQ_E_SINGULAR;
    if (want_nis) {
        for (int a = 0; a < dim; a++) {
            double s = 0.0;
            for (int q = 0; q < dim; q++) s += st->P[dim * a + q] * g[q];
            Pg[a] = s;
        }
        rc = joint_leave_one_out(&c, V, L, st->P, Pg, H, pre, taken, per);
        if (rc) return rc;
        if (!dq_finite_n(per->nis, N)) return DQ_E_OVERFLOW;
    }
    return DQ_OK;
}

int dq_joint_linearized(const double *z, const double *cov, const unsigned char *inlier,
                        size_t N, const dq_joint_model *m, double *work,
                        const dq_joint_state *st, double *H, double *g, size_t *bad)
{
    const int dim = (int)dq_joint_dim(m), k = (int)m->k;
    const int ext = dim - 6 * (int)m->m;
    double *groups = work + J_PER * N;
    double *shift = groups + G_PER * joint_max_groups(m), *eres = shift + 8 * m->m;
    joint_ctx c = {m, z, inlier, N, dim, ext - k, ext, work, groups,
                   joint_groups(m, work, groups), shift, eres};
    int rc = joint_blocks(&c, cov, bad);
    if (rc && rc != DQ_E_NO_INLIERS) return rc;
    joint_extrinsics(&c, st->Ehat);
    joint_evaluate(&c, st->X, st->V, st->L, 1);
    joint_linearize(&c, st->V, st->L, H, g);
    return DQ_OK;
}
