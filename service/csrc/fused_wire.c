/*
 * fused_wire.c — a FusedPose's bytes (see fused_wire.h).
 */
#include "fused_wire.h"

#include "pbwrite.h"

/* the bytes of a double field: 0 for +0.0, which proto3 leaves out */
static size_t double_size(int field, double d)
{
    uint64_t v;
    memcpy(&v, &d, sizeof v);
    return v ? pb_varint_size((uint64_t)field << 3) + 8 : 0;
}

static size_t uint_size(int field, uint64_t v)
{
    return v ? pb_varint_size((uint64_t)field << 3) + pb_varint_size(v) : 0;
}

static size_t string_size(int field, dq_str s)
{
    return s.n ? pb_len_field_size(field, s.n) : 0;
}

static size_t packed_varints_size(const uint32_t *v, size_t n)
{
    size_t size = 0;
    for (size_t k = 0; k < n; k++) size += pb_varint_size(v[k]);
    return size;
}

static size_t source_size(const dq_wire_source *s)
{
    return string_size(1, s->name) + uint_size(2, s->count) + uint_size(3, s->rejected) +
           double_size(4, s->nis_mean) + double_size(5, s->low) + double_size(6, s->high) +
           uint_size(7, s->verdict);
}

static size_t dropped_size(const dq_wire_dropped *d)
{
    return uint_size(1, d->index) + string_size(2, d->source) + double_size(3, d->age) +
           string_size(4, d->reason);
}

static size_t latency_size(const dq_wire_latency *a)
{
    return string_size(1, a->source) + double_size(2, a->configured) +
           double_size(3, a->prior_sigma) + double_size(4, a->value) + double_size(5, a->sigma);
}

size_t dq_fused_pose_bound(const dq_fused_pose *f)
{
    /* a tag of field <= 25 is at most 2 bytes, a length at most 10 */
    size_t size = 12 + f->body.n + 10 + 69 + 12 + 36 * 8;
    size += 12 + 5 * (f->n_inliers + f->n_rejected);
    for (size_t k = 0; k < f->n_rejected; k++)
        size += 24 + f->reasons[k].n + f->rejected_sources[k].n;
    size += 10 + 2 * 12 + 3 * 12 + 36 + f->n * (8 + 8 + 1 + 48);
    for (size_t k = 0; k < f->n_sources; k++) size += 12 + source_size(f->sources + k);
    size += 12 + 12 + 10 * f->n_measurements;
    for (size_t k = 0; k < f->n_dropped; k++) size += 12 + dropped_size(f->dropped + k);
    size += 2 * 12 + 42 * 8 + 10;
    for (size_t k = 0; k < f->n_latencies; k++) size += 12 + latency_size(f->latencies + k);
    return size;
}

static uint8_t *put_packed_varints(uint8_t *p, int field, const uint32_t *v, size_t n)
{
    if (!n) return p;
    p = put_tag(p, field, WT_LEN);
    p = put_varint(p, packed_varints_size(v, n));
    for (size_t k = 0; k < n; k++) p = put_varint(p, v[k]);
    return p;
}

static uint8_t *put_sources(uint8_t *p, const dq_wire_source *s, size_t n)
{
    for (size_t k = 0; k < n; k++, s++) {
        p = put_tag(p, 16, WT_LEN);
        p = put_varint(p, source_size(s));
        p = put_string(p, 1, s->name.s, s->name.n);
        p = put_uint(p, 2, s->count);
        p = put_uint(p, 3, s->rejected);
        p = put_double(p, 4, s->nis_mean);
        p = put_double(p, 5, s->low);
        p = put_double(p, 6, s->high);
        p = put_uint(p, 7, s->verdict);
    }
    return p;
}

static uint8_t *put_dropped(uint8_t *p, const dq_wire_dropped *d, size_t n)
{
    for (size_t k = 0; k < n; k++, d++) {
        p = put_tag(p, 21, WT_LEN);
        p = put_varint(p, dropped_size(d));
        p = put_uint(p, 1, d->index);
        p = put_string(p, 2, d->source.s, d->source.n);
        p = put_double(p, 3, d->age);
        p = put_string(p, 4, d->reason.s, d->reason.n);
    }
    return p;
}

static uint8_t *put_latencies(uint8_t *p, const dq_wire_latency *a, size_t n)
{
    for (size_t k = 0; k < n; k++, a++) {
        p = put_tag(p, 25, WT_LEN);
        p = put_varint(p, latency_size(a));
        p = put_string(p, 1, a->source.s, a->source.n);
        p = put_double(p, 2, a->configured);
        p = put_double(p, 3, a->prior_sigma);
        p = put_double(p, 4, a->value);
        p = put_double(p, 5, a->sigma);
    }
    return p;
}

size_t dq_fused_pose_write(const dq_fused_pose *f, uint8_t *out)
{
    uint8_t *p = out;
    p = put_string(p, 1, f->body.s, f->body.n);
    p = put_double(p, 2, f->time);
    uint8_t *len = p + 1; /* pose: always present, at most 67 bytes */
    *p = (uint8_t)(3 << 3 | WT_LEN);
    p += 2;
    p = put_doubles(p, 1, f->t, 3);
    p = put_doubles(p, 2, f->quat, 4);
    *len = (uint8_t)(p - len - 1);
    p = put_packed_doubles(p, 4, f->covariance, 36);
    p = put_packed_varints(p, 5, f->inliers, f->n_inliers);
    p = put_packed_varints(p, 6, f->rejected, f->n_rejected);
    for (size_t k = 0; k < f->n_rejected; k++)
        p = put_element(p, 7, f->reasons[k].s, f->reasons[k].n);
    p = put_double(p, 8, f->chi2);
    p = put_uint(p, 9, f->dof);
    p = put_uint(p, 10, f->iterations);
    p = put_uint(p, 11, f->status);
    p = put_packed_doubles(p, 12, f->distances, f->n);
    p = put_packed_doubles(p, 13, f->nis, f->n);
    if (f->n) { /* packed bools: one byte each */
        p = put_tag(p, 14, WT_LEN);
        p = put_varint(p, f->n);
        for (size_t k = 0; k < f->n; k++) *p++ = f->tested[k] ? 1 : 0;
    }
    p = put_packed_doubles(p, 15, f->residuals, 6 * f->n);
    p = put_sources(p, f->sources, f->n_sources);
    p = put_uint(p, 18, f->request);
    if (f->n_measurements) {
        size_t size = 0;
        for (size_t k = 0; k < f->n_measurements; k++) size += pb_varint_size(f->measurements[k]);
        p = put_tag(p, 19, WT_LEN);
        p = put_varint(p, size);
        for (size_t k = 0; k < f->n_measurements; k++) p = put_varint(p, f->measurements[k]);
    }
    for (size_t k = 0; k < f->n_rejected; k++)
        p = put_element(p, 20, f->rejected_sources[k].s, f->rejected_sources[k].n);
    p = put_dropped(p, f->dropped, f->n_dropped);
    if (f->twist) {
        p = put_packed_doubles(p, 22, f->twist, 6);
        p = put_packed_doubles(p, 23, f->twist_covariance, 36);
    }
    p = put_double(p, 24, f->extrapolation);
    p = put_latencies(p, f->latencies, f->n_latencies);
    return (size_t)(p - out);
}
