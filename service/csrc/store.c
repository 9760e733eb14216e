/*
 * store.c — the per-body index of a live stream's store (store.h).
 */
#include "store.h"

#include "dq.h"

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
                   double window, long cap, size_t n, unsigned char *live, dq_store_spans *s)
{
    if (live) memset(live, 0, n);
    for (size_t k = 0; k < x->count; k++) {
        const dq_store_body *b = &x->bodies[k];
        if (s) {
            s->oldest[k] = HUGE_VAL;
            s->near[k] = 0;
        }
        if (!b->used) continue;
        double lo = newest[k] - window;
        long kept = 0;
        for (size_t i = b->used; i-- > 0;) {      /* newest arrival first, for the cap */
            int64_t r = b->rows[i];
            if ((size_t)r >= n || !(taken[r] >= lo)) continue;
            if (cap >= 0 && kept >= cap) continue;
            if (live) live[r] = 1;
            if (s) {
                if (taken[r] < s->oldest[k]) s->oldest[k] = taken[r];
                s->near[k] += taken[r] >= newest[k] - s->recent;
            }
            kept++;
        }
    }
}

static void refuse(const dq_store_rows *in, dq_store_refusal *out, size_t *nout, size_t k,
                   int code, double a, double b)
{
    in->ok[k] = 0;
    out[*nout].row = k;
    out[*nout].code = code;
    out[*nout].a = a;
    out[*nout].b = b;
    (*nout)++;
}

/* Whether no origin but r's fed body b within r->jump of `newest` (a stream's rows: always). */
static int alone(const dq_store_body *b, const dq_store_rules *r, double newest)
{
    if (r->anon) return 1;
    double floor = newest - r->jump;
    for (int i = 0; i < b->feeders; i++)
        if (b->feeder[i] != r->origin && b->fed[i] >= floor) return 0;
    return 1;
}

/* Whether a row of r's origin taken at t confirms body b's pending jump (then forgotten);
 * else it is the body's pending jump now. */
static int confirms(dq_store_body *b, const dq_store_rules *r, double t, double newest)
{
    if (b->pending && fabs(t - b->pending_t) <= r->jump
        && (r->anon || b->pending_anon || r->origin != b->pending_origin
            || alone(b, r, newest))) {
        b->pending = 0;
        return 1;
    }
    b->pending = 1;
    b->pending_t = t;
    b->pending_anon = (unsigned char)r->anon;
    b->pending_origin = r->origin;
    return 0;
}

/* The rows taken more than r->jump after their body's newest (the earlier rows of the call
 * counted; a body without one: from its earliest row of the call) refused, unless they confirm
 * its pending jump. top/seen of the bodies: scratch. */
static void jump_check(dq_store_index *x, const dq_store_state *st, const dq_store_rows *in,
                       const dq_store_rules *r, dq_store_refusal *out, size_t *nout)
{
    const int64_t call = x->calls;
    int ahead = 0;
    /* each body's reference: its newest, or its earliest ok row of the call (top) */
    for (size_t k = 0; k < in->n; k++) {
        if (!in->ok[k]) continue;
        dq_store_body *b = &x->bodies[in->body[k]];
        if (b->seen != call) {
            b->seen = call;
            b->top = isfinite(st->newest[in->body[k]]) ? st->newest[in->body[k]] : INFINITY;
            b->suspect = 0;
        }
        if (!isfinite(st->newest[in->body[k]]) && in->taken[k] < b->top) b->top = in->taken[k];
    }
    for (size_t k = 0; k < in->n; k++) {
        if (!in->ok[k]) continue;
        dq_store_body *b = &x->bodies[in->body[k]];
        if (in->taken[k] > b->top + r->jump) b->suspect = ahead = 1;
    }
    if (!ahead) return;
    /* the suspects' rows in order, each against the body's current newest (top from here) */
    for (size_t k = 0; k < in->n; k++) {
        dq_store_body *b = &x->bodies[in->body[k]];
        if (!in->ok[k] || !b->suspect) continue;
        double cur = b->top, t = in->taken[k];
        if (t <= cur + r->jump) {
            if (t > cur) b->top = t;
            continue;
        }
        if (confirms(b, r, t, cur)) {
            b->top = t;         /* a second measurement confirms it: the body moves on */
            continue;
        }
        refuse(in, out, nout, k, DQ_REFUSED_JUMP, t - cur, alone(b, r, cur));
    }
}

/* The rows taken more than the window before their body's newest, the earlier rows of the call
 * counted, refused. */
static void floor_check(dq_store_index *x, const dq_store_state *st, const dq_store_rows *in,
                        const dq_store_rules *r, dq_store_refusal *out, size_t *nout)
{
    const int64_t call = ++x->calls;
    for (size_t k = 0; k < in->n; k++) {
        if (!in->ok[k]) continue;
        dq_store_body *b = &x->bodies[in->body[k]];
        if (b->seen != call) {
            b->seen = call;
            b->top = st->newest[in->body[k]];
        }
        if (in->taken[k] > b->top) b->top = in->taken[k];
    }
    /* checked at once against the newest of the whole call, and only the rows that fail that
     * (stricter) test one by one in order */
    for (size_t k = 0; k < in->n; k++) {
        int64_t bk = in->body[k];
        if (!in->ok[k] || !(in->taken[k] < x->bodies[bk].top - r->window)) continue;
        double floor = st->newest[bk];
        for (size_t j = 0; j < k; j++)
            if (in->ok[j] && in->body[j] == bk && in->taken[j] > floor) floor = in->taken[j];
        if (in->taken[k] < floor - r->window)
            refuse(in, out, nout, k, DQ_REFUSED_FLOOR, in->taken[k], floor);
    }
}

/* Past max_rows live rows (those out of their window dropped first), the last rows refused. */
static int room_check(dq_store_index *x, dq_store_cols *cols, const dq_store_state *st,
                      const dq_store_rows *in, const dq_store_rules *r, dq_store_refusal *out,
                      size_t *nout)
{
    size_t k = 0;
    for (size_t i = 0; i < in->n; i++) k += in->ok[i];
    if (cols->n + k <= r->max_rows) return 0;
    if (cols->n) {
        unsigned char *live = malloc(cols->n);
        if (!live) return -1;
        dq_store_live(x, cols->taken, st->newest, r->window, r->cap, cols->n, live, NULL);
        int rc = dq_store_keep(x, cols, live);
        free(live);
        if (rc < 0) return rc;
    }
    if (cols->n + k <= r->max_rows) return 0;
    size_t over = cols->n + k - r->max_rows;
    for (size_t i = in->n; i-- > 0 && over;) {
        if (!in->ok[i]) continue;
        refuse(in, out, nout, i, DQ_REFUSED_ROOM, (double)cols->n, (double)r->max_rows);
        over--;
    }
    return 0;
}

/* Row k of `in` appended to the columns, world frame made where not given. */
static int append(dq_store_cols *c, const dq_store_rows *in, size_t k)
{
    size_t n = c->n;
    c->ids[n] = in->ids[k];
    c->body[n] = in->body[k];
    c->codes[n] = in->source[k];
    c->times[n] = in->times[k];
    c->taken[n] = in->taken[k];
    memcpy(c->poses + 8 * n, in->poses + 8 * k, 8 * sizeof(double));
    memcpy(c->covs + 36 * n, in->covs + 36 * k, 36 * sizeof(double));
    if (in->wposes) {
        memcpy(c->wposes + 8 * n, in->wposes + 8 * k, 8 * sizeof(double));
    } else {        /* _in_world's dq.normalize, then to_world's */
        double once[8];
        if (dq_normalize(in->poses + 8 * k, once) != DQ_OK
            || dq_normalize(once, c->wposes + 8 * n) != DQ_OK)
            return -3;
    }
    if (c->wcovs)
        memcpy(c->wcovs + 36 * n, (in->wcovs ? in->wcovs : in->covs) + 36 * k,
               36 * sizeof(double));
    c->n = n + 1;
    return 0;
}

/* `origin` fed body b rows taken up to t (its newest of the call): its feeders, the other
 * origins and it, newest first (equal ones in that order), the first two kept. */
static void fed(dq_store_body *b, int64_t origin, double t)
{
    int64_t o[3];
    double u[3];
    int m = 0;
    for (int i = 0; i < b->feeders; i++) {
        if (b->feeder[i] != origin) {
            o[m] = b->feeder[i];
            u[m++] = b->fed[i];
        } else if (b->fed[i] > t) {
            t = b->fed[i];
        }
    }
    o[m] = origin;
    u[m++] = t;
    for (int i = 1; i < m; i++)
        for (int j = i; j > 0 && u[j - 1] < u[j]; j--) {
            int64_t so = o[j];
            double su = u[j];
            o[j] = o[j - 1];
            u[j] = u[j - 1];
            o[j - 1] = so;
            u[j - 1] = su;
        }
    b->feeders = (unsigned char)(m < 2 ? m : 2);
    for (int i = 0; i < b->feeders; i++) {
        b->feeder[i] = o[i];
        b->fed[i] = u[i];
    }
}

int dq_store_ingest(dq_store_index *x, dq_store_cols *cols, const dq_store_state *st,
                    const dq_store_rows *in, const dq_store_rules *r, dq_store_refusal *out,
                    size_t *nout, int *fresh)
{
    *nout = 0;
    *fresh = 0;
    size_t offered = 0;
    for (size_t k = 0; k < in->n; k++) {
        int64_t s = in->source[k];
        int in_range = s >= 0 && (size_t)s < st->sources;
        if (in->ok[k]) {
            if (!in_range || (size_t)s >= st->stride || in->body[k] < 0
                || (size_t)in->body[k] >= st->bodies)
                return -2;
            offered++;
        }
        in->taken[k] = in->times[k] - (in_range ? st->latency[s] : 0.0);
    }
    if (cols->n + offered > cols->capacity) return -2;
    if (x->count < st->bodies && grow_bodies(x, st->bodies) < 0) return -1;
    ++x->calls;
    if (r->bounded) {
        for (size_t k = 0; k < in->n; k++)
            if (in->ok[k] && fabs(in->times[k]) > r->max_time)
                refuse(in, out, nout, k, DQ_REFUSED_TIME, in->times[k], r->max_time);
        jump_check(x, st, in, r, out, nout);
    }
    floor_check(x, st, in, r, out, nout);
    if (r->bounded) {
        int rc = room_check(x, cols, st, in, r, out, nout);
        if (rc < 0) return rc;
    }
    if (r->all_or_none)
        for (size_t k = 0; k < in->n; k++)
            if (!in->ok[k]) return 0;
    const int64_t call = ++x->calls;
    for (size_t k = 0; k < in->n; k++) {
        if (!in->ok[k]) continue;
        int64_t bk = in->body[k];
        if (append(cols, in, k) < 0) return -3;
        if (dq_store_push(x, bk, (int64_t)cols->n - 1, in->taken[k]) < 0) return -1;
        dq_store_body *b = &x->bodies[bk];
        double t = in->taken[k], *newest = &st->newest[bk];
        if (!isfinite(*newest)) *fresh = 1;
        if (t > *newest) *newest = t;
        double *seen = &st->by_source[(size_t)bk * st->stride + (size_t)in->source[k]];
        if (t > *seen) *seen = t;
        if (b->mark != call) {      /* the body's first row of the call */
            b->mark = call;
            b->version++;
            b->top = t;
        } else if (t > b->top) {
            b->top = t;
        }
    }
    if (!r->anon)
        for (size_t k = 0; k < in->n; k++) {
            dq_store_body *b = &x->bodies[in->body[k]];
            if (!in->ok[k] || b->seen == call) continue;
            b->seen = call;
            fed(b, r->origin, b->top);
        }
    return 0;
}

static void move_row(dq_store_cols *c, size_t to, size_t from)
{
    c->ids[to] = c->ids[from];
    c->body[to] = c->body[from];
    c->codes[to] = c->codes[from];
    c->times[to] = c->times[from];
    c->taken[to] = c->taken[from];
    memcpy(c->poses + 8 * to, c->poses + 8 * from, 8 * sizeof(double));
    memcpy(c->covs + 36 * to, c->covs + 36 * from, 36 * sizeof(double));
    memcpy(c->wposes + 8 * to, c->wposes + 8 * from, 8 * sizeof(double));
    if (c->wcovs) memcpy(c->wcovs + 36 * to, c->wcovs + 36 * from, 36 * sizeof(double));
}

int dq_store_keep(dq_store_index *x, dq_store_cols *cols, const unsigned char *live)
{
    size_t j = 0;
    for (size_t r = 0; r < cols->n; r++) {
        if (!live[r]) continue;
        if (j != r) move_row(cols, j, r);
        j++;
    }
    cols->n = j;
    dq_store_reset(x);
    for (size_t r = 0; r < j; r++)
        if (dq_store_push(x, cols->body[r], (int64_t)r, cols->taken[r]) < 0) return -1;
    return 0;
}

int64_t dq_store_version(const dq_store_index *x, int64_t body)
{
    return body >= 0 && (size_t)body < x->count ? x->bodies[body].version : 0;
}

void dq_store_forget(dq_store_index *x, int64_t body)
{
    if (body < 0 || (size_t)body >= x->count) return;
    x->bodies[body].pending = 0;
    x->bodies[body].feeders = 0;
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
