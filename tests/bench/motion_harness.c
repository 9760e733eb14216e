/*
 * motion_harness.c — times dq_motion_run (service/csrc/motion.c, the fit a tick runs) called from
 * C on the problems bench_fit.py writes into a directory, writes the results back there and
 * prints one JSON object per line (with and without the leave-one-out NIS).
 *
 * usage: motion_harness DIR N_PROBLEMS N_MEASUREMENTS SAMPLES
 *   DIR/poses.bin (P x n x 8), DIR/covariances.bin (P x n x 36), DIR/stamps.bin (P x n),
 *   DIR/latencies.bin (P x n) in: a twist estimated without a prior, no latency estimated, every
 *   measurement an inlier, the tested ones found as the binding's tested=True does;
 *   DIR/mean.out (P x 8), DIR/P.out (P x 144), DIR/nis.out (P x n) out.
 */
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "harness_io.h"
#include "motion.h"

/* The thread's CPU seconds: on a machine shared with other jobs, wall time would count theirs. */
static double cpu_now(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
    return ts.tv_sec + 1e-9 * ts.tv_nsec;
}

/* One pass over all problems; returns seconds per problem. */
static double pass(const double *z, const double *cov, const double *stamp, const double *lat,
                   size_t P, size_t n, int with_nis, double *work, double *zu, dq_taken *taken,
                   double *mean, double *Pm, double *nis)
{
    dq_fuse_params p = {1e-12, 100};
    long long *slot = malloc(sizeof *slot * n);
    unsigned char *tested = malloc(n);
    double *H = malloc(sizeof(double) * 144), *dt = malloc(sizeof(double) * n);
    double *res = malloc(sizeof(double) * 6 * n), *cost = malloc(sizeof(double) * n);
    for (size_t i = 0; i < n; i++) slot[i] = -1;
    double t0 = cpu_now();
    for (size_t k = 0; k < P; k++) {
        dq_motion_model m = {stamp + n * k, lat + n * k, slot, 0, NULL, NULL, 1, NULL};
        dq_motion_run_args a = {z + 8 * n * k, cov + 36 * n * k, NULL, NULL, n, NULL, 1,
                                with_nis ? tested : NULL, &p, work, zu, Pm + 144 * k, taken};
        dq_motion_fitted f;
        f.ell = NULL;
        f.H = H;
        dq_motion_outputs per = {dt, res, cost, NULL, with_nis ? nis + n * k : NULL};
        size_t bad;
        const char *name;
        if (dq_motion_run(&a, &m, &f, &per, &bad, &name)) {
            fprintf(stderr, "dq_motion_run failed on problem %zu\n", k);
            exit(3);
        }
        memcpy(mean + 8 * k, f.mean, sizeof f.mean);
    }
    double t = (cpu_now() - t0) / (double)P;
    free(slot); free(tested); free(H); free(dt); free(res); free(cost);
    return t;
}

int main(int argc, char **argv)
{
    if (argc != 5) {
        fprintf(stderr, "usage: %s DIR N_PROBLEMS N_MEASUREMENTS SAMPLES\n", argv[0]);
        return 2;
    }
    (void)now;   /* harness_io.h's wall clock: the CPU time serves here */
    dir = argv[1];
    size_t P = (size_t)atol(argv[2]), n = (size_t)atol(argv[3]), cnt;
    int samples = atoi(argv[4]);
    double *z = load("poses", &cnt), *cov = load("covariances", &cnt);
    double *stamp = load("stamps", &cnt), *lat = load("latencies", &cnt);
    long long slot0 = -1;
    dq_motion_model m0 = {stamp, lat, &slot0, 0, NULL, NULL, 1, NULL};
    double *work = malloc(sizeof(double) * dq_motion_workspace(n, &m0));
    double *zu = malloc(sizeof(double) * 8 * n), *mean = malloc(sizeof(double) * 8 * P);
    double *Pm = malloc(sizeof(double) * 144 * P), *nis = malloc(sizeof(double) * n * P);
    dq_taken *taken = malloc(sizeof *taken * n);
    double *t = malloc(sizeof(double) * (size_t)samples);
    for (int with_nis = 1; with_nis >= 0; with_nis--) {
        pass(z, cov, stamp, lat, P, n, with_nis, work, zu, taken, mean, Pm, nis);   /* warm-up */
        for (int s = 0; s < samples; s++)
            t[s] = pass(z, cov, stamp, lat, P, n, with_nis, work, zu, taken, mean, Pm, nis);
        qsort(t, (size_t)samples, sizeof *t, cmpd);
        printf("{\"nis\": %d, \"median\": %.9g, \"best\": %.9g}\n", with_nis, t[samples / 2],
               t[0]);
        if (with_nis) {
            save("mean", mean, 8 * P);
            save("P", Pm, 144 * P);
            save("nis", nis, n * P);
        }
    }
    return 0;
}
