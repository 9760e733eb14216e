/*
 * pbwrite.h — protobuf wire bytes written as the protobuf runtime writes them (proto3: a zero
 * scalar or an empty string left out, +0.0 only: -0.0 kept; repeated scalars packed), for the
 * writers of wire.c and fused_wire.c. The caller sizes the buffer; each function returns the end
 * of what it wrote.
 */
#ifndef DQPOSE_PBWRITE_H
#define DQPOSE_PBWRITE_H

#include <stddef.h>
#include <stdint.h>
#include <string.h>

enum { WT_VARINT = 0, WT_I64 = 1, WT_LEN = 2, WT_I32 = 5 };

/* bytes of v as a varint (1..10) */
static inline size_t pb_varint_size(uint64_t v)
{
    size_t n = 1;
    for (; v >= 0x80; v >>= 7) n++;
    return n;
}

static inline uint8_t *put_varint(uint8_t *p, uint64_t v)
{
    for (; v >= 0x80; v >>= 7) *p++ = (uint8_t)(v | 0x80);
    *p++ = (uint8_t)v;
    return p;
}

/* a field's tag (field numbers up to 2^28: at most 5 bytes) */
static inline uint8_t *put_tag(uint8_t *p, int field, int wt)
{
    return put_varint(p, (uint64_t)field << 3 | (uint64_t)wt);
}

static inline uint8_t *put_fixed64(uint8_t *p, double d)
{
    uint64_t v;
    memcpy(&v, &d, sizeof v);
    for (int i = 0; i < 8; i++) *p++ = (uint8_t)(v >> (8 * i));
    return p;
}

static inline uint8_t *put_double(uint8_t *p, int field, double d)
{
    uint64_t v;
    memcpy(&v, &d, sizeof v);
    if (!v) return p; /* proto3 omits +0.0 (only: the runtime compares bits) */
    p = put_tag(p, field, WT_I64);
    return put_fixed64(p, d);
}

/* a varint field (uint32, uint64, an enum >= 0), left out when 0 */
static inline uint8_t *put_uint(uint8_t *p, int field, uint64_t v)
{
    if (!v) return p;
    p = put_tag(p, field, WT_VARINT);
    return put_varint(p, v);
}

/* A submessage of doubles (fields 1..n); short enough that its length is one byte. */
static inline uint8_t *put_doubles(uint8_t *p, int field, const double *d, int n)
{
    uint8_t *len = p + 1;
    *p = (uint8_t)(field << 3 | WT_LEN);
    p += 2;
    for (int k = 0; k < n; k++) p = put_double(p, k + 1, d[k]);
    *len = (uint8_t)(p - len - 1);
    return p;
}

/* an element of a repeated string field: written even when empty */
static inline uint8_t *put_element(uint8_t *p, int field, const char *s, size_t n)
{
    p = put_tag(p, field, WT_LEN);
    p = put_varint(p, n);
    if (n) memcpy(p, s, n);
    return p + n;
}

/* a string field, left out when empty */
static inline uint8_t *put_string(uint8_t *p, int field, const char *s, size_t n)
{
    return n ? put_element(p, field, s, n) : p;
}

/* a repeated double field packed (left out when empty) */
static inline uint8_t *put_packed_doubles(uint8_t *p, int field, const double *d, size_t n)
{
    if (!n) return p;
    p = put_tag(p, field, WT_LEN);
    p = put_varint(p, 8 * n);
    for (size_t k = 0; k < n; k++) p = put_fixed64(p, d[k]);
    return p;
}

/* bytes a field's tag, length and a string (or submessage) of n bytes take */
static inline size_t pb_len_field_size(int field, size_t n)
{
    return pb_varint_size((uint64_t)field << 3) + pb_varint_size(n) + n;
}

#endif
