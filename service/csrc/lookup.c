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
#include "joint.h"
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

static int lookup_solve(const dq_lookup_store *s, dq_lookup_body *const *parts, int K,
                        const dq_lookup_args *a, fit_arrays *f, double *Pout)
{
    int rc = lookup_gather(s, parts, K, a, f);
    if (rc) return rc;
    dq_joint_part jp[2];
    for (int q = 0; q < K; q++) jp[q] = (dq_joint_part){parts[q]->n, 1, a->twist_w};
    const dq_joint_model m = {(size_t)K, jp, f->stamp, f->lat, f->lslot, f->eslot, f->k,
                              f->prior, f->prior_w, f->m, f->E, f->E_info};
    const int dim = (int)dq_joint_dim(&m);
    int warm = 0;
    for (int q = 0; q < K; q++) warm |= parts[q]->warm;
    for (size_t j = 0; j < f->k; j++) warm |= a->L[f->lcode[j]] == a->L[f->lcode[j]];
    for (size_t j = 0; j < f->m; j++) warm |= dq_finite_n(a->Ehat + 8 * f->ecode[j], 8);
    const dq_joint_outputs per = {NULL, NULL, NULL, NULL, NULL, NULL};
    for (;; warm = 0) {
        lookup_starts(parts, K, a, f, warm);
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
    return DQ_OK;
}

/* One fit of K parts (1 or 2): its arrays allocated for the parts' rows, solved, freed; Pout
 * the parts' poses' joint covariance (6K x 6K). */
static int lookup_fit(const dq_lookup_store *s, dq_lookup_body *const *parts, int K,
                      dq_lookup_args *a, double *Pout)
{
    fit_arrays f;
    size_t N = 0;
    for (int q = 0; q < K; q++) N += parts[q]->n;
    const size_t nc = s->ncodes, D = 12 * (size_t)K + 7 * nc;
    /* the largest model these rows can make: every source estimated and uncertain */
    dq_joint_part jp[2] = {{0, 1, NULL}, {0, 1, NULL}};
    const dq_joint_model big = {(size_t)K, jp, NULL, NULL, NULL, NULL, nc, NULL, NULL, nc, NULL,
                                NULL};
    jp[0].n = parts[0]->n;
    if (K > 1) jp[1].n = parts[1]->n;
    const size_t doubles = 8 * N + 36 * N + 2 * N + 2 * nc + 8 * nc + 36 * nc + 8 * (size_t)K +
                           6 * (size_t)K + nc + 8 * nc + 2 * D * D + D +
                           dq_joint_workspace(N, &big, 0);
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
    f.H = f.Ehat + 8 * nc;
    f.P = f.H + D * D;
    f.g = f.P + D * D;
    f.work = f.g + D;
    long long *ll = (long long *)(mem + doubles);
    f.lslot = ll;
    f.eslot = ll + N;
    f.slot_of = ll + 2 * N;
    f.lcode = f.slot_of + 2 * nc;
    f.ecode = f.lcode + nc;
    f.taken = (dq_taken *)(ll + longs);
    int rc = lookup_solve(s, parts, K, a, &f, Pout);
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
        rc = lookup_fit(s, parts, 2, a, P);
    } else {
        for (int q = 0; q < 2 && rc == DQ_OK; q++) {
            if (!body[q].n) continue;
            dq_lookup_body *part = &body[q];
            rc = lookup_fit(s, &part, 1, a, Pq);
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
