"""Protobuf wire bytes built and read without a message object per pose: requests written
straight from arrays (the client's), the C core's decoders and fast paths glued to the servers
(``service/csrc/wire.c``), and answers read back in NumPy. Each gives the bytes (or values)
protobuf would, and ``None`` where it does not apply, for the protobuf path to take.

Tags are ``field << 3 | wire type``: ``0x09``.. doubles, ``0x10`` a varint, ``0x0A``/``0x12``
length-delimited messages.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from dqpose import _dqcore
from dqpose.errors import FieldError
from dqpose.fusion import Fused
from dqpose.fusion.validation import SYMMETRY_TOL
from dqpose.rpc.fusion_convert import (
    STATUS_ENUMS,
    Measurements,
    measurement_columns,
    wire_measurement_error,
)
from dqpose.rpc.varint import packed, varint

# ---- the servers' C fast paths -------------------------------------------------------------------

def decode_blend_request(data: bytes):
    """A serialized ``BlendRequest`` straight to ``(poses (n, 7), weights (m,), method,
    tolerance, max_iterations)`` by the C decoder (service/csrc/wire.h), ~30x faster than
    reading the parsed message; ``None`` for bytes it does not understand (then parse them
    with protobuf, which names the problem)."""
    return _dqcore.blend_request_from_wire(data)


def blend_wire(data: bytes, max_poses: int, default_tol: float, default_max_iter: int,
               max_iter_limit: int) -> bytes | None:
    """The served Blend from request bytes to ``BlendResponse`` bytes, all in C
    (service/csrc/wire.h: ``dq_wire_blend``), for plain valid requests; ``None`` for anything
    else, which the full path then handles and names."""
    return _dqcore.blend_wire(data, max_poses, default_tol, default_max_iter, max_iter_limit)


def blend_batch_wire(data: bytes, max_requests: int, max_total_poses: int, max_poses: int,
                     default_tol: float, default_max_iter: int, max_iter_limit: int):
    """The served BlendBatch in C: ``(BlendBatchResponse bytes, number of requests)`` when the
    batch is within the limits and every request is plain and valid (see :func:`blend_wire`);
    ``None`` for anything else."""
    return _dqcore.blend_batch_wire(data, max_requests, max_total_poses, max_poses, default_tol,
                                    default_max_iter, max_iter_limit)


# ---- requests from arrays (client side) ---------------------------------------------------------

# One Pose as a length-delimited field with every double written out (proto3 parsers take
# explicit zeros), so a whole repeated field is one NumPy record array: Pose {position=1
# Vector3 {x=1; y=2; z=3}; orientation=2 Quaternion {w=1; x=2; y=3; z=4}}.
_POSE_RECORD = np.dtype([("k", "u1"), ("n", "u1"),
                         ("pk", "u1"), ("pn", "u1"), ("p", [("k", "u1"), ("v", "<f8")], 3),
                         ("ok", "u1"), ("on", "u1"), ("o", [("k", "u1"), ("v", "<f8")], 4)])


def _pose_records(q: np.ndarray, t: np.ndarray, field: int = 1) -> np.ndarray:
    q, t = np.asarray(q, dtype=np.float64), np.asarray(t, dtype=np.float64)
    r = np.empty(len(q), _POSE_RECORD)
    r["k"], r["n"] = field << 3 | 2, _POSE_RECORD.itemsize - 2
    r["pk"], r["pn"], r["ok"], r["on"] = 0x0A, 27, 0x12, 36
    r["p"]["k"], r["o"]["k"] = [0x09, 0x11, 0x19], [0x09, 0x11, 0x19, 0x21]
    r["p"]["v"], r["o"]["v"] = t, q
    return r


def poses_wire(q: np.ndarray, t: np.ndarray, field: int = 1) -> bytes:
    """Rows of ``q (n, 4)`` and ``t (n, 3)`` as repeated ``Pose`` field ``field``, in wire bytes:
    what ``pose_msgs`` plus serialisation gives (values as given), ~40x faster: one template
    pose repeated, the doubles written through strided views."""
    q, t = np.asarray(q, dtype=np.float64), np.asarray(t, dtype=np.float64)
    n = len(q)
    out = bytearray(_POSE_TEMPLATE * n)
    buf = np.frombuffer(out, np.uint8)
    if field != 1:
        buf[::_POSE_RECORD.itemsize] = field << 3 | 2
    _doubles_at(buf, 5, (n, 3), (_POSE_RECORD.itemsize, 9))[...] = t
    _doubles_at(buf, 34, (n, 4), (_POSE_RECORD.itemsize, 9))[...] = q
    return bytes(out)


def _doubles_at(buf: np.ndarray, offset: int, shape: tuple, strides: tuple) -> np.ndarray:
    """A float64 view of ``buf`` at any byte offset and strides (unaligned is fine for NumPy)."""
    if 0 in shape:
        return np.empty(shape)
    return np.ndarray(shape, "<f8", buf, offset, strides)


_POSE_TEMPLATE = _pose_records(np.zeros((1, 4)), np.zeros((1, 3))).tobytes()


def blend_request_wire(q: np.ndarray, t: np.ndarray, weights=None, method: int = 0,
                       tolerance: float = 0.0, max_iterations: int = 0) -> bytes:
    """A serialized ``BlendRequest`` from arrays, without a message object per pose."""
    if not 0 <= int(max_iterations) <= 0xFFFFFFFF or int(max_iterations) != max_iterations:
        raise ValueError(f"max_iterations: must be a whole number within 0..4294967295, "
                         f"got {max_iterations!r}")
    parts = [poses_wire(q, t)]
    parts.append(packed(2, np.asarray([] if weights is None else weights, dtype="<f8").ravel()))
    if method:
        parts += [b"\x18", varint(method & 0xFFFFFFFFFFFFFFFF)]      # enum: int32 as varint
    tol = np.float64(tolerance).astype("<f8").tobytes()
    if tol != bytes(8):                                         # -0.0 is sent, as protobuf does
        parts += [b"\x21", tol]
    if max_iterations:
        parts += [b"\x28", varint(int(max_iterations))]
    return b"".join(parts)


def blend_batch_items_wire(q: np.ndarray, t: np.ndarray, counts: np.ndarray,
                           weights: np.ndarray, weight_counts: np.ndarray, method: int = 0,
                           tolerance: float = 0.0, max_iterations: int = 0
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Many ``BlendRequest`` s as items of ``BlendBatchRequest.requests``, in wire bytes: request
    ``i`` has the next ``counts[i]`` rows of ``q (N, 4)``/``t (N, 3)`` and the next
    ``weight_counts[i]`` values of ``weights`` (0: none, equal weights), and all share
    ``method``, ``tolerance`` and ``max_iterations``. Returns ``(bytes as uint8, offsets)``:
    item ``i`` is ``buf[offsets[i]:offsets[i + 1]]``, so any run of items is a valid
    ``BlendBatchRequest``. Requests of one shape are one template row copied, then the doubles
    written through strided views: no Python work per pose or per request."""
    counts, weight_counts = np.asarray(counts, np.int64), np.asarray(weight_counts, np.int64)
    q, t = np.asarray(q, np.float64), np.asarray(t, np.float64)
    weights = np.asarray(weights, np.float64).ravel()
    m = len(counts)
    # the scalar fields after the poses and weights: an empty request with them set
    tail = blend_request_wire(np.empty((0, 4)), np.empty((0, 3)), None, method, tolerance,
                              max_iterations)
    pose, size = _POSE_TEMPLATE, len(_POSE_TEMPLATE)
    if m and (counts == counts[0]).all() and (weight_counts == weight_counts[0]).all():
        shapes, which = np.array([[counts[0], weight_counts[0]]]), np.zeros(m, np.int64)
    else:
        shapes, which = np.unique(np.stack([counts, weight_counts], axis=1), axis=0,
                                  return_inverse=True)
        which = which.ravel()
    pose_start = np.concatenate([[0], np.cumsum(counts)])
    w_start = np.concatenate([[0], np.cumsum(weight_counts)])
    groups, sizes = [], np.empty(m, np.int64)
    for g, (n, k) in enumerate(shapes.tolist()):
        whead = b"\x12" + varint(8 * k) if k else b""
        body = n * size + len(whead) + 8 * k + len(tail)
        head = b"\x0a" + varint(body)
        rows = np.flatnonzero(which == g)
        items = np.empty((len(rows), len(head) + body), np.uint8)
        items[:] = np.frombuffer(head + pose * n + whead + bytes(8 * k) + tail, np.uint8)
        if len(shapes) == 1:                   # rows are every request, in order: no gather
            qs, ts, ws = q.reshape(m, n, 4), t.reshape(m, n, 3), weights.reshape(m, k)
        else:
            idx = pose_start[rows, None] + np.arange(n)
            qs, ts, ws = q[idx], t[idx], weights[w_start[rows, None] + np.arange(k)]
        # Pose: k n | 0a 1b (09 x) (11 y) (19 z) | 12 24 (09 w) (11 x) (19 y) (21 z)
        row = items.shape[1]
        _doubles_at(items, len(head) + 5, (len(rows), n, 3), (row, size, 9))[...] = ts
        _doubles_at(items, len(head) + 34, (len(rows), n, 4), (row, size, 9))[...] = qs
        _doubles_at(items, len(head) + n * size + len(whead), (len(rows), k), (row, 8))[...] = ws
        groups.append((rows, items))
        sizes[rows] = row
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    if len(groups) == 1:
        return groups[0][1].ravel(), offsets
    buf = np.empty(offsets[-1], np.uint8)
    for rows, items in groups:
        buf[offsets[rows, None] + np.arange(items.shape[1])] = items
    return buf, offsets


_STAMPED_RECORD = np.dtype([("k", "u1"), ("n", "u1"), ("tk", "u1"), ("time", "<f8"),
                            ("pose", _POSE_RECORD)])


def interpolate_request_wire(keyframes: bytes, times: np.ndarray, interpolation: int) -> bytes:
    """A serialized ``InterpolateRequest``: ``keyframes`` from :func:`stamped_poses_wire`, the
    ``times`` packed, then the ``interpolation`` enum."""
    parts = [keyframes, packed(2, np.ravel(times))]
    if interpolation:
        parts += [b"\x18", varint(interpolation & 0xFFFFFFFFFFFFFFFF)]
    return b"".join(parts)


def stamped_poses_wire(times: np.ndarray, q: np.ndarray, t: np.ndarray, field: int = 1) -> bytes:
    """``times (n,)`` with rows of ``q``/``t`` as repeated ``StampedPose`` field ``field``
    (``StampedPose {double time = 1; Pose pose = 2}``), in wire bytes, values as given."""
    r = np.empty(len(q), _STAMPED_RECORD)
    r["k"], r["n"], r["tk"] = field << 3 | 2, _STAMPED_RECORD.itemsize - 2, 0x09
    r["time"], r["pose"] = times, _pose_records(q, t, field=2)
    return r.tobytes()


def measurements_wire(poses, covariances=None, weights=None, names=None, bodies=None,
                      times=None, field: int = 3) -> bytes:
    """:func:`~dqpose.rpc.fusion_convert.measurement_msgs` as repeated
    ``FuseStreamRequest.measurements`` (``field`` 3; 1: ``PublishRequest.measurements``) in wire
    bytes, the bytes protobuf would write for them (``service/csrc/wire.c``), ~30x faster: what
    a client streaming thousands of measurements a second spends per message."""
    q, t, covariances, weights, names, bodies, times = measurement_columns(
        poses, covariances, weights, names, bodies, times)
    return _dqcore.measurements_wire(
        q, t, None if covariances is None else covariances.reshape(len(q), 36),
        None if weights is None else np.asarray(weights, np.float64),
        None if times is None else np.asarray(times, np.float64), names, bodies, field)


def messages_wire(messages: list[bytes], field: int = 1) -> bytes:
    """Serialized messages as the repeated message field ``field`` (< 16): each behind its tag
    and length, not parsed or serialized again (World.SubscribeBatches' ``FusedPoseBatch``)."""
    tag = bytes([field << 3 | 2])
    return b"".join(part for m in messages for part in (tag, varint(len(m)), m))


def publish_request_wire(batch, producer: str, sequence: int) -> bytes:
    """A serialized World ``PublishRequest`` of ``batch`` (a client ``Batch``: its
    measurements), ``producer`` and ``sequence``: the bytes protobuf writes for it, fields in
    order, empty ones left out."""
    poses, covariances, weights, names, bodies, times = batch
    parts = [measurements_wire(poses, covariances, weights, names, bodies, times, field=1)]
    if producer:
        name = producer.encode()
        parts += [b"\x12", varint(len(name)), name]
    if sequence:
        parts += [b"\x18", varint(sequence)]
    return b"".join(parts)


# ---- a fused pose (the servers' answers) ---------------------------------------------------------

def fused_pose_bytes(f: Fused, body: str, time: float, request: int = 0, measurements=(),
                     pose=None, covariance=None) -> bytes:
    """The ``FusedPose`` of fit ``f`` of ``body`` at ``time`` in wire bytes, written in C
    (service/csrc/fused_wire.h) as protobuf writes the message
    :func:`~dqpose.rpc.fusion_convert.fused_to_msg` makes with ``request`` and ``measurements``
    set: every answer a server gives of a fit (Fuse, StreamFuse, a World's Subscribe) goes
    through this one writer. ``pose`` and ``covariance``: another pose and covariance than the
    fit's (a World answer relative to another body), its other fields the fit's."""
    rejected = f.rejected
    return _dqcore.fused_pose_wire(
        body, float(time), f.mean if pose is None else pose,
        f.covariance if covariance is None else covariance, f.inliers,
        [r.index for r in rejected], [r.reason for r in rejected], [r.source for r in rejected],
        f.chi2, f.dof, f.iterations, STATUS_ENUMS[f.status], f.distances, f.nis, f.tested,
        f.residuals, [(s.name, s.count, s.rejected, s.nis_mean, s.low, s.high, int(s.verdict))
                      for s in f.sources], request, measurements,
        [(d.index, d.source, d.age, d.reason) for d in f.dropped], f.twist,
        f.twist_covariance, f.extrapolation,
        [(a.name, a.configured, a.prior_sigma, a.value, a.sigma) for a in f.latencies])


# ---- answers read back (client side) ------------------------------------------------------------

# What the client reads back: fields by tag byte, to a column of one output row, or a nested
# message.
_VECTOR3 = {0x09: ("d", 4), 0x11: ("d", 5), 0x19: ("d", 6)}
_QUATERNION = {0x09: ("d", 0), 0x11: ("d", 1), 0x19: ("d", 2), 0x21: ("d", 3)}
_POSE = {0x0A: ("m", _VECTOR3), 0x12: ("m", _QUATERNION)}
_BLEND_RESPONSE = {0x0A: ("m", _POSE), 0x10: ("v", 7), 0x19: ("d", 8)}


def _layout(item: bytes, schema: dict, start: int, end: int, values: dict, fixed: list) -> bool:
    """Walk one message the way protobuf would: where each value sits (``values``: column ->
    ``(kind, position, length)``, the last occurrence wins) and which bytes are structure
    (``fixed``: tags, lengths, varint continuation bits). False for anything else."""
    i = start
    while i < end:
        kind, arg = schema.get(item[i], (None, None))
        fixed.append(i)
        if kind == "d":
            if i + 9 > end:
                return False
            values[arg] = ("d", i + 1, 8)
            i += 9
        elif kind == "v":
            j = i + 1
            while j < end and item[j] & 0x80:
                j += 1
            if j >= end or j - i > 10:
                return False
            values[arg] = ("v", i + 1, j - i)
            i = j + 1
        elif kind == "m":
            if i + 1 >= end or item[i + 1] & 0x80 or i + 2 + item[i + 1] > end:
                return False
            fixed.append(i + 1)
            if not _layout(item, arg, i + 2, i + 2 + item[i + 1], values, fixed):
                return False
            i += 2 + item[i + 1]
        else:
            return False
    return True


def blend_responses_from_wire(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``BlendBatchResponse`` bytes to ``(poses (m, 7) [qw, qx, qy, qz, x, y, z], iterations
    (m,), residuals (m,))`` without a message object per response, when every response has the
    layout of the first (same fields present, same lengths: what the server sends for one
    method); ``None`` otherwise (then parse with protobuf). The values are the parser's, bit for
    bit."""
    buf = np.frombuffer(data, np.uint8)
    if buf.size == 0:
        return np.empty((0, 7)), np.empty(0, np.uint32), np.empty(0)
    if buf.size < 2 or buf[0] != 0x0A or buf[1] & 0x80:
        return None
    stride = 2 + int(buf[1])
    if buf.size % stride:
        return None
    values: dict = {}
    fixed = [0, 1]
    if not _layout(data, _BLEND_RESPONSE, 2, stride, values, fixed):
        return None
    items = buf.reshape(-1, stride)
    varint = [p for kind, p, n in values.values() if kind == "v" for p in range(p, p + n)]
    if not ((items[:, fixed] == items[0, fixed]).all()
            and ((items[:, varint] & 0x80) == (items[0, varint] & 0x80)).all()):
        return None
    out = np.zeros((len(items), 9))
    iterations = np.zeros(len(items), np.uint64)
    for col, (kind, p, n) in values.items():
        if kind == "d":
            out[:, col] = np.ascontiguousarray(items[:, p:p + 8]).view("<f8")[:, 0]
        else:   # little-endian base-128; a uint32 field keeps the low 32 bits
            for j in range(n):
                iterations |= (items[:, p + j] & 0x7F).astype(np.uint64) << np.uint64(7 * j)
    return out[:, :7], (iterations & 0xFFFFFFFF).astype(np.uint32), out[:, 8]


# ---- StreamFuse: measurements in C ---------------------------------------------------------------

#: The last of :attr:`WireMeasurements.codes` that ``measurements_to_arrays``'s checks give.
CONVERT_LAST: int = _dqcore.MEASUREMENT_CONVERT_LAST


class WireMeasurements(NamedTuple):
    """A ``FuseStreamRequest``'s measurements decoded and checked in C
    (:func:`fuse_stream_from_wire`): every row, refused or not, with ``codes`` saying which check
    refused it (0: none; up to :data:`CONVERT_LAST` those of
    :func:`~dqpose.rpc.fusion_convert.measurements_to_arrays`, the
    rest :class:`fusion.Tracker`'s) and ``spans`` where its bytes are."""
    poses: np.ndarray          # (n, 8), as dq.from_pose makes them
    covariances: np.ndarray    # (n, 6, 6) symmetrised (as given where the Tracker refuses it)
    times: np.ndarray          # (n,)
    codes: np.ndarray          # (n,) uint8
    bodies: tuple[str, ...]
    sources: tuple[str, ...]
    spans: np.ndarray          # (n, 2): offset and length of the Measurement in the bytes


def fuse_stream_from_wire(data: bytes) -> WireMeasurements | None:
    """A serialized ``FuseStreamRequest`` of measurements only, decoded and checked by the C
    core (service/csrc/wire.h ``dq_wire_fuse_stream``) by the rules of
    :func:`~dqpose.rpc.fusion_convert.measurements_to_arrays` and :meth:`fusion.Tracker.ingest`;
    ``None`` for anything
    else (options, unknown fields, bytes protobuf would refuse, a measurement on the edge of a
    rule), which the protobuf path then takes."""
    out = _dqcore.fuse_stream_from_wire(data, SYMMETRY_TOL)
    return None if out is None else WireMeasurements(*out)


def publish_from_wire(data: bytes) -> WireMeasurements | None:
    """:func:`fuse_stream_from_wire` of a serialized World ``PublishRequest``: its measurements
    (field 1), its producer and sequence skipped (the caller reads them from the parsed
    message, which checks the producer's UTF-8)."""
    out = _dqcore.fuse_stream_from_wire(data, SYMMETRY_TOL, True)
    return None if out is None else WireMeasurements(*out)


def publish_head(data: bytes) -> tuple[str, int, int] | None:
    """A serialized World ``PublishRequest``'s producer, sequence and number of measurements,
    read by the C core as protobuf reads them (none of its measurements decoded); ``None`` for
    bytes outside its plain case (unknown fields, a producer that is not ASCII, bytes it cannot
    read), which protobuf then reads."""
    return _dqcore.publish_head(data)


def wire_rows(data: bytes, w: WireMeasurements,
              field: str) -> tuple[Measurements, list[tuple[int, FieldError]], np.ndarray]:
    """The decoded request ``w`` (of ``data``) as :func:`~dqpose.rpc.fusion_convert.
    measurements_to_arrays` gives it: the rows it keeps, the ones it refuses as ``(i,
    FieldError)`` with its texts (``field``: the repeated field's path), and the kept rows'
    codes (0, or the Tracker's check that refuses the row)."""
    codes = w.codes
    errors = ([(i, wire_measurement_error(data, w.spans[i], field, i))
               for i, c in enumerate(codes.tolist()) if 0 < c <= CONVERT_LAST]
              if np.count_nonzero(codes) else [])
    if not errors:
        return (Measurements(np.arange(len(w.times)), w.bodies, w.sources, w.times, w.poses,
                             w.covariances), errors, codes)
    index = np.flatnonzero((codes == 0) | (codes > CONVERT_LAST))
    rows = index.tolist()
    return (Measurements(index, tuple(w.bodies[i] for i in rows),
                         tuple(w.sources[i] for i in rows), w.times[index], w.poses[index],
                         w.covariances[index]), errors, codes[index])
