/*
 * store.c — the per-body index of a live stream's store (store.h).
 */
#include "store.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

static int grow_bodies(dq_store_index *x, size_t count)
{
    size_t size = x->count ? x->count : 16;
    while (size < count) size *= 2;
    dq_store_body *b = realloc(x->bodies, size * sizeof *b);
    if (!b) return -1;
    memset(b + x->count, 0, (size - x->count) * sizeof *b);
    x->bodies = b;
    x->count = size;
    return 0;
}

static int grow_body(dq_store_body *b)
{
    size_t size = b->size ? 2 * b->size : 16;
    int64_t *rows = realloc(b->rows, size * sizeof *rows);
    if (!rows) return -1;
    b->rows = rows;
    double *reach = realloc(b->reach, size * sizeof *reach);
    if (!reach) return -1;      /* rows grown, size not: still consistent */
    b->reach = reach;
    b->size = size;
    return 0;
}

int dq_store_push(dq_store_index *x, int64_t body, int64_t row, double taken)
{
    if ((size_t)body >= x->count && grow_bodies(x, (size_t)body + 1) < 0) return -1;
    dq_store_body *b = &x->bodies[body];
    if (b->used == b->size && grow_body(b) < 0) return -1;
    b->rows[b->used] = row;
    /* the larger of taken and the reach before it: max(), as NumPy's maximum.accumulate */
    b->reach[b->used] = b->used && !(taken > b->reach[b->used - 1]) ? b->reach[b->used - 1]
                                                                      : taken;
    b->used++;
    return 0;
}

size_t dq_store_after(const dq_store_index *x, int64_t body, double lo, const int64_t **rows)
{
    *rows = NULL;
    if (body < 0 || (size_t)body >= x->count) return 0;
    const dq_store_body *b = &x->bodies[body];
    size_t a = 0, z = b->used;        /* the first reach >= lo: reach ascends */
    while (a < z) {
        size_t mid = a + (z - a) / 2;
        if (b->reach[mid] < lo)
            a = mid + 1;
        else
            z = mid;
    }
    *rows = b->rows + a;
    return b->used - a;
}

size_t dq_store_count(const dq_store_index *x, int64_t body)
{
    return body >= 0 && (size_t)body < x->count ? x->bodies[body].used : 0;
}

void dq_store_live(const dq_store_index *x, const double *taken, const double *newest,
                   double window, long cap, size_t n, unsigned char *live)
{
    memset(live, 0, n);
    for (size_t k = 0; k < x->count; k++) {
        const dq_store_body *b = &x->bodies[k];
        if (!b->used) continue;
        double lo = newest[k] - window;
        long kept = 0;
        for (size_t i = b->used; i-- > 0;) {      /* newest arrival first, for the cap */
            int64_t r = b->rows[i];
            if ((size_t)r >= n || !(taken[r] >= lo)) continue;
            if (cap >= 0 && kept >= cap) continue;
            live[r] = 1;
            kept++;
        }
    }
}

/* The earliest of these rows of each body without a newest one (+inf elsewhere): first[]. */
static void earliest(const double *newest, size_t bodies, const int64_t *body,
                     const double *taken, size_t n, double *first)
{
    for (size_t b = 0; b < bodies; b++) first[b] = INFINITY;
    for (size_t k = 0; k < n; k++)
        if (!isfinite(newest[body[k]]) && taken[k] < first[body[k]]) first[body[k]] = taken[k];
}

int dq_store_plain(double *newest, size_t bodies, const int64_t *body, const double *times,
                   const double *taken, size_t n, double window, double max_time, double jump)
{
    int fresh = 0;
    for (size_t k = 0; k < n; k++) {
        if (body[k] < 0 || (size_t)body[k] >= bodies) return 0;
        if (fabs(times[k]) > max_time) return 0;
        if (!isfinite(newest[body[k]])) fresh = 1;
        else if (taken[k] > newest[body[k]] + jump) return 0;
    }
    if (fresh) {
        double *first = malloc(bodies * sizeof *first);
        if (!first) return -1;
        earliest(newest, bodies, body, taken, n, first);
        int ahead = 0;
        for (size_t k = 0; k < n && !ahead; k++)
            ahead = !isfinite(newest[body[k]]) && taken[k] > first[body[k]] + jump;
        free(first);
        if (ahead) return 0;
    }
    for (size_t k = 0; k < n; k++)
        if (taken[k] > newest[body[k]]) newest[body[k]] = taken[k];
    for (size_t k = 0; k < n; k++)
        if (taken[k] < newest[body[k]] - window) return 0;
    return 1;
}

void dq_store_reset(dq_store_index *x)
{
    for (size_t k = 0; k < x->count; k++) x->bodies[k].used = 0;
}

void dq_store_free(dq_store_index *x)
{
    for (size_t k = 0; k < x->count; k++) {
        free(x->bodies[k].rows);
        free(x->bodies[k].reach);
    }
    free(x->bodies);
    x->bodies = NULL;
    x->count = 0;
}
