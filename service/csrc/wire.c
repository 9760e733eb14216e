/*
 * wire.c — dqpose.v1.BlendRequest from protobuf wire bytes (see wire.h for why and the fields).
 */
#include "wire.h"

#include <stdlib.h>
#include <string.h>

#include "blend.h"
#include "dq.h"
#include "fusion.h"
#include "pbwrite.h"

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

/* A field's tag: at most 5 bytes and 32 bits, field number not 0, as protobuf reads it (a longer
 * tag is corrupt to it, however the varint decodes). So every number is within 1..2^29-1. */
static int tag(cursor *c, int *field, int *wt)
{
    uint64_t key;
    const uint8_t *start = c->p;
    if (varint(c, &key) || c->p - start > 5 || key > 0xFFFFFFFFu || (key >> 3) == 0) return -1;
    *field = (int)(key >> 3);
    *wt = (int)(key & 7);
    return 0;
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

/* A length-delimited field's body. Its length, like a tag, is corrupt to protobuf beyond 5 bytes. */
static int length(cursor *c, cursor *sub)
{
    uint64_t n;
    const uint8_t *start = c->p;
    if (varint(c, &n) || c->p - start > 5 || n > (uint64_t)(c->end - c->p)) return -1;
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
        int field, wt;
        if (tag(&c, &field, &wt)) return -1;
        if (field <= nfields) {
            if (wt != WT_I64 || fixed64(&c, &out[field - 1])) return -1;
        } else if (skip(&c, wt)) {
            return -1;
        }
    }
    return 0;
}

/* Walks the fields of a message: every field numbered 1..max_field must be length-delimited
 * and goes to fn(field, sub, ctx); other fields are skipped. -1 on undecodable bytes (see tag)
 * or when fn fails. */
static int each_message_field(cursor c, int max_field, int (*fn)(int, cursor, void *), void *ctx)
{
    while (c.p < c.end) {
        int field, wt;
        cursor sub;
        if (tag(&c, &field, &wt)) return -1;
        if (field <= max_field) {
            if (wt != WT_LEN || length(&c, &sub) || fn(field, sub, ctx)) return -1;
        } else if (skip(&c, wt)) {
            return -1;
        }
    }
    return 0;
}

/* Pose field 1 (position) or 2 (orientation) into row [qw, qx, qy, qz, x, y, z]. */
static int pose_field(int field, cursor sub, void *row)
{
    double *r = (double *)row;
    return field == 1 ? doubles(sub, r + 4, 3) : doubles(sub, r, 4);
}

/* One Pose into its row (merged into what the row already holds). */
static int pose(cursor c, double *row)
{
    return each_message_field(c, 2, pose_field, row);
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
        uint64_t v;
        cursor sub;
        int field, wt;
        if (tag(&c, &field, &wt)) return -1;
        switch (field) {
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

/* ---- the served Blend ----------------------------------------------------------------------- */

static size_t encode_response(const double *quat, const double *t, uint32_t iterations,
                              double residual, uint8_t *out)
{
    uint8_t *p = out, *len = out + 1;
    *p = (uint8_t)(1 << 3 | WT_LEN); /* pose: always present, as the server sets it */
    p += 2;
    p = put_doubles(p, 1, t, 3);
    p = put_doubles(p, 2, quat, 4);
    *len = (uint8_t)(p - len - 1);
    if (iterations) {
        *p++ = (uint8_t)(2 << 3 | WT_VARINT);
        for (uint32_t v = iterations;; v >>= 7) {
            if (v < 0x80) { *p++ = (uint8_t)v; break; }
            *p++ = (uint8_t)(v | 0x80);
        }
    }
    p = put_double(p, 3, residual);
    return (size_t)(p - out);
}

int dq_wire_blend(const uint8_t *buf, size_t len, const dq_wire_config *cfg, uint8_t *out,
                  size_t *out_len)
{
    dq_blend_request r;
    memset(&r, 0, sizeof r);
    if (dq_wire_blend_request(buf, len, &r) < 0) return -1;
    size_t n = r.n_poses, m = r.n_weights;
    if (n == 0 || n > cfg->max_poses || (m && m != n)) return -1;
    dq_blend_params p;
    /* METHOD_UNSPECIFIED means DIB; any other value is a dq_method or refused by the check */
    p.method = r.method == 0 ? DQ_DIB : (int)r.method;
    if (dq_blend_check(p.method, n)) return -1;
    p.tol = r.tolerance != 0.0 ? r.tolerance : cfg->default_tol;
    if (!(p.tol > 0.0 && p.tol * 0.0 == 0.0)) return -1;
    uint64_t max_iter = r.max_iterations ? r.max_iterations : cfg->default_max_iter;
    if (max_iter > cfg->max_iter_limit) return -1;
    p.max_iter = (int)max_iter;

    /* rows [qw qx qy qz x y z], weights in, unit dual quaternions, normalised weights */
    double stack[16 * 32];
    size_t need = 7 * n + m + 8 * n + n;
    double *mem = need <= sizeof stack / sizeof stack[0] ? stack : malloc(need * sizeof(double));
    if (!mem) return -1;
    int rc = -1;
    r.poses = mem;
    r.weights = m ? mem + 7 * n : NULL;
    r.n_poses = n;
    r.n_weights = m;
    double *q = mem + 7 * n + m, *w = q + 8 * n;
    if (dq_wire_blend_request(buf, len, &r) < 0) goto done;
    for (size_t i = 0; i < n; i++) {
        double tmp[8];
        if (dq_from_pose(r.poses + 7 * i, r.poses + 7 * i + 4, tmp)) goto done;
        if (dq_unit(tmp, q + 8 * i)) goto done;
    }
    size_t bad;
    if (dq_weights(r.weights, n, w, &bad)) goto done;
    double mean[8], unit[8], quat[4], t[3], residual;
    int iterations;
    if (dq_blend_set(q, w, n, &p, mean, &iterations, &residual) || dq_unit(mean, unit)) goto done;
    dq_to_pose(unit, quat, t);
    *out_len = encode_response(quat, t, (uint32_t)iterations, residual, out);
    rc = 0;
done:
    if (mem != stack) free(mem);
    return rc;
}

/* ---- the served BlendBatch -------------------------------------------------------------------- */

/* Calls fn(1, sub, ctx) for every BlendRequest of a BlendBatchRequest {requests=1}. */
static int each_request(const uint8_t *buf, size_t len, int (*fn)(int, cursor, void *), void *ctx)
{
    cursor c = {buf, buf + len};
    return each_message_field(c, 1, fn, ctx);
}

typedef struct { size_t n_requests, n_poses; } batch_count;

static int count_one(int field, cursor sub, void *ctx)
{
    (void)field;
    batch_count *bc = (batch_count *)ctx;
    dq_blend_request r;
    memset(&r, 0, sizeof r);
    if (dq_wire_blend_request(sub.p, (size_t)(sub.end - sub.p), &r) < 0) return -1;
    bc->n_requests++;
    bc->n_poses += r.n_poses;
    return 0;
}

int dq_wire_batch_count(const uint8_t *buf, size_t len, size_t *n_requests, size_t *n_poses)
{
    batch_count bc = {0, 0};
    if (each_request(buf, len, count_one, &bc)) return -1;
    *n_requests = bc.n_requests;
    *n_poses = bc.n_poses;
    return 0;
}

typedef struct { const dq_wire_config *cfg; uint8_t *p; } batch_out;

static int blend_one(int field, cursor sub, void *ctx)
{
    (void)field;
    batch_out *bo = (batch_out *)ctx;
    size_t n = 0;
    if (dq_wire_blend(sub.p, (size_t)(sub.end - sub.p), bo->cfg, bo->p + 2, &n)) return -1;
    bo->p[0] = (uint8_t)(1 << 3 | WT_LEN);
    bo->p[1] = (uint8_t)n; /* n <= DQ_WIRE_RESPONSE_MAX < 128: one length byte */
    bo->p += 2 + n;
    return 0;
}

int dq_wire_blend_batch(const uint8_t *buf, size_t len, const dq_wire_config *cfg, uint8_t *out,
                        size_t *out_len)
{
    batch_out bo = {cfg, out};
    if (each_request(buf, len, blend_one, &bo)) return -1;
    *out_len = (size_t)(bo.p - out);
    return 0;
}

/* ---- StreamFuse: FuseStreamRequest to arrays -------------------------------------------------- */

typedef struct {
    double row[7];       /* the Pose: [qw qx qy qz x y z] */
    double cov[36];
    size_t ncov;
    double time, weight;
    cursor source, body;
} measurement;

/* A repeated double, packed or not: values beyond 36 are only counted. */
static int covariance_value(cursor *c, int wt, measurement *m)
{
    double d;
    cursor sub;
    if (wt == WT_I64) {
        if (fixed64(c, &d)) return -1;
        if (m->ncov < 36) m->cov[m->ncov] = d;
        m->ncov++;
        return 0;
    }
    if (wt != WT_LEN || length(c, &sub) || (sub.end - sub.p) % 8) return -1;
    while (sub.p < sub.end) {
        if (fixed64(&sub, &d)) return -1;
        if (m->ncov < 36) m->cov[m->ncov] = d;
        m->ncov++;
    }
    return 0;
}

static int ascii(cursor s)
{
    for (const uint8_t *p = s.p; p < s.end; p++)
        if (*p & 0x80) return 0;
    return 1;
}

/* One Measurement's fields, merged as protobuf merges them (the last scalar or string wins, Pose
 * fields merge, covariance values append); -1 for an unknown field or a non-ASCII name. */
static int measurement_fields(cursor c, measurement *m)
{
    memset(m, 0, sizeof *m);
    m->source.p = m->source.end = m->body.p = m->body.end = c.p;
    while (c.p < c.end) {
        int field, wt;
        cursor sub;
        if (tag(&c, &field, &wt)) return -1;
        switch (field) {
        case 1:
        case 2:
            if (wt != WT_LEN || length(&c, &sub) || !ascii(sub)) return -1;
            *(field == 1 ? &m->source : &m->body) = sub;
            break;
        case 3:
            if (wt != WT_I64 || fixed64(&c, &m->time)) return -1;
            break;
        case 4:
            if (wt != WT_LEN || length(&c, &sub) || pose(sub, m->row)) return -1;
            break;
        case 5:
            if (covariance_value(&c, wt, m)) return -1;
            break;
        case 6:
            if (wt != WT_I64 || fixed64(&c, &m->weight)) return -1;
            break;
        default:
            return -1;
        }
    }
    return 0;
}

static int is_finite(double x) { return x * 0.0 == 0.0; }

/* The checks, in the Python path's order; -1 where the two paths could differ. */
static int check_measurement(measurement *m, double sym_tol, double *pose_out, double *cov_out,
                             uint8_t *code)
{
    for (int k = 0; k < 8; k++) pose_out[k] = 0.0;
    double w = m->weight == 0.0 ? 1.0 : m->weight; /* weight 0 (or -0) means 1 */
    if (!is_finite(m->time)) { *code = DQ_MEAS_TIME; return 0; }
    if (m->ncov != 0 && m->ncov != 36) { *code = DQ_MEAS_COV_COUNT; return 0; }
    if (m->ncov == 36 && m->weight != 0.0) { *code = DQ_MEAS_COV_AND_WEIGHT; return 0; }
    if (m->ncov == 0 && !(is_finite(w) && w > 0.0)) { *code = DQ_MEAS_WEIGHT; return 0; }
    if (dq_from_pose(m->row, m->row + 4, pose_out)) {
        for (int k = 0; k < 8; k++) pose_out[k] = 0.0;
        *code = DQ_MEAS_POSE;
        return 0;
    }
    double unit[8];
    if (dq_unit(pose_out, unit)) return -1; /* the Tracker's pose check, never seen to fail */
    if (m->body.p == m->body.end) { *code = DQ_MEAS_BODY; return 0; }
    const double *S = m->cov;
    double iso[36];
    if (m->ncov == 0) {
        /* np.eye(6) / w */
        for (int k = 0; k < 36; k++) iso[k] = (k % 7 ? 0.0 : 1.0) / w;
        S = iso;
    }
    switch (dq_covariance_check(S, sym_tol, cov_out)) {
    case DQ_OK: *code = DQ_MEAS_OK; return 0;
    case DQ_E_NONFINITE: *code = DQ_MEAS_COV_NONFINITE; break;
    case DQ_E_ASYMMETRIC: *code = DQ_MEAS_COV_ASYMMETRIC; break;
    case DQ_E_NOT_SPD: *code = DQ_MEAS_COV_NOT_SPD; break;
    case DQ_E_SCALE: *code = DQ_MEAS_COV_SCALE; break;
    default: return -1;
    }
    memcpy(cov_out, S, 36 * sizeof(double)); /* as given: the Python check names the problem */
    return 0;
}

/* Walks the request: fn(measurement body, ctx) for each measurement, in order; -1 for options,
 * an output rate or an unknown field (the protobuf path's), or undecodable bytes. A
 * PublishRequest's (r->publish) producer and sequence go to r, the last of each as protobuf
 * reads them (its producer's UTF-8 is the caller's to check). */
static int each_measurement(const uint8_t *buf, size_t len, dq_fuse_stream *r,
                            int (*fn)(cursor, void *), void *ctx)
{
    cursor c = {buf, buf + len};
    if (len > 0xFFFFFFFFu) return -1; /* spans are 32 bits */
    const int publish = r->publish, measurements = publish ? 1 : 3;
    r->producer = r->producer_len = 0;
    r->sequence = 0;
    while (c.p < c.end) {
        int field, wt;
        cursor sub;
        if (tag(&c, &field, &wt)) return -1;
        if (publish && field == 2 && wt == WT_LEN) {
            if (length(&c, &sub)) return -1;
            r->producer = (size_t)(sub.p - buf);
            r->producer_len = (size_t)(sub.end - sub.p);
        } else if (publish && field == 3 && wt == WT_VARINT) {
            if (varint(&c, &r->sequence)) return -1;
        } else if (field != measurements || wt != WT_LEN || length(&c, &sub) || fn(sub, ctx)) {
            return -1;
        }
    }
    return 0;
}

static int count_measurement(cursor sub, void *ctx)
{
    (void)sub;
    ((dq_fuse_stream *)ctx)->n++;
    return 0;
}

int dq_wire_fuse_count(const uint8_t *buf, size_t len, dq_fuse_stream *r)
{
    r->n = 0;
    return each_measurement(buf, len, r, count_measurement, r);
}

typedef struct {
    dq_fuse_stream *r;
    const uint8_t *buf;
    double sym_tol;
    size_t i;
} fill_state;

static int fill_measurement(cursor sub, void *ctx)
{
    fill_state *f = (fill_state *)ctx;
    dq_fuse_stream *r = f->r;
    size_t i = f->i++;
    measurement m;
    if (i >= r->n || measurement_fields(sub, &m)) return -1;
    r->times[i] = m.time;
    uint32_t *s = r->spans + 6 * i;
    s[0] = (uint32_t)(sub.p - f->buf);
    s[1] = (uint32_t)(sub.end - sub.p);
    s[2] = (uint32_t)(m.source.p - f->buf);
    s[3] = (uint32_t)(m.source.end - m.source.p);
    s[4] = (uint32_t)(m.body.p - f->buf);
    s[5] = (uint32_t)(m.body.end - m.body.p);
    return check_measurement(&m, f->sym_tol, r->poses + 8 * i, r->covs + 36 * i, r->codes + i);
}

int dq_wire_fuse_stream(const uint8_t *buf, size_t len, double sym_tol, dq_fuse_stream *r)
{
    fill_state f = {r, buf, sym_tol, 0};
    if (each_measurement(buf, len, r, fill_measurement, &f) || f.i != r->n) return -1;
    return 0;
}

/* ---- the client's FuseStreamRequest ----------------------------------------------------------- */

size_t dq_wire_measurement(uint8_t *out, const char *source, size_t source_len, const char *body,
                           size_t body_len, double time, const double q[4], const double t[3],
                           const double *cov, double weight)
{
    /* the fields are written after room for the longest tag and length, then moved back */
    uint8_t *start = out + 11, *p = start;
    p = put_string(p, 1, source, source_len);
    p = put_string(p, 2, body, body_len);
    p = put_double(p, 3, time);
    uint8_t *len = p + 1;
    *p = (uint8_t)(4 << 3 | WT_LEN); /* pose: at most 67 bytes, a one-byte length */
    p += 2;
    p = put_doubles(p, 1, t, 3);
    p = put_doubles(p, 2, q, 4);
    *len = (uint8_t)(p - len - 1);
    if (cov) p = put_packed_doubles(p, 5, cov, 36);
    p = put_double(p, 6, weight);
    size_t n = (size_t)(p - start);
    uint8_t head[11], *h = head;
    *h++ = (uint8_t)(3 << 3 | WT_LEN);
    h = put_varint(h, n);
    size_t hn = (size_t)(h - head);
    memmove(out + hn, start, n);
    memcpy(out, head, hn);
    return hn + n;
}
