/*
 * lookup.c — lookup.h's Lookup: the bodies' rows gathered from the store, the slots of the
 * latencies and extrinsics they estimate (in order of first appearance), each fit dq_joint_fit's
 * from the warm starts (else the cold ones, and from the cold ones again when a warm start
 * does not converge), then the relative pose and its covariance.
 */
#include "lookup.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "dq.h"
#include "gn.h"
#include "joint.h"
#include "linalg6.h"
#include "pbwrite.h"
#include "se3.h"

static const double IDENT[8] = {1.0, 0, 0, 0, 0, 0, 0, 0};

/* A fit's arrays, one allocation: its rows gathered, the model's slots, the state. */
typedef struct {
    size_t N, k, m;
    int dim;
    double *zu, *S, *stamp, *lat, *prior, *prior_w, *E, *E_info;
    long long *lslot, *eslot, *slot_of;   /* slot_of: ncodes x 2 (latency, extrinsic) */
    long long *lcode, *ecode;             /* each slot's source code */
    double *X, *V, *L, *Ehat, *H, *P, *g, *work;
    dq_taken *taken;
} fit_arrays;

/* Whether source c estimates something two bodies may share (an uncertain extrinsic, an
 * estimated latency). */
static int lookup_shared_source(const dq_lookup_store *s, long long c)
{
    return s->latency_w[c] > 0.0 || s->uncertain[c];
}

/* The parts' rows into f (unit poses, covariances, stamps less the time, configured latencies,
 * slots by first appearance) and their span checked: DQ_OK, DQ_LOOKUP_ELSEWHERE (one instant,
 * or beyond max_extrapolation), or dq_unit's code. */
static int lookup_gather(const dq_lookup_store *s, dq_lookup_body *const *parts, int K,
                         const dq_lookup_args *a, fit_arrays *f)
{
    for (size_t c = 0; c < 2 * s->ncodes; c++) f->slot_of[c] = -1;
    size_t i = 0;
    f->k = f->m = 0;
    for (int q = 0; q < K; q++) {
        double lo = HUGE_VAL, hi = -HUGE_VAL;
        for (size_t j = 0; j < parts[q]->n; j++, i++) {
            const long long r = parts[q]->rows[j], c = s->codes[r];
            int rc = dq_unit(s->poses + 8 * r, f->zu + 8 * i);
            if (rc) return rc;
            memcpy(f->S + 36 * i, s->covs + 36 * r, 36 * sizeof(double));
            f->stamp[i] = s->times[r] - a->at;
            f->lat[i] = s->latency[c];
            const double taken = s->times[r] - s->latency[c];
            lo = taken < lo ? taken : lo;
            hi = taken > hi ? taken : hi;
            long long *ls = f->slot_of + 2 * c, *es = ls + 1;
            if (s->latency_w[c] > 0.0 && *ls < 0) {
                f->lcode[f->k] = c;
                *ls = (long long)f->k++;
            }
            if (s->uncertain[c] && *es < 0) {
                f->ecode[f->m] = c;
                *es = (long long)f->m++;
            }
            f->lslot[i] = *ls;
            f->eslot[i] = *es;
        }
        double out = a->at - hi > lo - a->at ? a->at - hi : lo - a->at;
        if (!(lo < hi) || out > a->max_extrapolation) return DQ_LOOKUP_ELSEWHERE;
    }
    for (size_t j = 0; j < f->k; j++) {
        f->prior[j] = s->latency[f->lcode[j]];
        f->prior_w[j] = s->latency_w[f->lcode[j]];
    }
    for (size_t j = 0; j < f->m; j++) {
        memcpy(f->E + 8 * j, s->E + 8 * f->ecode[j], 8 * sizeof(double));
        memcpy(f->E_info + 36 * j, s->E_info + 36 * f->ecode[j], 36 * sizeof(double));
    }
    return DQ_OK;
}

/* The starts: warm ones where given (warm), else the row taken nearest the time at rest, the
 * latencies at their priors, the extrinsics as configured. */
static void lookup_starts(dq_lookup_body *const *parts, int K, const dq_lookup_args *a,
                          fit_arrays *f, int warm)
{
    size_t i = 0;
    for (int q = 0; q < K; q++) {
        const dq_lookup_body *b = parts[q];
        if (warm && b->warm) {
            double h[6], M[8], X[8];
            for (int j = 0; j < 6; j++) h[j] = 0.5 * ((a->at - b->t0) * b->V[j]);
            dq_exp(h, M);
            dq_mul(b->X, M, X);
            dq_normalize(X, f->X + 8 * q);
            memcpy(f->V + 6 * q, b->V, 6 * sizeof(double));
        } else {
            size_t best = i;
            double nearest = HUGE_VAL;
            for (size_t j = i; j < i + b->n; j++) {
                double d = fabs(f->stamp[j] - f->lat[j]);
                if (d < nearest) {
                    nearest = d;
                    best = j;
                }
            }
            memcpy(f->X + 8 * q, f->zu + 8 * best, 8 * sizeof(double));
            memset(f->V + 6 * q, 0, 6 * sizeof(double));
        }
        i += b->n;
    }
    for (size_t j = 0; j < f->k; j++) {
        const double l = a->L[f->lcode[j]];
        f->L[j] = warm && l == l ? l : f->prior[j];
    }
    for (size_t j = 0; j < f->m; j++) {
        const double *e = a->Ehat + 8 * f->ecode[j];
        if (warm && dq_finite_n(e, 8)) dq_normalize(e, f->Ehat + 8 * j);
        else memcpy(f->Ehat + 8 * j, f->E + 8 * j, 8 * sizeof(double));
    }
}

/* A fit's record (lookup.h): header, then the slots' codes, the state (X, V per part, L,
 * Ehat), the parts' rows and their ids, H and g at the estimate. */
enum { R_DIM, R_K, R_KL, R_M, R_T0, R_N0, R_N1, R_HEAD };

static size_t rec_size(size_t dim, size_t K, size_t k, size_t m, size_t n)
{
    return R_HEAD + k + m + 14 * K + k + 8 * m + 2 * n + dim * dim + dim;
}

/* The record of the fit just made (parts' estimates in f, H and g at them). */
static double *rec_make(const dq_lookup_store *s, dq_lookup_body *const *parts, int K,
                        const dq_lookup_args *a, const fit_arrays *f, size_t dim, size_t *n_out)
{
    const size_t n = f->N, size = rec_size(dim, (size_t)K, f->k, f->m, n);
    double *r = malloc(sizeof(double) * size);
    if (!r) return NULL;
    r[R_DIM] = (double)dim;
    r[R_K] = K;
    r[R_KL] = (double)f->k;
    r[R_M] = (double)f->m;
    r[R_T0] = a->at;
    r[R_N0] = (double)parts[0]->n;
    r[R_N1] = K > 1 ? (double)parts[1]->n : 0.0;
    double *p = r + R_HEAD;
    for (size_t j = 0; j < f->k; j++) *p++ = (double)f->lcode[j];
    for (size_t j = 0; j < f->m; j++) *p++ = (double)f->ecode[j];
    memcpy(p, f->X, sizeof(double) * 8 * K);
    p += 8 * K;
    memcpy(p, f->V, sizeof(double) * 6 * K);
    p += 6 * K;
    memcpy(p, f->L, sizeof(double) * f->k);
    p += f->k;
    memcpy(p, f->Ehat, sizeof(double) * 8 * f->m);
    p += 8 * f->m;
    for (int q = 0; q < K; q++)
        for (size_t j = 0; j < parts[q]->n; j++) *p++ = (double)parts[q]->rows[j];
    for (int q = 0; q < K; q++)
        for (size_t j = 0; j < parts[q]->n; j++) *p++ = (double)s->ids[parts[q]->rows[j]];
    memcpy(p, f->H, sizeof(double) * dim * dim);
    memcpy(p + dim * dim, f->g, sizeof(double) * dim);
    *n_out = size;
    return r;
}

/* The rows of sorted a not in sorted b (their indices in a into out); their count. */
static size_t rows_not_in(const long long *a, size_t na, const long long *b, size_t nb,
                          size_t *out)
{
    size_t i = 0, j = 0, c = 0;
    while (i < na) {
        while (j < nb && b[j] < a[i]) j++;
        if (j >= nb || b[j] != a[i]) out[c++] = i;
        i++;
    }
    return c;
}

/* Whether the rows of sorted a (ids aid) that are also in sorted b hold the same measurements
 * still (a compaction moves rows: the same index, another measurement). */
static int rows_kept(const dq_lookup_store *s, const long long *a, const double *aid, size_t na,
                     const long long *b, size_t nb)
{
    size_t j = 0;
    for (size_t i = 0; i < na; i++) {
        while (j < nb && b[j] < a[i]) j++;
        if (j < nb && b[j] == a[i] && (double)s->ids[a[i]] != aid[i]) return 0;
    }
    return 1;
}

/* H, g of the given rows at state st (X, V, L, Ehat), priors included: the rows' arrays
 * gathered per part (their counts in cnt), dq_joint_linearized. */
static int rows_linearized(const dq_joint_model *m0, const size_t *cnt, const double *z,
                           const double *S, const double *stamp, const double *lat,
                           const long long *ls, const long long *es, const dq_joint_state *st,
                           double *H, double *g)
{
    dq_joint_part jp[2];
    size_t n = 0;
    for (size_t q = 0; q < m0->parts; q++) {
        jp[q] = m0->part[q];
        jp[q].n = cnt[q];
        n += cnt[q];
    }
    const dq_joint_model m = {m0->parts, jp, stamp, lat, ls, es, m0->k, m0->prior, m0->prior_w,
                              m0->m, m0->E, m0->E_info};
    double *work = malloc(sizeof(double) * (dq_joint_workspace(n, &m, 0) + 1));
    if (!work) return DQ_LOOKUP_NOMEM;
    size_t bad = 0;
    int rc = dq_joint_linearized(z, S, NULL, n, &m, work, st, H, g, &bad);
    free(work);
    return rc;
}

/* lookup_refine's start: the record's state (X0, V0, L0, E0, changed here) moved by the step
 * delta, each body's pose carried d s on its twist, into f's start; f unchanged when a step
 * fails. */
static void refine_step(fit_arrays *f, int K, const double *delta, double d, double *X0,
                        double *V0, double *L0, double *E0)
{
    for (int q = 0; q < K; q++) {
        double X[8], h[6], M[8];
        if (dq_retract(X0 + 8 * q, delta + 12 * q, X)) return;
        for (int j = 0; j < 6; j++) V0[6 * q + j] += delta[12 * q + 6 + j];
        for (int j = 0; j < 6; j++) h[j] = 0.5 * (d * V0[6 * q + j]);
        dq_exp(h, M);
        dq_mul(X, M, X0 + 8 * q);
    }
    for (size_t j = 0; j < f->k; j++) L0[j] += delta[12 * K + j];
    for (size_t j = 0; j < f->m; j++) {
        double X[8];
        if (dq_retract(E0 + 8 * j, delta + 12 * K + f->k + 6 * j, X)) return;
        memcpy(E0 + 8 * j, X, sizeof X);
    }
    double Xn[16];
    for (int q = 0; q < K; q++)
        if (dq_normalize(X0 + 8 * q, Xn + 8 * q)) return;
    memcpy(f->X, Xn, sizeof(double) * 8 * (size_t)K);
    for (int q = 0; q < K; q++) memcpy(f->V + 6 * q, V0 + 6 * q, 6 * sizeof(double));
    memcpy(f->L, L0, sizeof(double) * f->k);
    memcpy(f->Ehat, E0, sizeof(double) * 8 * f->m);
}

/* The start from the record rec of this fit's last run: its state moved by one Newton step of
 * the normal equations there (its own time's parametrisation, the rows' stamps from that time:
 * the record's H and g, exact there, less the rows that left, plus those that came), then
 * carried to this time on the twists. Nothing is changed when the record does not describe
 * this fit (its layout, its slots), a row that left is no longer the store's, rows a
 * compaction moved, more than half the rows changed, or the step fails. */
static void lookup_refine(const dq_lookup_store *s, dq_lookup_body *const *parts, int K,
                          const dq_lookup_args *a, fit_arrays *f, const dq_joint_model *m,
                          const double *rec, size_t rec_n)
{
    const size_t dim = dq_joint_dim(m);
    if (!rec || rec_n < R_HEAD || rec[R_DIM] != (double)dim || rec[R_K] != K ||
        rec[R_KL] != (double)f->k || rec[R_M] != (double)f->m)
        return;
    const size_t pn[2] = {(size_t)rec[R_N0], (size_t)rec[R_N1]}, n = pn[0] + pn[1];
    if (rec_n != rec_size(dim, (size_t)K, f->k, f->m, n)) return;
    const double *p = rec + R_HEAD, d = a->at - rec[R_T0];
    for (size_t j = 0; j < f->k; j++)
        if (p[j] != (double)f->lcode[j]) return;
    for (size_t j = 0; j < f->m; j++)
        if (p[f->k + j] != (double)f->ecode[j]) return;
    const double *X0 = p + f->k + f->m, *V0 = X0 + 8 * K, *L0 = V0 + 6 * K, *E0 = L0 + f->k;
    const double *prow = E0 + 8 * f->m, *pid = prow + n, *H0 = pid + n, *g0 = H0 + dim * dim;
    if (!dq_finite_n(X0, 14 * (size_t)K + f->k + 8 * f->m) || !(fabs(d) < HUGE_VAL)) return;
    size_t nmax = 1;
    for (int q = 0; q < K; q++) nmax += pn[q] + parts[q]->n;
    const size_t D = dim;
    const size_t state = 14 * (size_t)K + f->k + 8 * f->m;
    /* scratch: H, g, Ha, ga, Lh, dh, delta, the state; the rows that left and came (at most
     * all of both fits') */
    double *mem = malloc(sizeof(double) * (3 * D * D + 4 * D + state + 46 * nmax) +
                         sizeof(long long) * 2 * nmax + sizeof(size_t) * 3 * nmax);
    if (!mem) return;
    double *H = mem, *g = H + D * D, *Ha = g + D, *ga = Ha + D * D, *Lh = ga + D,
           *dh = Lh + D * D, *delta = dh + D, *X0c = delta + D, *V0c = X0c + 8 * K,
           *L0c = V0c + 6 * K, *E0c = L0c + f->k, *z = X0c + state, *S = z + 8 * nmax,
           *st_ = S + 36 * nmax, *lt = st_ + nmax;
    long long *ls = (long long *)(lt + nmax), *es = ls + nmax;
    size_t *idx = (size_t *)(es + nmax), *came = idx + nmax, *left = came + nmax;
    memcpy(X0c, X0, sizeof(double) * state);
    memcpy(H, H0, sizeof(double) * D * D);
    memcpy(g, g0, sizeof(double) * D);
    const dq_joint_state st = {X0c, V0c, L0c, E0c, NULL, NULL, NULL, 0.0, 0, 0, 1};
    /* the rows that came (this fit's not in the record's: came[], by index in f) and those that
     * left (the record's not in this fit's: left[], by index in the record), per part */
    size_t ncame[2] = {0, 0}, nleft[2] = {0, 0}, nc = 0, nl = 0, first = 0, pfirst = 0;
    for (int q = 0; q < K; q++) {
        long long *prev = ls;      /* scratch: this part's rows in the record */
        for (size_t j = 0; j < pn[q]; j++) prev[j] = (long long)prow[pfirst + j];
        if (!rows_kept(s, prev, pid + pfirst, pn[q], parts[q]->rows, parts[q]->n)) goto done;
        ncame[q] = rows_not_in(parts[q]->rows, parts[q]->n, prev, pn[q], idx);
        for (size_t j = 0; j < ncame[q]; j++) came[nc + j] = first + idx[j];
        nleft[q] = rows_not_in(prev, pn[q], parts[q]->rows, parts[q]->n, idx);
        for (size_t j = 0; j < nleft[q]; j++) left[nl + j] = pfirst + idx[j];
        nc += ncame[q];
        nl += nleft[q];
        first += parts[q]->n;
        pfirst += pn[q];
    }
    if (2 * (nc + nl) > f->N) goto done;
    for (size_t j = 0; j < nc; j++) {
        const size_t i = came[j];
        memcpy(z + 8 * j, f->zu + 8 * i, sizeof(double) * 8);
        memcpy(S + 36 * j, f->S + 36 * i, sizeof(double) * 36);
        st_[j] = f->stamp[i] + d;
        lt[j] = f->lat[i];
        ls[j] = f->lslot[i];
        es[j] = f->eslot[i];
    }
    if (rows_linearized(m, ncame, z, S, st_, lt, ls, es, &st, Ha, ga)) goto done;
    for (size_t j = 0; j < D * D; j++) H[j] += Ha[j];
    for (size_t j = 0; j < D; j++) g[j] += ga[j];
    for (size_t j = 0; j < nl; j++) {
        const size_t i = left[j];
        const long long r = (long long)prow[i];
        if (r < 0 || (size_t)r >= s->rows || (double)s->ids[r] != pid[i]) goto done;
        const long long c = s->codes[r];
        if (c < 0 || (size_t)c >= s->ncodes || dq_unit(s->poses + 8 * r, z + 8 * j)) goto done;
        memcpy(S + 36 * j, s->covs + 36 * r, sizeof(double) * 36);
        st_[j] = s->times[r] - rec[R_T0];
        lt[j] = s->latency[c];
        ls[j] = f->slot_of[2 * c];
        es[j] = f->slot_of[2 * c + 1];
        if ((s->latency_w[c] > 0.0 && ls[j] < 0) || (s->uncertain[c] && es[j] < 0)) goto done;
    }
    if (rows_linearized(m, nleft, z, S, st_, lt, ls, es, &st, Ha, ga)) goto done;
    for (size_t j = 0; j < D * D; j++) H[j] -= Ha[j];
    for (size_t j = 0; j < D; j++) g[j] -= ga[j];
    double len;
    if (dq_newton_step(H, g, (int)D, Lh, dh, delta, &len) || !(len < 1.0)) goto done;
    refine_step(f, K, delta, d, X0c, V0c, L0c, E0c);
done:
    free(mem);
}

/* Whether the record rec is this fit's at this time over the same rows (the same measurements):
 * then its state, H and g are the fit's, which start from there would only confirm, and they
 * are taken outright (P = H^-1 into f->P, work dim^2 + 2 dim). */
static int lookup_kept(const dq_lookup_store *s, dq_lookup_body *const *parts, int K,
                       const dq_lookup_args *a, fit_arrays *f, size_t dim, const double *rec,
                       size_t rec_n, double *work)
{
    if (!rec || rec_n < R_HEAD || rec[R_DIM] != (double)dim || rec[R_K] != K ||
        rec[R_KL] != (double)f->k || rec[R_M] != (double)f->m || rec[R_T0] != a->at ||
        rec[R_N0] != (double)parts[0]->n || (K > 1 && rec[R_N1] != (double)parts[1]->n))
        return 0;
    const size_t n = f->N, state = 14 * (size_t)K + f->k + 8 * f->m;
    if (rec_n != rec_size(dim, (size_t)K, f->k, f->m, n)) return 0;
    const double *p = rec + R_HEAD;
    for (size_t j = 0; j < f->k; j++)
        if (p[j] != (double)f->lcode[j]) return 0;
    for (size_t j = 0; j < f->m; j++)
        if (p[f->k + j] != (double)f->ecode[j]) return 0;
    const double *X0 = p + f->k + f->m, *prow = X0 + state, *pid = prow + n, *H0 = pid + n;
    for (int q = 0, i = 0; q < K; q++)
        for (size_t j = 0; j < parts[q]->n; j++, i++) {
            const long long r = parts[q]->rows[j];
            if (prow[i] != (double)r || pid[i] != (double)s->ids[r]) return 0;
        }
    if (!dq_finite_n(X0, state) || !dq_spd_inverse(H0, (int)dim, work, f->P)) return 0;
    memcpy(f->X, X0, sizeof(double) * 8 * K);
    memcpy(f->V, X0 + 8 * K, sizeof(double) * 6 * K);
    memcpy(f->L, X0 + 14 * K, sizeof(double) * f->k);
    memcpy(f->Ehat, X0 + 14 * K + f->k, sizeof(double) * 8 * f->m);
    memcpy(f->H, H0, sizeof(double) * dim * dim);
    memcpy(f->g, H0 + dim * dim, sizeof(double) * dim);
    return 1;
}

static int lookup_solved(const dq_lookup_store *s, dq_lookup_body *const *parts, int K,
                         dq_lookup_args *a, fit_arrays *f, const dq_joint_model *mp,
                         double *Pout, int slot);

/* One fit of the parts (f's arrays for their rows): gathered, its model's arrays allocated,
 * solved (lookup_solved), freed. */
static int lookup_solve(const dq_lookup_store *s, dq_lookup_body *const *parts, int K,
                        dq_lookup_args *a, fit_arrays *f, double *Pout, int slot)
{
    int rc = lookup_gather(s, parts, K, a, f);
    if (rc) return rc;
    dq_joint_part jp[2];
    for (int q = 0; q < K; q++) jp[q] = (dq_joint_part){parts[q]->n, 1, a->twist_w};
    const dq_joint_model m = {(size_t)K, jp, f->stamp, f->lat, f->lslot, f->eslot, f->k,
                              f->prior, f->prior_w, f->m, f->E, f->E_info};
    const int dim = (int)dq_joint_dim(&m);
    double *dmem = malloc(sizeof(double) * (2 * (size_t)dim * dim + dim +
                                            dq_joint_workspace(f->N, &m, 0)));
    if (!dmem) return DQ_LOOKUP_NOMEM;
    f->H = dmem;
    f->P = f->H + dim * dim;
    f->g = f->P + dim * dim;
    f->work = f->g + dim;
    rc = lookup_solved(s, parts, K, a, f, &m, Pout, slot);
    free(dmem);
    return rc;
}

/* lookup_solve's fit, its arrays allocated (f->H, P, g, work for the model m). */
static int lookup_solved(const dq_lookup_store *s, dq_lookup_body *const *parts, int K,
                         dq_lookup_args *a, fit_arrays *f, const dq_joint_model *mp,
                         double *Pout, int slot)
{
    const dq_joint_model m = *mp;
    const int dim = (int)dq_joint_dim(&m);
    int rc, warm = 0;
    for (int q = 0; q < K; q++) warm |= parts[q]->warm;
    for (size_t j = 0; j < f->k; j++) warm |= a->L[f->lcode[j]] == a->L[f->lcode[j]];
    for (size_t j = 0; j < f->m; j++) warm |= dq_finite_n(a->Ehat + 8 * f->ecode[j], 8);
    warm |= a->rec_in[slot] != NULL;
    const dq_joint_outputs per = {NULL, NULL, NULL, NULL, NULL, NULL};
    if (lookup_kept(s, parts, K, a, f, (size_t)dim, a->rec_in[slot], a->rec_in_n[slot],
                    f->work))
        warm = -1;
    for (; warm >= 0; warm = 0) {
        lookup_starts(parts, K, a, f, warm);
        if (warm) lookup_refine(s, parts, K, a, f, &m, a->rec_in[slot], a->rec_in_n[slot]);
        dq_joint_state st = {f->X, f->V, f->L, f->Ehat, f->H, f->P, f->g, 0.0, 0, 0, 1};
        size_t bad = 0;
        rc = dq_joint_fit(f->zu, f->S, NULL, f->N, &m, &a->p, f->work, f->taken, &st, &per,
                          &bad);
        if (rc == DQ_OK && st.status == DQ_FUSE_CONVERGED) break;
        if (!warm) return DQ_LOOKUP_ELSEWHERE;   /* the other path says why, or answers */
    }
    for (int q = 0; q < K; q++) {
        memcpy(parts[q]->X, f->X + 8 * q, 8 * sizeof(double));
        memcpy(parts[q]->V, f->V + 6 * q, 6 * sizeof(double));
        parts[q]->t0 = a->at;
        for (int r = 0; r < K; r++)
            for (int x = 0; x < 6; x++)
                for (int y = 0; y < 6; y++)
                    Pout[6 * K * (6 * q + x) + 6 * r + y] = f->P[dim * (12 * q + x) + 12 * r + y];
    }
    for (size_t j = 0; j < f->k; j++) a->L[f->lcode[j]] = f->L[j];
    for (size_t j = 0; j < f->m; j++)
        memcpy(a->Ehat + 8 * f->ecode[j], f->Ehat + 8 * j, 8 * sizeof(double));
    free(a->rec_out[slot]);
    a->rec_out[slot] = rec_make(s, parts, K, a, f, (size_t)dim, &a->rec_out_n[slot]);
    return DQ_OK;
}

/* One fit of K parts (1 or 2): its arrays allocated for the parts' rows, solved, freed; Pout
 * the parts' poses' joint covariance (6K x 6K). */
static int lookup_fit(const dq_lookup_store *s, dq_lookup_body *const *parts, int K,
                      dq_lookup_args *a, double *Pout, int slot)
{
    fit_arrays f;
    size_t N = 0;
    for (int q = 0; q < K; q++) N += parts[q]->n;
    const size_t nc = s->ncodes;
    /* the rows' arrays and the sources' (the state's and the normal equations' are sized by
     * the model the rows make: lookup_solve's) */
    const size_t doubles = 8 * N + 36 * N + 2 * N + 2 * nc + 8 * nc + 36 * nc + 8 * (size_t)K +
                           6 * (size_t)K + nc + 8 * nc;
    const size_t longs = 2 * N + 4 * nc;
    double *mem = malloc(sizeof(double) * doubles + sizeof(long long) * longs +
                         sizeof(dq_taken) * (N ? N : 1));
    if (!mem) return DQ_LOOKUP_NOMEM;
    f.N = N;
    f.zu = mem;
    f.S = f.zu + 8 * N;
    f.stamp = f.S + 36 * N;
    f.lat = f.stamp + N;
    f.prior = f.lat + N;
    f.prior_w = f.prior + nc;
    f.E = f.prior_w + nc;
    f.E_info = f.E + 8 * nc;
    f.X = f.E_info + 36 * nc;
    f.V = f.X + 8 * K;
    f.L = f.V + 6 * K;
    f.Ehat = f.L + nc;
    long long *ll = (long long *)(mem + doubles);
    f.lslot = ll;
    f.eslot = ll + N;
    f.slot_of = ll + 2 * N;
    f.lcode = f.slot_of + 2 * nc;
    f.ecode = f.lcode + nc;
    f.taken = (dq_taken *)(ll + longs);
    int rc = lookup_solve(s, parts, K, a, &f, Pout, slot);
    free(mem);
    return rc;
}

/* Whether the two bodies' rows share a source of lookup_shared_source. */
static int lookup_share(const dq_lookup_store *s, const dq_lookup_body *b)
{
    unsigned char *seen = calloc(s->ncodes ? s->ncodes : 1, 1);
    if (!seen) return -1;
    int shared = 0;
    for (size_t j = 0; j < b[0].n; j++) seen[s->codes[b[0].rows[j]]] = 1;
    for (size_t j = 0; j < b[1].n && !shared; j++) {
        const long long c = s->codes[b[1].rows[j]];
        shared = seen[c] && lookup_shared_source(s, c);
    }
    free(seen);
    return shared;
}

int dq_lookup(const dq_lookup_store *s, dq_lookup_body *body, dq_lookup_args *a, double *pose,
              double *cov, int *shared)
{
    double P[144] = {0.0}, Pq[36];
    int rc = DQ_OK;
    *shared = body[0].n && body[1].n ? lookup_share(s, body) : 0;
    if (*shared < 0) return DQ_LOOKUP_NOMEM;
    if (*shared) {
        dq_lookup_body *parts[2] = {&body[0], &body[1]};
        rc = lookup_fit(s, parts, 2, a, P, 2);
    } else {
        for (int q = 0; q < 2 && rc == DQ_OK; q++) {
            if (!body[q].n) continue;
            dq_lookup_body *part = &body[q];
            rc = lookup_fit(s, &part, 1, a, Pq, q);
            for (int x = 0; x < 6; x++)
                for (int y = 0; y < 6; y++) P[12 * (6 * q + x) + 6 * q + y] = Pq[6 * x + y];
        }
    }
    if (rc) return rc;
    const double *Xa = body[0].n ? body[0].X : IDENT, *Xb = body[1].n ? body[1].X : IDENT;
    double Xc[8], Tc[8], Ad[36], J[72], JP[72];
    dq_conj(Xa, Xc);
    dq_mul(Xc, Xb, pose);
    dq_conj(pose, Tc);
    dq_adjoint(Tc, Ad);
    for (int x = 0; x < 6; x++)
        for (int y = 0; y < 6; y++) {
            J[12 * x + y] = -Ad[6 * x + y];
            J[12 * x + 6 + y] = x == y ? 1.0 : 0.0;
        }
    for (int x = 0; x < 6; x++)
        for (int y = 0; y < 12; y++) {
            double t = 0.0;
            for (int z = 0; z < 12; z++) t += J[12 * x + z] * P[12 * z + y];
            JP[12 * x + y] = t;
        }
    for (int x = 0; x < 6; x++)
        for (int y = 0; y < 6; y++) {
            double t = 0.0;
            for (int z = 0; z < 12; z++) t += JP[12 * x + z] * J[12 * y + z];
            cov[6 * x + y] = t;
        }
    for (int x = 0; x < 6; x++)
        for (int y = 0; y < x; y++) cov[6 * x + y] = cov[6 * y + x] =
            0.5 * (cov[6 * x + y] + cov[6 * y + x]);
    return dq_finite_n(pose, 8) && dq_finite_n(cov, 36) ? DQ_OK : DQ_E_OVERFLOW;
}

size_t dq_relative_pose_write(const double *pose, const double *cov, double time,
                              unsigned char *out)
{
    double quat[4], t[3];
    dq_to_pose(pose, quat, t);
    uint8_t *p = out, *len = p + 1; /* pose: always present, at most 67 bytes */
    *p = (uint8_t)(1 << 3 | WT_LEN);
    p += 2;
    p = put_doubles(p, 1, t, 3);
    p = put_doubles(p, 2, quat, 4);
    *len = (uint8_t)(p - len - 1);
    p = put_packed_doubles(p, 2, cov, 36);
    p = put_double(p, 3, time);
    return (size_t)(p - out);
}
