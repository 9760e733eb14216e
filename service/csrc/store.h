/*
 * store.h — the per-body index of a live stream's store (service/fusion/store.py's _Store keeps
 * the rows' columns; this finds them): each body's rows in arrival order with the running
 * maximum of their taken times, so the rows taken from a time on are found from the first entry
 * whose running maximum reaches it (a window's rows and those that came late, not the body's
 * whole buffer), and which rows a compaction keeps. Pure C99, no allocation but the index's own.
 */
#ifndef DQ_STORE_H
#define DQ_STORE_H

#include <stddef.h>
#include <stdint.h>

/* One body's rows: row numbers ascending, reach[i] the largest taken of rows[0..i]. */
typedef struct {
    int64_t *rows;
    double *reach;
    size_t used, size;
} dq_store_body;

/* Every body's index, by body code (0 .. count - 1). */
typedef struct {
    dq_store_body *bodies;
    size_t count;
} dq_store_index;

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
 * body in arrival order. Every row must be in the index (each body's newest given). */
void dq_store_live(const dq_store_index *x, const double *taken, const double *newest,
                   double window, long cap, size_t n, unsigned char *live);

/* Whether rows (body[k], times[k], taken[k]), k < n, none refused so far, pass a tracker's
 * rules with nothing to refuse (service/fusion/tracker.py's _admit, whose slow path names each
 * refusal): |time| <= max_time; none taken more than `jump` after its body's newest (a body
 * without one: after its earliest row of these); none taken more than `window` before its
 * body's newest with these rows taken in. 1 with newest[] (bodies entries) the maxima with
 * these rows; 0 when a row needs the slow path (newest[] may have moved: the caller's copy is
 * spent); -1 when memory ran out. */
int dq_store_plain(double *newest, size_t bodies, const int64_t *body, const double *times,
                   const double *taken, size_t n, double window, double max_time, double jump);

/* Every body's index emptied (memory kept), or freed. */
void dq_store_reset(dq_store_index *x);
void dq_store_free(dq_store_index *x);

#endif
