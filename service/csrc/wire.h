/*
 * wire.h — a decoder for one message of the API contract, dqpose.v1.BlendRequest, straight from
 * its protobuf wire bytes into arrays, in pure C99.
 *
 * Why: reading ten poses out of parsed protobuf objects in Python costs more than the blend
 * itself; the server's hot path decodes the bytes here instead. The decoder follows the protobuf
 * encoding rules (fields in any order, repeated scalars packed or not, a repeated message field
 * merged field by field, the last value of a scalar wins, unknown fields skipped, varints not
 * necessarily minimal but tags and lengths of at most 5 bytes as protobuf reads them), and reports
 * anything it does not understand as an error so the caller can fall back to the full protobuf
 * parser. tests/rpc/test_wire.py checks it against that parser on random messages.
 *
 * Field numbers (proto/dqpose/v1): BlendRequest {poses=1; weights=2; method=3; tolerance=4;
 * max_iterations=5}, Pose {position=1; orientation=2}, Vector3 {x=1; y=2; z=3},
 * Quaternion {w=1; x=2; y=3; z=4}.
 */
#ifndef DQPOSE_WIRE_H
#define DQPOSE_WIRE_H

#include <stddef.h>
#include <stdint.h>

typedef struct {
    double *poses;      /* n_poses rows of [qw, qx, qy, qz, x, y, z]; NULL to only count */
    size_t n_poses;
    double *weights;    /* n_weights values; NULL to only count */
    size_t n_weights;
    int64_t method;
    double tolerance;
    uint64_t max_iterations;
} dq_blend_request;

/* Decodes buf. With r->poses / r->weights NULL it only counts (first pass); with arrays of the
 * counted sizes it fills them (second pass). Returns 0, or -1 for bytes it cannot decode. */
int dq_wire_blend_request(const uint8_t *buf, size_t len, dq_blend_request *r);

/* The served Blend from request bytes to response bytes (dqpose.v1.BlendResponse {Pose pose=1;
 * uint32 iterations=2; double residual=3}), with no object per pose.
 *
 * It takes only the plain case: a decodable request with 1..max_poses poses (each finite, unit
 * within DQ_UNIT_TOL), no weights or one valid weight per pose, any method (SCLERP with 2
 * poses), tolerance 0 (= default_tol) or finite > 0, max_iterations 0 (= default_max_iter) or
 * <= max_iter_limit, and a finite result. Anything else returns -1 and writes nothing: the caller
 * then takes its full path, which names the problem. On success it returns 0 and the response is
 * out[0 .. *out_len), byte for byte what the protobuf runtime writes for the same values (proto3:
 * zero scalars omitted, -0.0 kept). The arithmetic is the same sequence of calls as the Python
 * API's (dq_from_pose, dq_unit, dq_weights, dq_blend_set, dq_unit, dq_to_pose), so both paths
 * give identical bits. */
#define DQ_WIRE_RESPONSE_MAX 96
typedef struct {
    size_t max_poses;
    double default_tol;
    uint32_t default_max_iter;
    uint32_t max_iter_limit;
} dq_wire_config;

int dq_wire_blend(const uint8_t *buf, size_t len, const dq_wire_config *cfg, uint8_t *out,
                  size_t *out_len);

/* The served BlendBatch: BlendBatchRequest {repeated BlendRequest requests=1} bytes to
 * BlendBatchResponse {repeated BlendResponse responses=1} bytes, each request as dq_wire_blend.
 * dq_wire_batch_count counts the requests and their poses (-1 for bytes it cannot decode);
 * dq_wire_blend_batch then writes at most n_requests * DQ_WIRE_BATCH_ITEM_MAX bytes to out, or
 * returns -1 when any request is not plain (the caller's full path then names the problem). */
#define DQ_WIRE_BATCH_ITEM_MAX (DQ_WIRE_RESPONSE_MAX + 2)
int dq_wire_batch_count(const uint8_t *buf, size_t len, size_t *n_requests, size_t *n_poses);
int dq_wire_blend_batch(const uint8_t *buf, size_t len, const dq_wire_config *cfg, uint8_t *out,
                        size_t *out_len);

/*
 * StreamFuse's hot path: FuseStreamRequest {FusionOptions options=1; double output_rate=2;
 * repeated Measurement measurements=3} wire bytes to arrays, every measurement checked here by
 * the rules of the Python path it replaces. Measurement {string source=1; string body=2;
 * double time=3; Pose pose=4; repeated double covariance=5; double weight=6}.
 *
 * The plain case only: no options or output_rate (those are the first request's, which the
 * protobuf path reads), no unknown field in a request or a measurement, names in ASCII (so
 * that they are valid UTF-8 as protobuf requires), and no measurement on an edge where the two
 * paths could decide differently (a pose from_pose accepts but the unit check would not; a
 * covariance with extreme entries or on the edge of positive definite: see
 * dq_covariance_check). Anything else returns -1 and the caller parses the bytes with
 * protobuf, which names every problem.
 *
 * Each measurement gets a code: which check refused it, in the order the Python path checks
 * (first what service/rpc/convert.py measurements_to_arrays checks, then what
 * service/fusion/ Tracker checks). The texts are the Python path's, in one place: the caller
 * runs that path's check on a refused measurement alone to name it.
 */
enum {
    DQ_MEAS_OK = 0,
    /* measurements_to_arrays */
    DQ_MEAS_TIME = 1,            /* time not finite */
    DQ_MEAS_COV_COUNT = 2,       /* covariance of neither 0 nor 36 values */
    DQ_MEAS_COV_AND_WEIGHT = 3,  /* both a covariance and a weight */
    DQ_MEAS_WEIGHT = 4,          /* weight (0 = 1) not positive and finite */
    DQ_MEAS_POSE = 5,            /* dq_from_pose refuses the pose */
    DQ_MEAS_CONVERT_LAST = 5,
    /* Tracker */
    DQ_MEAS_BODY = 6,            /* no body */
    DQ_MEAS_COV_NONFINITE = 7,
    DQ_MEAS_COV_ASYMMETRIC = 8,
    DQ_MEAS_COV_NOT_SPD = 9,
    DQ_MEAS_COV_SCALE = 10       /* a variance outside fusion.h's bounds */
};

typedef struct {
    size_t n;          /* measurements (dq_wire_fuse_count), and the rows of the arrays below */
    double *poses;     /* n x 8: the pose as dq_from_pose makes it (a refused pose: zeros) */
    double *covs;      /* n x 36: the symmetric part of the covariance (I / weight when none);
                        * as given where code >= DQ_MEAS_COV_NONFINITE */
    double *times;     /* n */
    uint32_t *spans;   /* n x 6: offset and length in buf of the measurement, its source, its body */
    uint8_t *codes;    /* n */
    int publish;       /* the bytes are a World PublishRequest (measurements field 1, beside a
                        * producer string 2 and a sequence varint 3), not a FuseStreamRequest */
    size_t producer, producer_len;  /* where its producer is in buf (the last one given) */
    uint64_t sequence;              /* its sequence (the last one given; 0: none) */
} dq_fuse_stream;

/* Counts the measurements (r->n), and a PublishRequest's producer and sequence; -1 outside the
 * plain case at the request's level. */
int dq_wire_fuse_count(const uint8_t *buf, size_t len, dq_fuse_stream *r);
/* Fills r's arrays (r->n rows, as counted) and checks every measurement; -1 outside the plain
 * case. sym_tol: the relative symmetry tolerance of a covariance (service/fusion/'s). */
int dq_wire_fuse_stream(const uint8_t *buf, size_t len, double sym_tol, dq_fuse_stream *r);

/* The client's side of the same: one Measurement as FuseStreamRequest.measurements (field 3),
 * written to out, which has room for DQ_WIRE_MEASUREMENT_MAX + source_len + body_len bytes;
 * returns the bytes written. Fields at their default (+0.0, an empty name, cov NULL) are left
 * out and the pose's position and orientation are always present, as protobuf's serializer
 * does for the client's messages, so the bytes are SerializeToString()'s. */
/* tag and length, source's and body's tags and lengths, time, pose, covariance, weight */
#define DQ_WIRE_MEASUREMENT_MAX (11 + 11 + 11 + 9 + 69 + 291 + 9)
size_t dq_wire_measurement(uint8_t *out, const char *source, size_t source_len, const char *body,
                           size_t body_len, double time, const double q[4], const double t[3],
                           const double *cov, double weight);

#endif
