/*
 * fusion_harness.c — times dq_fuse (service/csrc/fusion.c) called from C on the problems that
 * bench_fusion_core.py writes into a directory, writes the results back there and prints one
 * JSON object per line.
 *
 * usage: fusion_harness DIR N_PROBLEMS N_MEASUREMENTS SAMPLES
 *   DIR/poses.bin (P x n x 8 doubles), DIR/covariances.bin (P x n x 36) in;
 *   DIR/mean.out (P x 8), DIR/covariance.out (P x 36), DIR/nis.out (P x n) out.
 */
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "dq.h"
#include "fusion.h"
#include "harness_io.h"

/* One pass over all problems; returns seconds per problem. */
static double pass(const double *z, const double *cov, size_t P, size_t n, int with_nis,
                   double *work, double *mean, double *covariance, double *res, double *dist,
                   double *nis, unsigned char *tested, int *iters)
{
    dq_fuse_params p = {1e-12, 100};
    double t0 = now();
    for (size_t k = 0; k < P; k++) {
        dq_fused f;
        dq_fuse_outputs per = {res, dist, with_nis ? nis + n * k : NULL, with_nis ? tested : NULL};
        size_t bad;
        if (dq_fuse(z + 8 * n * k, cov + 36 * n * k, NULL, n, &p, work, &f, &per, &bad)) {
            fprintf(stderr, "dq_fuse failed on problem %zu\n", k);
            exit(3);
        }
        memcpy(mean + 8 * k, f.mean, sizeof f.mean);
        memcpy(covariance + 36 * k, f.covariance, sizeof f.covariance);
        iters[k] = f.iterations;
    }
    return (now() - t0) / (double)P;
}

int main(int argc, char **argv)
{
    if (argc != 5) {
        fprintf(stderr, "usage: %s DIR N_PROBLEMS N_MEASUREMENTS SAMPLES\n", argv[0]);
        return 2;
    }
    dir = argv[1];
    size_t P = (size_t)atol(argv[2]), n = (size_t)atol(argv[3]);
    int samples = atoi(argv[4]);
    size_t nz, ns;
    double *z = load("poses", &nz), *cov = load("covariances", &ns);
    if (nz != P * n * 8 || ns != P * n * 36) {
        fprintf(stderr, "inputs do not hold %zu problems of %zu measurements\n", P, n);
        return 2;
    }
    double *work = malloc(sizeof(double) * dq_fuse_workspace(n));
    double *mean = malloc(sizeof(double) * 8 * P), *covariance = malloc(sizeof(double) * 36 * P);
    double *res = malloc(sizeof(double) * 6 * n), *dist = malloc(sizeof(double) * n);
    double *nis = malloc(sizeof(double) * n * P);
    unsigned char *tested = malloc(n);
    int *iters = malloc(sizeof(int) * P);
    double *t = malloc(sizeof(double) * (size_t)samples);
    for (int with_nis = 0; with_nis < 2; with_nis++) {
        pass(z, cov, P, n, with_nis, work, mean, covariance, res, dist, nis, tested, iters);
        for (int s = 0; s < samples; s++)
            t[s] = pass(z, cov, P, n, with_nis, work, mean, covariance, res, dist, nis, tested,
                        iters);
        qsort(t, (size_t)samples, sizeof(double), cmpd);
        double it = 0.0;
        for (size_t k = 0; k < P; k++) it += iters[k];
        printf("{\"nis\": %d, \"seconds\": %.9g, \"best\": %.9g, \"iterations\": %.3f}\n",
               with_nis, t[samples / 2], t[0], it / (double)P);
    }
    save("mean", mean, 8 * P);
    save("covariance", covariance, 36 * P);
    save("nis", nis, n * P);
    return 0;
}
