/*
 * harness.c — times the C core (service/csrc) and the floor (floor.c) on the inputs that
 * bench_core.py writes into a directory, writes their results back there (so the Python side
 * can compare them with the Python API and the peers) and prints one JSON object per line.
 *
 * usage: harness DIR
 */
#define _POSIX_C_SOURCE 199309L
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "blend.h"
#include "dq.h"
#include "harness_io.h"

void floor_sclerp(const double *a, const double *b, double tau, double *out);
void floor_sclerp_each(const double *a, const double *b, const double *tau, size_t n, double *out);
void floor_dlb(const double *q, const double *w, size_t n, double *out);
int floor_dib(const double *q, const double *w, size_t n, double tol, int max_iter, double *out);

typedef void (*job_fn)(void *ctx);


#define SAMPLES 21

/* Calls of f to fill a sample of >= min_s seconds (far above the clock resolution); the
 * calibration is the warm-up. */
static int calibrate(job_fn f, void *ctx, double min_s)
{
    int reps = 1;
    for (;;) {
        double t0 = now();
        for (int r = 0; r < reps; r++) f(ctx);
        double dt = now() - t0;
        if (dt >= min_s) return reps;
        reps = dt > 0 ? (int)(reps * 1.1 * min_s / dt) + 1 : reps * 10;
    }
}

/* Median over SAMPLES samples of the time of one call. */
static double median_seconds(job_fn f, void *ctx)
{
    int reps = calibrate(f, ctx, 2e-3);
    double s[SAMPLES];
    for (int k = 0; k < SAMPLES; k++) {
        double t0 = now();
        for (int r = 0; r < reps; r++) f(ctx);
        s[k] = (now() - t0) / reps;
    }
    qsort(s, SAMPLES, sizeof(double), cmpd);

    return s[SAMPLES / 2];
}

/* Median over RATIO_SAMPLES of time(f) / time(g), the samples of f and g taken alternately, so
 * a change of load on a shared machine moves both sides of each ratio alike. Samples are short
 * (>= 0.2 ms), so that most pairs of them run without being preempted by other jobs. */
#define RATIO_SAMPLES 201
static double median_ratio(job_fn f, job_fn g, void *ctx)
{
    int rf = calibrate(f, ctx, 2e-4), rg = calibrate(g, ctx, 2e-4);
    double s[RATIO_SAMPLES];
    for (int k = 0; k < RATIO_SAMPLES; k++) {
        double t0 = now();
        for (int r = 0; r < rf; r++) f(ctx);
        double t1 = now();
        for (int r = 0; r < rg; r++) g(ctx);
        double t2 = now();
        s[k] = ((t1 - t0) / rf) / ((t2 - t1) / rg);
    }
    qsort(s, RATIO_SAMPLES, sizeof(double), cmpd);
    return s[RATIO_SAMPLES / 2];
}

/* ---- jobs ---------------------------------------------------------------------------------- */

typedef struct {
    const double *a, *b, *tau, *w;
    size_t n;
    double *out;
    int iters;
} job;

static void core_sclerp_tau(void *c)
{
    job *j = c;
    dq_sclerp_pair p;
    dq_sclerp_prepare(j->a, j->b, &p);
    for (size_t i = 0; i < j->n; i++) dq_sclerp_eval(&p, j->tau[i], j->out + 8 * i);
}

static void floor_sclerp_tau(void *c)
{
    job *j = c;
    for (size_t i = 0; i < j->n; i++) floor_sclerp(j->a, j->b, j->tau[i], j->out + 8 * i);
}

static void core_sclerp_pairs(void *c)
{
    job *j = c;
    dq_sclerp_pairs(j->a, j->b, j->tau, j->n, j->out);
}

static void floor_sclerp_pairs(void *c)
{
    job *j = c;
    floor_sclerp_each(j->a, j->b, j->tau, j->n, j->out);
}

static void core_dlb(void *c) { job *j = c; dq_dlb(j->a, j->w, j->n, j->out); }
static void floor_dlb_job(void *c) { job *j = c; floor_dlb(j->a, j->w, j->n, j->out); }

static void core_dib(void *c)
{
    job *j = c;
    double res;
    dq_dib(j->a, j->w, j->n, 1e-12, 100, j->out, &j->iters, &res);
}

static void floor_dib_job(void *c) { job *j = c; j->iters = floor_dib(j->a, j->w, j->n, 1e-12, 100, j->out); }

static void core_to_matrix(void *c)
{
    job *j = c;
    for (size_t i = 0; i < j->n; i++) dq_to_matrix(j->a + 8 * i, j->out + 16 * i);
}

static void core_from_matrix(void *c)
{
    job *j = c;
    for (size_t i = 0; i < j->n; i++) dq_from_matrix(j->a + 16 * i, j->out + 8 * i);
}

static void report(const char *op, const char *impl, double sec, double per, int iters)
{
    printf("{\"op\": \"%s\", \"impl\": \"%s\", \"seconds\": %.6e, \"units\": %.0f, \"iters\": %d}\n",
           op, impl, sec, per, iters);
    fflush(stdout);
}

int main(int argc, char **argv)
{
    if (argc != 2) { fprintf(stderr, "usage: harness DIR\n"); return 2; }
    dir = argv[1];
    size_t n;

    /* ScLERP, one pair, many tau */
    double *pair = load("pair", &n);
    size_t nt;
    double *taus = load("taus", &nt);
    double *out = malloc(sizeof(double) * 16 * (nt > 100000 ? nt : 100000));
    job j = {pair, pair + 8, taus, NULL, nt, out, 0};
    report("sclerp_tau", "core", median_seconds(core_sclerp_tau, &j), (double)nt, 0);
    save("sclerp_tau_core", out, 8 * nt);
    report("sclerp_tau", "floor", median_seconds(floor_sclerp_tau, &j), (double)nt, 0);
    save("sclerp_tau_floor", out, 8 * nt);

    /* ScLERP, independent pairs */
    size_t np;
    double *A = load("pairs_a", &np), *B = load("pairs_b", &np), *pt = load("pairs_tau", &np);
    job jp = {A, B, pt, NULL, np, out, 0};
    report("sclerp_pairs", "core", median_seconds(core_sclerp_pairs, &jp), (double)np, 0);
    save("sclerp_pairs_core", out, 8 * np);
    report("sclerp_pairs", "floor", median_seconds(floor_sclerp_pairs, &jp), (double)np, 0);
    save("sclerp_pairs_floor", out, 8 * np);
    printf("{\"op\": \"sclerp_pairs\", \"impl\": \"core/floor\", \"ratio\": %.6e}\n",
           median_ratio(core_sclerp_pairs, floor_sclerp_pairs, &jp));

    /* means */
    const char *sets[] = {"set10", "set1000"};
    for (int s = 0; s < 2; s++) {
        size_t m;
        double *q = load(sets[s], &m);
        m /= 8;
        double *w = malloc(sizeof(double) * m);
        for (size_t i = 0; i < m; i++) w[i] = 1.0 / (double)m;
        job jm = {q, NULL, NULL, w, m, out, 0};
        char op[64];
        snprintf(op, sizeof op, "dlb%zu", m);
        report(op, "core", median_seconds(core_dlb, &jm), 1, 0);
        save(op, out, 8);
        report(op, "floor", median_seconds(floor_dlb_job, &jm), 1, 0);
        snprintf(op, sizeof op, "dib%zu", m);
        /* time first: the call fills jm.iters */
        double sec = median_seconds(core_dib, &jm);
        report(op, "core", sec, (double)m, jm.iters);
        char name[80];
        snprintf(name, sizeof name, "%s_core", op);
        save(name, out, 8);
        sec = median_seconds(floor_dib_job, &jm);
        report(op, "floor", sec, (double)m, jm.iters);
        snprintf(name, sizeof name, "%s_floor", op);
        save(name, out, 8);
    }

    /* conversions */
    size_t nc;
    double *cq = load("conv_dq", &nc);
    nc /= 8;
    job jc = {cq, NULL, NULL, NULL, nc, out, 0};
    report("to_matrix", "core", median_seconds(core_to_matrix, &jc), (double)nc, 0);
    double *cm = malloc(sizeof(double) * 16 * nc);
    memcpy(cm, out, sizeof(double) * 16 * nc);
    jc.a = cm;
    report("from_matrix", "core", median_seconds(core_from_matrix, &jc), (double)nc, 0);
    return 0;
}
