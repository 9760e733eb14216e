/*
 * wire.c — dqpose.v1.BlendRequest from protobuf wire bytes (see wire.h for why and the fields).
 */
#include "wire.h"

#include <string.h>

enum { WT_VARINT = 0, WT_I64 = 1, WT_LEN = 2, WT_I32 = 5 };

typedef struct {
    const uint8_t *p, *end;
} cursor;

static int varint(cursor *c, uint64_t *out)
{
    uint64_t v = 0;
    for (int shift = 0; shift < 64; shift += 7) {
        if (c->p >= c->end) return -1;
        uint8_t b = *c->p++;
        v |= (uint64_t)(b & 0x7f) << shift;
        if (!(b & 0x80)) {
            *out = v;
            return 0;
        }
    }
    return -1; /* more than 10 bytes */
}

static int fixed64(cursor *c, double *out)
{
    if (c->end - c->p < 8) return -1;
    uint64_t v = 0;
    for (int i = 7; i >= 0; i--) v = (v << 8) | c->p[i]; /* little endian on the wire */
    memcpy(out, &v, sizeof v);
    c->p += 8;
    return 0;
}

static int length(cursor *c, cursor *sub)
{
    uint64_t n;
    if (varint(c, &n) || n > (uint64_t)(c->end - c->p)) return -1;
    sub->p = c->p;
    sub->end = c->p + n;
    c->p += n;
    return 0;
}

static int skip(cursor *c, int wt)
{
    uint64_t v;
    cursor s;
    switch (wt) {
    case WT_VARINT: return varint(c, &v);
    case WT_I64: if (c->end - c->p < 8) return -1; c->p += 8; return 0;
    case WT_LEN: return length(c, &s);
    case WT_I32: if (c->end - c->p < 4) return -1; c->p += 4; return 0;
    default: return -1; /* groups: not in our contract */
    }
}

/* Doubles of a Vector3 / Quaternion: field k (1-based) goes to out[k - 1]; last value wins. */
static int doubles(cursor c, double *out, int nfields)
{
    while (c.p < c.end) {
        uint64_t key;
        if (varint(&c, &key)) return -1;
        int field = (int)(key >> 3), wt = (int)(key & 7);
        if (field == 0) return -1;
        if (field >= 1 && field <= nfields) {
            if (wt != WT_I64 || fixed64(&c, &out[field - 1])) return -1;
        } else if (skip(&c, wt)) {
            return -1;
        }
    }
    return 0;
}

/* One Pose into row [qw, qx, qy, qz, x, y, z] (merged into what the row already holds). */
static int pose(cursor c, double *row)
{
    while (c.p < c.end) {
        uint64_t key;
        cursor sub;
        if (varint(&c, &key)) return -1;
        int field = (int)(key >> 3), wt = (int)(key & 7);
        if (field == 0) return -1;
        if (field == 1 || field == 2) {
            if (wt != WT_LEN || length(&c, &sub)) return -1;
            if (field == 1 ? doubles(sub, row + 4, 3) : doubles(sub, row, 4)) return -1;
        } else if (skip(&c, wt)) {
            return -1;
        }
    }
    return 0;
}

int dq_wire_blend_request(const uint8_t *buf, size_t len, dq_blend_request *r)
{
    cursor c = {buf, buf + len};
    int fill = r->poses != NULL || r->weights != NULL;
    size_t np = 0, nw = 0;
    r->method = 0;
    r->tolerance = 0.0;
    r->max_iterations = 0;
    while (c.p < c.end) {
        uint64_t key, v;
        cursor sub;
        if (varint(&c, &key)) return -1;
        int field = (int)(key >> 3), wt = (int)(key & 7);
        switch (field) {
        case 0:
            return -1; /* field number 0 is invalid */
        case 1:
            if (wt != WT_LEN || length(&c, &sub)) return -1;
            if (fill) {
                if (np >= r->n_poses) return -1;
                double *row = r->poses + 7 * np;
                for (int k = 0; k < 7; k++) row[k] = 0.0;
                if (pose(sub, row)) return -1;
            }
            np++;
            break;
        case 2:
            if (wt == WT_LEN) { /* packed */
                if (length(&c, &sub) || (sub.end - sub.p) % 8) return -1;
                for (; sub.p < sub.end; nw++) {
                    double d;
                    if (fixed64(&sub, &d)) return -1;
                    if (fill) {
                        if (nw >= r->n_weights) return -1;
                        r->weights[nw] = d;
                    }
                }
            } else if (wt == WT_I64) {
                double d;
                if (fixed64(&c, &d)) return -1;
                if (fill) {
                    if (nw >= r->n_weights) return -1;
                    r->weights[nw] = d;
                }
                nw++;
            } else {
                return -1;
            }
            break;
        case 3:
            if (wt != WT_VARINT || varint(&c, &v)) return -1;
            r->method = (int64_t)(int32_t)(uint32_t)v; /* enums are int32 on the wire */
            break;
        case 4:
            if (wt != WT_I64 || fixed64(&c, &r->tolerance)) return -1;
            break;
        case 5:
            if (wt != WT_VARINT || varint(&c, &v)) return -1;
            r->max_iterations = (uint32_t)v; /* uint32: the parser keeps the low 32 bits */
            break;
        default:
            if (skip(&c, wt)) return -1;
        }
    }
    if (fill && (np != r->n_poses || nw != r->n_weights)) return -1;
    r->n_poses = np;
    r->n_weights = nw;
    return 0;
}
