/*
 * store.h — the per-body index of a live stream's store (service/fusion/store.py's Store keeps
 * the rows' columns; this finds them): each body's rows in arrival order with the running
 * maximum of their taken times, so the rows taken from a time on are found from the first entry
 * whose running maximum reaches it (a window's rows and those that came late, not the body's
 * whole buffer), and which rows a compaction keeps. Pure C99, no allocation but the index's own.
 */
#ifndef DQ_STORE_H
#define DQ_STORE_H

#include <stddef.h>
#include <stdint.h>

/* One body's rows: row numbers ascending, reach[i] the largest taken of rows[0..i]; and what a
 * reset keeps: its version (requests that brought it rows), and its time jumps: the last one
 * refused (taken, origin; anon: of no origin), the origins that fed it last (at most two, newest
 * taken first); seen, top and suspect: one call's scratch. */
typedef struct {
    int64_t *rows;
    double *reach;
    size_t used, size;
    int64_t version, mark, seen;
    double top;
    unsigned char suspect;
    double pending_t;
    int64_t pending_origin;
    unsigned char pending, pending_anon, feeders;
    int64_t feeder[2];
    double fed[2];
} dq_store_body;

/* Every body's index, by body code (0 .. count - 1); calls: ingests so far (a body's mark). */
typedef struct {
    dq_store_body *bodies;
    size_t count;
    int64_t calls;
} dq_store_index;

/* A store's columns (service/fusion/store.py's Store): n rows of capacity, row r's id, body and
 * source codes, stamp, taken, pose (8), covariance (36), world pose (8), world covariance (36;
 * NULL: the store keeps none). */
typedef struct {
    int64_t *ids, *body, *codes;
    double *times, *taken, *poses, *covs, *wposes, *wcovs;
    size_t n, capacity;
} dq_store_cols;

/* A request's rows offered to dq_store_ingest: n rows (body and source codes, ids, stamps,
 * poses, covariances, checked by fuse's rules), ok[k] whether row k is still offered (refused
 * rows are 0; out: taken in), wposes/wcovs the rows in the world frame (NULL: the poses made unit
 * twice and the covariances as they are, what to_world makes of rows of a source without
 * frames), taken[] (n, out) stamp less the source's latency. */
typedef struct {
    size_t n;
    const int64_t *body, *source, *ids;
    const double *times, *poses, *covs, *wposes, *wcovs;
    unsigned char *ok;
    double *taken;
} dq_store_rows;

/* A tracker's state beside the index: newest[b] (bodies entries) the newest taken of body b,
 * by_source[b * stride + s] of body b and source s, latency[s] (sources entries). */
typedef struct {
    double *newest, *by_source;
    size_t bodies, stride, sources;
    const double *latency;
} dq_store_state;

/* What the tracker bounds: window (s), cap (< 0: none), bounded: max_time (s), jump (s),
 * max_rows; origin: who sent the rows (anon: no one, a stream), all_or_none: nothing taken when
 * anything is refused. */
typedef struct {
    double window, max_time, jump;
    long cap;
    size_t max_rows;
    int bounded, anon, all_or_none;
    int64_t origin;
} dq_store_rules;

/* A refused row: its index, why, and the numbers its text names. */
enum { DQ_REFUSED_TIME = 1,     /* a: the time, b: max_time */
       DQ_REFUSED_JUMP = 2,     /* a: how far after the body's newest, b: 1 when no other
                                 * origin fed the body lately */
       DQ_REFUSED_FLOOR = 3,    /* a: taken, b: the body's newest it is too far before */
       DQ_REFUSED_ROOM = 4 };   /* a: the rows the store holds, b: max_rows */
typedef struct {
    size_t row;
    int code;
    double a, b;
} dq_store_refusal;

/* Row `row` of body `body` (>= 0), taken at `taken`, appended to its index: 0, or -1 when
 * memory ran out (the index as it was). */
int dq_store_push(dq_store_index *x, int64_t body, int64_t row, double taken);

/* Body `body`'s rows from its first entry whose running maximum reaches `lo` (every earlier row
 * was taken before lo; NumPy's searchsorted(reach, lo, "left")): their number, *rows pointing at
 * the first (into the index: valid until the next push or reset). */
size_t dq_store_after(const dq_store_index *x, int64_t body, double lo, const int64_t **rows);

/* How many rows body `body` has in the index. */
size_t dq_store_count(const dq_store_index *x, int64_t body);

/* live[r] for rows 0 .. n - 1 (body[r], taken[r]): taken within `window` of its body's newest
 * (taken >= newest[body] - window) and, with cap >= 0, among the last `cap` such rows of its
 * body in arrival order. Every row must be in the index (each body's newest given). live and s
 * may each be NULL; s: each body's span over those rows (ListFrames'). */
typedef struct {
    double recent;  /* in: seconds before a body's newest that count as near */
    double *oldest; /* out, one a body of the index: its live rows' oldest taken (HUGE_VAL) */
    int64_t *near;  /* out: its live rows taken within `recent` of its newest */
} dq_store_spans;

void dq_store_live(const dq_store_index *x, const double *taken, const double *newest,
                   double window, long cap, size_t n, unsigned char *live, dq_store_spans *s);

/* A request's rows into the store (service/fusion/tracker.py's Tracker._admit): refused in order
 * (refusals written to out[], at most in->n, *nout of them) those stamped beyond +-max_time; those
 * taken more than `jump` after their body's newest (the earlier rows of the call counted; a body
 * without one: its earliest row of the call), unless a row confirms its body's last refused jump
 * by lying within `jump` of it and coming from another origin than that jump's, or from the same
 * one while no other origin fed the body within `jump` of its newest; those taken more than the
 * window before their body's newest (the earlier rows of the call counted); those past max_rows
 * live rows in all (the rows out of their window dropped first). Then, unless all_or_none and
 * anything was refused, the rest appended to the columns (capacity for every offered row
 * needed) and the index, newest, by_source, the bodies' versions and feeders updated; *fresh: a
 * body without rows before got some. 0, -1 when memory ran out, -2 when a code is out of range
 * or the columns are full, -3 when a pose is not a rigid motion (nothing taken). */
int dq_store_ingest(dq_store_index *x, dq_store_cols *cols, const dq_store_state *st,
                    const dq_store_rows *in, const dq_store_rules *r, dq_store_refusal *out,
                    size_t *nout, int *fresh);

/* Rows r with live[r] kept, in order, the others dropped (columns and index); cols->n updated. */
int dq_store_keep(dq_store_index *x, dq_store_cols *cols, const unsigned char *live);

/* Body `body`'s version (0: never fed), and its jump state forgotten (removed). */
int64_t dq_store_version(const dq_store_index *x, int64_t body);
void dq_store_forget(dq_store_index *x, int64_t body);

/* Every body's index emptied (memory kept), or freed. */
void dq_store_reset(dq_store_index *x);
void dq_store_free(dq_store_index *x);

#endif
