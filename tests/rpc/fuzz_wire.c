/*
 * fuzz_wire.c — mutational fuzzing of the server's C wire paths (dq_wire_blend_request,
 * dq_wire_blend, dq_wire_batch_count, dq_wire_blend_batch, dq_wire_fuse_count,
 * dq_wire_fuse_stream) from seed messages, built by
 * tests/test_wire.py with AddressSanitizer and UBSan: any out-of-bounds read or write, or
 * undefined behaviour, on any input ends the run with a report.
 *
 *     fuzz_wire ITERATIONS SEED_FILE...
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "wire.h"

static unsigned long long state = 88172645463325252ULL;

static unsigned rnd(void)
{
    state ^= state << 13;
    state ^= state >> 7;
    state ^= state << 17;
    return (unsigned)state;
}

int main(int argc, char **argv)
{
    if (argc < 3) return 2;
    long iters = atol(argv[1]);
    static uint8_t seeds[16][1 << 14];
    size_t lens[16];
    int ns = 0;
    for (int i = 2; i < argc && ns < 16; i++) {
        FILE *f = fopen(argv[i], "rb");
        if (!f) return 2;
        lens[ns] = fread(seeds[ns], 1, sizeof seeds[0], f);
        ns++;
        fclose(f);
    }
    dq_wire_config cfg = {50, 1e-12, 100, 1000};
    long answered = 0, batches = 0, streams = 0;
    for (long it = 0; it < iters; it++) {
        int k = (int)(rnd() % (unsigned)ns);
        size_t len = lens[k];
        int muts = 1 + (int)(rnd() % 4);
        uint8_t *buf = malloc(len + 8 * (size_t)muts + 1);
        memcpy(buf, seeds[k], len);
        for (int m = 0; m < muts && len; m++) {
            size_t i = rnd() % len;
            switch (rnd() % 4) {
            case 0: buf[i] = (uint8_t)rnd(); break;
            case 1: buf[i] ^= (uint8_t)(1u << (rnd() % 8)); break;
            case 2: {
                /* the varint (tag, length or value) ending at i, if one does, made 1..8 bytes
                 * longer with the same value: what protobuf reads up to 5 or 10 bytes */
                size_t extra = 1 + rnd() % 8;
                if (buf[i] & 0x80) break;
                memmove(buf + i + 1 + extra, buf + i + 1, len - i - 1);
                buf[i] |= 0x80;
                memset(buf + i + 1, 0x80, extra - 1);
                buf[i + extra] = 0x00;
                len += extra;
                break;
            }
            default: len = i; /* truncate */
            }
        }
        /* an exact-size copy, so reading one byte past the end is caught */
        uint8_t *exact = malloc(len ? len : 1);
        memcpy(exact, buf, len);
        free(buf);
        uint8_t out[DQ_WIRE_RESPONSE_MAX];
        size_t n = 0, nr = 0, np = 0;
        if (dq_wire_blend(exact, len, &cfg, out, &n) == 0) {
            if (n > DQ_WIRE_RESPONSE_MAX) abort();
            answered++;
        }
        if (dq_wire_batch_count(exact, len, &nr, &np) == 0 && nr > 0 && nr < 4096) {
            uint8_t *bo = malloc(nr * DQ_WIRE_BATCH_ITEM_MAX);
            if (dq_wire_blend_batch(exact, len, &cfg, bo, &n) == 0) {
                if (n > nr * DQ_WIRE_BATCH_ITEM_MAX) abort();
                batches++;
            }
            free(bo);
        }
        /* the same bytes read as a FuseStreamRequest and as a PublishRequest */
        for (int publish = 0; publish < 2; publish++) {
            dq_fuse_stream fs = {0};
            fs.publish = publish;
            if (dq_wire_fuse_count(exact, len, &fs) == 0 && fs.n > 0 && fs.n < 4096) {
                /* exact-size arrays, so a write past a row is caught */
                fs.poses = malloc(fs.n * 8 * sizeof(double));
                fs.covs = malloc(fs.n * 36 * sizeof(double));
                fs.times = malloc(fs.n * sizeof(double));
                fs.spans = malloc(fs.n * 6 * sizeof(uint32_t));
                fs.codes = malloc(fs.n);
                if (dq_wire_fuse_stream(exact, len, 1e-9, &fs) == 0) {
                    for (size_t j = 0; j < fs.n; j++) {
                        const uint32_t *sp = fs.spans + 6 * j;
                        for (int k = 0; k < 6; k += 2)
                            if ((size_t)sp[k] + sp[k + 1] > len) abort();
                        if (fs.codes[j] > DQ_MEAS_COV_SCALE) abort();
                    }
                    streams++;
                }
                free(fs.poses); free(fs.covs); free(fs.times); free(fs.spans); free(fs.codes);
            }
        }
        free(exact);
    }
    printf("%ld %ld %ld %ld\n", iters, answered, batches, streams);
    return 0;
}
