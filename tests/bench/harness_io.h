/*
 * harness_io.h — what the C harnesses of the benchmarks share: the input and output files in the
 * directory the Python side gives (DIR/name.bin in, DIR/name.out back), a monotonic clock and a
 * comparison for qsort.
 */
#ifndef DQPOSE_HARNESS_IO_H
#define DQPOSE_HARNESS_IO_H

#include <stdio.h>
#include <stdlib.h>
#include <time.h>

static const char *dir;

static double *load(const char *name, size_t *count)
{
    char path[4096];
    snprintf(path, sizeof path, "%s/%s.bin", dir, name);
    FILE *f = fopen(path, "rb");
    if (!f) { perror(path); exit(2); }
    fseek(f, 0, SEEK_END);
    long len = ftell(f);
    fseek(f, 0, SEEK_SET);
    double *v = malloc((size_t)len);
    if (!v || fread(v, 1, (size_t)len, f) != (size_t)len) { perror(path); exit(2); }
    fclose(f);
    *count = (size_t)len / sizeof(double);
    return v;
}

static void save(const char *name, const double *v, size_t count)
{
    char path[4096];
    snprintf(path, sizeof path, "%s/%s.out", dir, name);
    FILE *f = fopen(path, "wb");
    if (!f || fwrite(v, sizeof(double), count, f) != count) { perror(path); exit(2); }
    fclose(f);
}

static double now(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + 1e-9 * ts.tv_nsec;
}

static int cmpd(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

#endif
