"""Protobuf messages <-> NumPy arrays for the gRPC layer, with errors named after proto fields.

The core names its arguments (``q[3]: zero quaternion``); only this layer knows that ``q[3]`` came
from ``poses[3].orientation``, so conversion validates per field and renames.
"""
from __future__ import annotations

import itertools
import math
import re
from typing import NamedTuple

import numpy as np

from dqpose import _dqcore, dq, fusion, handeye, trajectory
from dqpose.errors import FieldError, rename, rename_all
from dqpose.rpc._proto.dqpose.v1 import blending_pb2 as pb
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb
from dqpose.rpc._proto.dqpose.v1 import geometry_pb2 as geo
from dqpose.rpc._proto.dqpose.v1 import handeye_pb2 as hpb
from dqpose.rpc._proto.dqpose.v1 import trajectories_pb2 as tpb

def field_named(e: ValueError, fields: tuple[str, ...], default: str) -> FieldError:
    """``e`` as a :class:`FieldError` (an Infeasible stays one) whose text starts with a field
    path of the request, one of ``fields`` (``pairs`` covers ``pairs[3].robot_covariance``):
    as it is when it does, else after ``default``: what NumPy, SciPy or casadi raised from
    inside the domain (``Singular matrix``) then says which input it was about."""
    out = rename(e, {})
    if re.match(r"^(%s)\b" % "|".join(map(re.escape, fields)), str(out)):
        return out
    return type(out)(f"{default}: {out}")


def poses_to_flat(poses) -> np.ndarray:
    """Repeated ``Pose`` to ``(n, 7)`` rows ``[qw, qx, qy, qz, x, y, z]``, unvalidated."""
    # One flat list through np.array is the cheapest path out of upb messages (no per-pose
    # array objects); the server's hot path avoids even this (decode_blend_request).
    flat = np.array([(o.w, o.x, o.y, o.z, t.x, t.y, t.z)
                     for o, t in ((p.orientation, p.position) for p in poses)], dtype=np.float64)
    return flat.reshape(-1, 7)


def flat_to_dqs(flat: np.ndarray, field: str, sub: str = "") -> np.ndarray:
    """``(n, 7)`` rows to ``(n, 8)``; errors read ``{field}[i]{sub}.orientation: ...``."""
    try:
        return dq.from_pose(flat[:, :4], flat[:, 4:])
    except ValueError as e:
        raise rename(e, {"q": f"{field}{{}}{sub}.orientation",
                         "t": f"{field}{{}}{sub}.position"}) from None


def poses_to_dqs(poses, field: str, sub: str = "") -> np.ndarray:
    """Repeated ``Pose`` (or the ``.pose`` of repeated ``StampedPose`` with ``sub=".pose"``) to
    ``(n, 8)``; errors read ``{field}[i]{sub}.orientation: ...``."""
    if sub:
        poses = [p.pose for p in poses]
    return flat_to_dqs(poses_to_flat(poses), field, sub)


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


def dq_to_pose(a: np.ndarray, out: geo.Pose | None = None) -> geo.Pose:
    """One ``(8,)`` dual quaternion to a ``Pose`` (written into ``out`` when given)."""
    q, t = dq.to_pose(a)
    pose = geo.Pose() if out is None else out
    pose.position.x, pose.position.y, pose.position.z = t.tolist()
    o = pose.orientation
    o.w, o.x, o.y, o.z = q.tolist()
    return pose


def poses_to_arrays(poses) -> tuple[np.ndarray, np.ndarray]:
    """Repeated ``Pose`` to ``(q (n, 4), t (n, 3))`` without validation (client side)."""
    flat = poses_to_flat(poses)
    return flat[:, :4], flat[:, 4:]


def pose_msgs(q: np.ndarray, t: np.ndarray) -> list[geo.Pose]:
    """Rows of ``q (n, 4)`` and ``t (n, 3)`` to ``Pose`` messages, as given (no validation)."""
    return [geo.Pose(position=geo.Vector3(x=x, y=y, z=z),
                     orientation=geo.Quaternion(w=qw, x=qx, y=qy, z=qz))
            for (qw, qx, qy, qz), (x, y, z) in zip(np.asarray(q).tolist(), np.asarray(t).tolist())]


# One Pose as a length-delimited field with every double written out (proto3 parsers take
# explicit zeros), so a whole repeated field is one NumPy record array: Pose {position=1
# Vector3 {x=1; y=2; z=3}; orientation=2 Quaternion {w=1; x=2; y=3; z=4}}.
_POSE_RECORD = np.dtype([("k", "u1"), ("n", "u1"),
                         ("pk", "u1"), ("pn", "u1"), ("p", [("k", "u1"), ("v", "<f8")], 3),
                         ("ok", "u1"), ("on", "u1"), ("o", [("k", "u1"), ("v", "<f8")], 4)])


def _varint(v: int) -> bytes:
    out = bytearray()
    while v >= 0x80:
        out.append(v & 0x7F | 0x80)
        v >>= 7
    out.append(v)
    return bytes(out)


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
    w = np.asarray([] if weights is None else weights, dtype="<f8").ravel()
    if w.size:
        parts += [b"\x12", _varint(8 * w.size), w.tobytes()]          # packed doubles
    if method:
        parts += [b"\x18", _varint(method & 0xFFFFFFFFFFFFFFFF)]      # enum: int32 as varint
    tol = np.float64(tolerance).astype("<f8").tobytes()
    if tol != bytes(8):                                               # -0.0 is sent, as protobuf does
        parts += [b"\x21", tol]
    if max_iterations:
        parts += [b"\x28", _varint(int(max_iterations))]
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
        whead = b"\x12" + _varint(8 * k) if k else b""
        body = n * size + len(whead) + 8 * k + len(tail)
        head = b"\x0a" + _varint(body)
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
    times = np.ascontiguousarray(times, dtype="<f8")
    parts = [keyframes]
    if times.size:
        parts += [b"\x12", _varint(8 * times.size), times.tobytes()]
    if interpolation:
        parts += [b"\x18", _varint(interpolation & 0xFFFFFFFFFFFFFFFF)]
    return b"".join(parts)


def stamped_poses_wire(times: np.ndarray, q: np.ndarray, t: np.ndarray, field: int = 1) -> bytes:
    """``times (n,)`` with rows of ``q``/``t`` as repeated ``StampedPose`` field ``field``
    (``StampedPose {double time = 1; Pose pose = 2}``), in wire bytes, values as given."""
    r = np.empty(len(q), _STAMPED_RECORD)
    r["k"], r["n"], r["tk"] = field << 3 | 2, _STAMPED_RECORD.itemsize - 2, 0x09
    r["time"], r["pose"] = times, _pose_records(q, t, field=2)
    return r.tobytes()


# What the client reads back: fields by tag byte, to a column of one output row, or a nested
# message. Tags are (field << 3 | wire type): 0x09.. doubles, 0x10 a varint, 0x0A/0x12 messages.
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


def dqs_to_poses(dqs: np.ndarray) -> list[geo.Pose]:
    """``(n, 8)`` to a list of ``Pose`` messages."""
    return pose_msgs(*dq.to_pose(np.asarray(dqs, dtype=np.float64).reshape(-1, 8)))


def stamped_to_arrays(stamped, field: str = "keyframes") -> tuple[np.ndarray, np.ndarray]:
    """Repeated ``StampedPose`` to ``(times (n,), dqs (n, 8))``."""
    times = np.array([s.time for s in stamped], dtype=np.float64)
    return times, poses_to_dqs(stamped, field, ".pose")


def arrays_to_stamped(times: np.ndarray, dqs: np.ndarray) -> list[geo.StampedPose]:
    """``(n,)`` times and ``(n, 8)`` poses to ``StampedPose`` messages."""
    return [geo.StampedPose(time=s, pose=p)
            for s, p in zip(np.asarray(times).tolist(), dqs_to_poses(dqs))]


# dq.METHODS by name: its "dlb" is METHOD_DLB (tests/rpc/test_convert.py checks the values too).
METHOD_ENUMS = {name: pb.Method.Value(f"METHOD_{name.upper()}") for name in dq.METHODS}
METHOD_NAMES = {pb.METHOD_UNSPECIFIED: "dib", **{code: name for name, code in METHOD_ENUMS.items()}}
INTERPOLATION_NAMES = {geo.INTERPOLATION_UNSPECIFIED: "screw", geo.INTERPOLATION_SCREW: "screw",
                       geo.INTERPOLATION_TOOL_LINEAR: "tool_linear"}
INTERPOLATION_ENUMS = {"screw": geo.INTERPOLATION_SCREW, "tool_linear": geo.INTERPOLATION_TOOL_LINEAR}


# ---- fusion --------------------------------------------------------------------------------------
COVARIANCE_SIZE = fusion.DOF * fusion.DOF
DEFAULT_PROBABILITY = fusion.DEFAULT_PROBABILITY


class Measurements(NamedTuple):
    """Repeated ``Measurement`` as arrays; ``index[k]`` is the message's measurement of row k."""
    index: np.ndarray          # (n,) int
    bodies: tuple[str, ...]
    sources: tuple[str, ...]
    times: np.ndarray          # (n,)
    poses: np.ndarray          # (n, 8) T_frame_body, unit
    covariances: np.ndarray    # (n, 6, 6), as given (the domain checks SPD and finiteness)


def measurements_to_arrays(ms, field: str = "measurements",
                           errors: list | None = None, first: int = 0) -> Measurements:
    """Repeated ``Measurement`` to :class:`Measurements`. A bad measurement raises the
    :class:`FieldError` naming it (``{field}[i].time: ...``); with ``errors`` (a list) it is
    appended there as ``(i, FieldError)`` and left out instead. Each field is read for all
    measurements at once and checked in NumPy; only the measurements with a problem are looked
    at one by one, to name it. ``first``: the number the texts give ``ms[0]`` (``ms`` a part of
    the field)."""
    ms = list(ms)
    n = len(ms)
    times = np.array([m.time for m in ms], dtype=np.float64)
    weights = np.array([m.weight for m in ms], dtype=np.float64)
    counts = np.array([len(m.covariance) for m in ms], dtype=np.int64)
    flat = np.array([(o.w, o.x, o.y, o.z, t.x, t.y, t.z) for o, t in
                     ((m.pose.orientation, m.pose.position) for m in ms)],
                    dtype=np.float64).reshape(-1, 7)
    full = counts == COVARIANCE_SIZE
    bad = {}
    if full.all() and not weights.any() and np.isfinite(times).all():
        # the common case, every measurement with its 36 values: one pass, no checks to name
        covs = np.fromiter(itertools.chain.from_iterable(m.covariance for m in ms),
                           np.float64, n * COVARIANCE_SIZE).reshape(n, fusion.DOF, fusion.DOF)
        problems = ()
    else:
        covs = np.empty((n, COVARIANCE_SIZE))
        for k in np.flatnonzero(full).tolist():
            covs[k] = ms[k].covariance
        covs = covs.reshape(n, fusion.DOF, fusion.DOF)
        iso = counts == 0
        w = np.where(weights == 0.0, 1.0, weights)        # weight 0 means 1
        covs[iso] = np.eye(fusion.DOF) / w[iso, None, None]
        problems = (
        (~np.isfinite(times), lambda i: f"time: must be finite, got {ms[i].time!r}"),
        (~iso & ~full, lambda i: f"covariance: expected {COVARIANCE_SIZE} values (6x6, "
                                 f"row-major, rotation first) or none, got {counts[i]}"),
        (full & (weights != 0.0), lambda i: "weight: give a covariance or a weight, not both"),
        (iso & ~(np.isfinite(w) & (w > 0.0)),
         lambda i: f"weight: must be positive and finite (0 means 1), got {float(w[i])!r}"))
    for mask, text in problems:
        for i in np.flatnonzero(mask).tolist():
            bad.setdefault(i, FieldError(f"{field}[{first + i}].{text(i)}"))
    keep = np.ones(n, dtype=bool)
    if bad:
        keep[list(bad)] = False
    index = np.flatnonzero(keep)
    try:
        poses = dq.from_pose(flat[index, :4], flat[index, 4:])
    except ValueError:
        # Name the measurement, not the row: one at a time to find every bad one.
        for i in index.tolist():
            try:
                _pose_from_row(flat[i], f"{field}[{first + i}].pose")
            except FieldError as e:
                bad[i] = e
                keep[i] = False
        index = np.flatnonzero(keep)
        poses = dq.from_pose(flat[index, :4], flat[index, 4:])
    if bad:
        found = sorted(bad.items())
        if errors is None:
            raise found[0][1]
        errors.extend(found)
        errors.sort(key=lambda x: x[0])
    return Measurements(index, tuple(ms[i].body for i in index), tuple(ms[i].source for i in index),
                        times[index], poses, covs[index])


class WireMeasurements(NamedTuple):
    """A ``FuseStreamRequest``'s measurements decoded and checked in C
    (:func:`fuse_stream_from_wire`): every row, refused or not, with ``codes`` saying which check
    refused it (0: none; up to ``CONVERT_LAST`` those of :func:`measurements_to_arrays`, the
    rest :class:`fusion.Tracker`'s) and ``spans`` where its bytes are."""
    poses: np.ndarray          # (n, 8), as dq.from_pose makes them
    covariances: np.ndarray    # (n, 6, 6) symmetrised (as given where the Tracker refuses it)
    times: np.ndarray          # (n,)
    codes: np.ndarray          # (n,) uint8
    bodies: tuple[str, ...]
    sources: tuple[str, ...]
    spans: np.ndarray          # (n, 2): offset and length of the Measurement in the bytes

    CONVERT_LAST = _dqcore.MEASUREMENT_CONVERT_LAST


def fuse_stream_from_wire(data: bytes) -> WireMeasurements | None:
    """A serialized ``FuseStreamRequest`` of measurements only, decoded and checked by the C
    core (service/csrc/wire.h ``dq_wire_fuse_stream``) by the rules of
    :func:`measurements_to_arrays` and :meth:`fusion.Tracker.ingest`; ``None`` for anything
    else (options, unknown fields, bytes protobuf would refuse, a measurement on the edge of a
    rule), which the protobuf path then takes."""
    out = _dqcore.fuse_stream_from_wire(data, fusion._SYMMETRY_TOL)
    return None if out is None else WireMeasurements(*out)


def wire_measurement_error(data: bytes, span, field: str, i: int) -> FieldError:
    """The error :func:`measurements_to_arrays` names measurement ``i`` (its bytes at ``span``)
    with: one Measurement parsed and checked the protobuf way, so the text has one source."""
    msg = fpb.Measurement.FromString(data[int(span[0]):int(span[0]) + int(span[1])])
    errors: list = []
    measurements_to_arrays([msg], field, errors, first=i)
    return errors[0][1]


def _pose_from_row(row: np.ndarray, where: str) -> np.ndarray:
    """One ``[qw, qx, qy, qz, x, y, z]`` to ``(8,)``; errors read ``{where}.orientation: ...``."""
    try:
        return dq.from_pose(row[None, :4], row[None, 4:])[0]
    except ValueError as e:
        raise rename(e, {"q": f"{where}.orientation", "t": f"{where}.position"}) from None


def _optional_pose(msg, name: str, where: str) -> np.ndarray | None:
    if not msg.HasField(name):
        return None
    o, t = getattr(msg, name).orientation, getattr(msg, name).position
    return _pose_from_row(np.array([o.w, o.x, o.y, o.z, t.x, t.y, t.z], dtype=np.float64),
                          f"{where}.{name}")


DEFAULT_MAX_EXTRAPOLATION = fusion.DEFAULT_MAX_EXTRAPOLATION
DEFAULT_WINDOW = 0.2


class Options(NamedTuple):
    """``FusionOptions`` as the domain's arguments (:meth:`fuse_kwargs` those of
    :func:`fusion.fuse` and :class:`fusion.Tracker`)."""
    robust: bool
    time: float                      # 0: the newest measurement's
    sources: tuple[fusion.Source, ...]
    probability: float
    max_skew: float | None = None
    max_extrapolation: float | None = DEFAULT_MAX_EXTRAPOLATION
    window: float = 0.0              # 0: DEFAULT_WINDOW (StreamFuse)
    twist_covariance: np.ndarray | None = None
    acceleration_psd: np.ndarray | None = None

    def fuse_kwargs(self) -> dict:
        return dict(sources=self.sources, robust=self.robust, probability=self.probability,
                    max_skew=self.max_skew, max_extrapolation=self.max_extrapolation,
                    twist_covariance=self.twist_covariance,
                    acceleration_psd=self.acceleration_psd)


def options_from_msg(options, field: str = "options") -> Options:
    """``FusionOptions`` to :class:`Options`: frames converted and the proto's zeros turned into
    the domain's defaults here; the domain checks the rest (names, duplicates, signs, the twist
    prior) and its errors are renamed to these fields."""
    sources = []
    for k, s in enumerate(options.sources):
        where = f"{field}.sources[{k}]"
        sources.append(fusion.Source(s.name, _optional_pose(s, "extrinsic", where),
                                     _optional_pose(s, "body_offset", where), s.latency,
                                     s.latency_sigma or None))
    if not math.isfinite(options.time):
        raise FieldError(f"{field}.time: must be finite, got {options.time!r}")
    p = options.probability or DEFAULT_PROBABILITY
    if not 0.0 < p < 1.0:
        raise FieldError(f"{field}.probability: must be within (0, 1) (0 means "
                         f"{DEFAULT_PROBABILITY}), got {options.probability!r}")
    matrices = {}
    for name in ("twist_covariance", "acceleration_psd"):
        k = len(getattr(options, name))
        if k not in (0, COVARIANCE_SIZE):
            raise FieldError(f"{field}.{name}: expected {COVARIANCE_SIZE} values (6x6, "
                             f"row-major, rotation first) or none, got {k}")
        matrices[name] = np.array(getattr(options, name), dtype=np.float64).reshape(
            fusion.DOF, fusion.DOF) if k else None
    extrapolation = options.max_extrapolation or DEFAULT_MAX_EXTRAPOLATION
    return Options(
        bool(options.robust), float(options.time), tuple(sources), p,
        max_skew=options.max_skew or None,
        max_extrapolation=None if extrapolation == math.inf else extrapolation,
        window=options.window, **matrices)


def options_msg(robust: bool = False, time: float = 0.0, sources=(), probability: float = 0.0,
                max_skew: float | None = None,
                max_extrapolation: float | None = DEFAULT_MAX_EXTRAPOLATION,
                window: float = 0.0, twist_covariance=None, acceleration_psd=None):
    """``FusionOptions`` from the domain's arguments (``sources``: :class:`fusion.Source`;
    ``max_extrapolation`` None: unbounded)."""
    msg = fpb.FusionOptions(robust=bool(robust), time=float(time),
                            probability=float(probability or 0.0),
                            max_skew=float(max_skew or 0.0),
                            max_extrapolation=math.inf if max_extrapolation is None
                            else float(max_extrapolation),
                            window=float(window or 0.0))
    for name, value in (("twist_covariance", twist_covariance),
                        ("acceleration_psd", acceleration_psd)):
        if value is not None:
            c = np.asarray(value, dtype=np.float64)
            if c.shape != (fusion.DOF, fusion.DOF):
                raise ValueError(f"{name}: expected shape (6, 6), got {c.shape}")
            getattr(msg, name).extend(c.ravel().tolist())
    for s in sources or ():
        out = msg.sources.add(name=s.name, latency=float(s.latency),
                              latency_sigma=float(s.latency_sigma or 0.0))
        if s.extrinsic is not None:
            dq_to_pose(np.asarray(s.extrinsic, dtype=np.float64), out.extrinsic)
        if s.body_offset is not None:
            dq_to_pose(np.asarray(s.body_offset, dtype=np.float64), out.body_offset)
    return msg


def _measurement_columns(poses, covariances, weights, names, bodies, times):
    """The client's measurement arrays checked for shape: ``(q, t, covariances, weights, names,
    bodies, times)``, ``q``/``t`` the wire's (:func:`pose_arrays`), absent columns None."""
    a = np.asarray(poses, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 8:
        raise ValueError(f"poses: expected shape (n, 8), got {a.shape}")
    n = len(a)

    def column(x, name, tail=()):
        if x is None:
            return None
        if isinstance(x, str):
            raise ValueError(f"{name}: expected one value per measurement, got a string")
        c = list(x) if not tail else np.asarray(x, dtype=np.float64)
        if len(c) != n or (tail and c.shape[1:] != tail):
            shape = ", ".join(str(k) for k in (n,) + tail)
            raise ValueError(f"{name}: expected ({shape}) for {n} poses, got "
                             f"{getattr(c, 'shape', (len(c),))}")
        return c

    covariances = column(covariances, "covariances", (fusion.DOF, fusion.DOF))
    weights, names = column(weights, "weights"), column(names, "names")
    bodies, times = column(bodies, "bodies"), column(times, "times")
    if covariances is not None and weights is not None:
        raise ValueError("weights: give covariances or weights, not both")
    return (*pose_arrays(a), covariances, weights, names, bodies, times)


def measurement_msgs(poses, covariances=None, weights=None, names=None, bodies=None,
                     times=None) -> list:
    """``Measurement`` messages from arrays (client side; values as given, the server checks
    them): ``poses`` ``(n, 8)``, ``covariances`` ``(n, 6, 6)`` or ``weights`` ``(n,)`` or
    neither, and per-measurement ``names`` (sources), ``bodies`` and ``times``."""
    q, t, covariances, weights, names, bodies, times = _measurement_columns(
        poses, covariances, weights, names, bodies, times)
    out = []
    for i, m in enumerate(pose_msgs(q, t)):
        msg = fpb.Measurement(pose=m, source=names[i] if names else "",
                              body=bodies[i] if bodies else "",
                              time=float(times[i]) if times is not None else 0.0)
        if covariances is not None:
            msg.covariance.extend(covariances[i].ravel().tolist())
        elif weights is not None:
            msg.weight = float(weights[i])
        out.append(msg)
    return out


def measurements_wire(poses, covariances=None, weights=None, names=None, bodies=None,
                      times=None) -> bytes:
    """:func:`measurement_msgs` as repeated ``FuseStreamRequest.measurements`` in wire bytes,
    the bytes protobuf would write for them (``service/csrc/wire.c``), ~30x faster: what a
    client streaming thousands of measurements a second spends per message."""
    q, t, covariances, weights, names, bodies, times = _measurement_columns(
        poses, covariances, weights, names, bodies, times)
    return _dqcore.measurements_wire(
        q, t, None if covariances is None else covariances.reshape(len(q), 36),
        None if weights is None else np.asarray(weights, np.float64),
        None if times is None else np.asarray(times, np.float64), names, bodies)


def pose_arrays(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(n, 8)`` to the ``(q, t)`` of the wire (client side), by the core when the poses are
    valid. Invalid ones are sent as they are, so that the server's message, naming the field,
    applies."""
    try:
        return dq.to_pose(a)
    except ValueError:
        q = a[:, :4]
        t = 2.0 * _qmul(a[:, 4:], q * [1.0, -1.0, -1.0, -1.0])[:, 1:] / np.maximum(
            np.einsum("ij,ij->i", q, q), np.finfo(float).tiny)[:, None]
        return q, t


def _qmul(a, b):
    aw, ax, ay, az = a.T
    bw, bx, by, bz = b.T
    return np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw],
                    axis=-1)


STATUS_ENUMS = {s: s.value + 1 for s in fusion.Status}     # proto 0 is an error entry
STATUS_NAMES = {v: k for k, v in STATUS_ENUMS.items()}


def fused_to_msg(f: fusion.Fused, body: str, time: float, out=None):
    """A :class:`fusion.Fused` into a ``FusedPose`` (written into ``out`` when given)."""
    msg = fpb.FusedPose() if out is None else out
    msg.body, msg.time = body, float(time)
    dq_to_pose(f.mean, msg.pose)
    msg.covariance.extend(f.covariance.ravel().tolist())
    msg.inliers.extend(f.inliers.tolist())
    msg.rejected.extend(r.index for r in f.rejected)
    msg.rejected_sources.extend(r.source for r in f.rejected)
    msg.reasons.extend(r.reason for r in f.rejected)
    msg.chi2, msg.dof, msg.iterations = f.chi2, f.dof, f.iterations
    msg.status = STATUS_ENUMS[f.status]
    msg.distances.extend(f.distances.tolist())
    msg.nis.extend(f.nis.tolist())
    msg.tested.extend(f.tested.tolist())
    msg.residuals.extend(f.residuals.ravel().tolist())
    for s in f.sources:
        msg.sources.add(name=s.name, count=s.count, rejected=s.rejected, nis_mean=s.nis_mean,
                        low=s.low, high=s.high, verdict=int(s.verdict))
    for d in f.dropped:
        msg.dropped.add(index=d.index, source=d.source, age=d.age, reason=d.reason)
    if f.twist is not None:
        msg.twist.extend(f.twist.tolist())
        msg.twist_covariance.extend(f.twist_covariance.ravel().tolist())
    msg.extrapolation = f.extrapolation
    for a in f.latencies:
        msg.latencies.add(source=a.name, configured=a.configured, prior_sigma=a.prior_sigma,
                          value=a.value, sigma=a.sigma)
    return msg


def fused_from_msg(msg, probability: float = DEFAULT_PROBABILITY,
                   max_skew: float | None = None) -> fusion.Fused:
    """A ``FusedPose`` back into the :class:`fusion.Fused` it was made from (client side);
    ``probability`` and ``max_skew`` are the request's (the gate of each rejection, the bound
    of each drop)."""
    p, o = msg.pose.position, msg.pose.orientation
    nis = np.array(msg.nis, dtype=np.float64)
    gate = math.sqrt(fusion.chi2_quantile(probability, fusion.DOF))
    rejected = [fusion.Rejection(int(i), source, math.sqrt(nis[i]), gate, probability)
                for i, source in zip(msg.rejected, msg.rejected_sources)]

    def frozen(a):
        a = np.ascontiguousarray(a)
        a.flags.writeable = False
        return a

    return fusion.Fused(
        status=STATUS_NAMES.get(msg.status, fusion.Status.CONVERGED),
        mean=frozen(dq.from_pose((o.w, o.x, o.y, o.z), (p.x, p.y, p.z))),
        covariance=frozen(np.array(msg.covariance, dtype=np.float64).reshape(6, 6)),
        residuals=frozen(np.array(msg.residuals, dtype=np.float64).reshape(-1, 6)),
        distances=frozen(np.array(msg.distances, dtype=np.float64)),
        nis=frozen(nis),
        tested=frozen(np.array(msg.tested, dtype=bool)),
        inliers=frozen(np.array(msg.inliers, dtype=np.int64)),
        rejected=tuple(rejected),
        chi2=msg.chi2, dof=msg.dof, iterations=msg.iterations,
        sources=tuple(fusion.SourceStats(s.name, s.count, s.rejected, s.nis_mean, s.low, s.high,
                                         fusion.Verdict(s.verdict)) for s in msg.sources),
        time=msg.time,
        twist=frozen(np.array(msg.twist, dtype=np.float64)) if msg.twist else None,
        twist_covariance=frozen(np.array(msg.twist_covariance, dtype=np.float64).reshape(6, 6))
        if msg.twist else None,
        extrapolation=msg.extrapolation,
        dropped=tuple(fusion.Dropped(d.index, d.source, d.age, max_skew or 0.0)
                      for d in msg.dropped),
        latencies=tuple(fusion.Latency(a.source, a.configured, a.prior_sigma, a.value, a.sigma)
                        for a in msg.latencies))


# ---- trajectories --------------------------------------------------------------------------------

PLAN_INTERPOLATIONS = {geo.INTERPOLATION_UNSPECIFIED: "tool_linear",
                       geo.INTERPOLATION_SCREW: "screw",
                       geo.INTERPOLATION_TOOL_LINEAR: "tool_linear"}


def limits_from_msg(msg, field: str = "limits"):
    """A ``Limits`` message to :class:`dqpose.trajectory.Limits`; errors name ``field``."""
    try:
        return trajectory.Limits(**{name: getattr(msg, name) for name in trajectory.LIMIT_FIELDS})
    except ValueError as e:
        raise rename(e, {"limits": field}) from None


def limits_msg(limits) -> tpb.Limits:
    return tpb.Limits(**{name: float(getattr(limits, name)) for name in trajectory.LIMIT_FIELDS})


class PlanArgs(NamedTuple):
    """A ``PlanRequest`` as the arguments of :func:`dqpose.trajectory.plan`."""
    waypoints: list
    limits: object
    interpolation: str
    start_velocity: np.ndarray | None
    rate_hz: float


def plan_from_msg(req, field: str = "", need_rate: bool = True) -> PlanArgs:
    """A ``PlanRequest`` to :class:`PlanArgs`; errors name the field under ``field`` (``"plan."``
    inside an ``ExecuteRequest``)."""
    mode = PLAN_INTERPOLATIONS.get(req.interpolation)
    if mode is None:
        raise FieldError(f"{field}interpolation: unknown Interpolation value {req.interpolation}")
    rate = float(req.rate_hz)
    if need_rate and not (math.isfinite(rate) and 0 < rate <= 10_000):
        raise FieldError(f"{field}rate_hz: must be within (0, 10000] samples per second, got {rate:g}")
    if not req.HasField("limits"):
        raise FieldError(f"{field}limits: required (velocity and acceleration limits)")
    limits = limits_from_msg(req.limits, f"{field}limits")
    dqs = poses_to_dqs(req.waypoints, f"{field}waypoints", ".pose")
    waypoints = [trajectory.Waypoint(pose=dqs[i], time=w.time, blend_radius=w.blend_radius)
                 for i, w in enumerate(req.waypoints)]
    start = None
    if req.HasField("start_linear_velocity") or req.HasField("start_angular_velocity"):
        v, w = req.start_linear_velocity, req.start_angular_velocity
        start = np.array([v.x, v.y, v.z, w.x, w.y, w.z], dtype=np.float64)
        for name, part in (("start_linear_velocity", start[:3]),
                           ("start_angular_velocity", start[3:])):
            if not np.isfinite(part).all():
                raise FieldError(f"{field}{name}: contains NaN or infinity")
    return PlanArgs(waypoints, limits, mode, start, rate)


def plan_msg(waypoints, limits, rate_hz: float = 0.0, interpolation: str = "tool_linear",
             start_velocity=None):
    """Client side: the ``PlanRequest`` of :func:`dqpose.trajectory.plan`'s arguments
    (``waypoints``: :class:`~dqpose.trajectory.Waypoint` or ``(8,)`` poses)."""
    if interpolation not in trajectory.INTERPOLATIONS:
        raise ValueError(f"interpolation: unknown {interpolation!r}; expected one of "
                         f"{', '.join(trajectory.INTERPOLATIONS)}")
    wps = [w if isinstance(w, trajectory.Waypoint) else trajectory.Waypoint(pose=np.asarray(w))
           for w in waypoints]
    poses = pose_msgs(*pose_arrays(np.array([w.pose for w in wps], dtype=np.float64).reshape(-1, 8)))
    req = tpb.PlanRequest(
        waypoints=[tpb.Waypoint(pose=p, time=w.time, blend_radius=w.blend_radius)
                   for p, w in zip(poses, wps)],
        limits=limits_msg(limits), rate_hz=rate_hz,
        interpolation=INTERPOLATION_ENUMS[interpolation])
    if start_velocity is not None:
        s = np.asarray(start_velocity, dtype=np.float64).reshape(6).tolist()
        req.start_linear_velocity.CopyFrom(geo.Vector3(x=s[0], y=s[1], z=s[2]))
        req.start_angular_velocity.CopyFrom(geo.Vector3(x=s[3], y=s[4], z=s[5]))
    return req


def plan_info_msg(traj):
    return tpb.PlanInfo(duration=traj.duration, segments=[
        tpb.Segment(start=s.start, duration=s.duration, binding=s.binding) for s in traj.segments])


def sample_msgs(samples) -> list:
    """:class:`dqpose.trajectory.Samples` to ``TrajectorySample`` messages."""
    q, t = pose_arrays(samples.pose)
    v = np.asarray(samples.linear_velocity).tolist()
    w = np.asarray(samples.angular_velocity).tolist()
    return [tpb.TrajectorySample(time=time, pose=pose, linear_velocity=geo.Vector3(x=a, y=b, z=c),
                                 angular_velocity=geo.Vector3(x=d, y=e, z=f))
            for time, pose, (a, b, c), (d, e, f)
            in zip(np.asarray(samples.time).tolist(), pose_msgs(q, t), v, w)]


def stamped_msgs(times, dqs) -> list:
    """Client side: ``(n,)`` times and ``(n, 8)`` poses to ``StampedPose`` messages as given (the
    server names what is wrong with them)."""
    return [geo.StampedPose(time=s, pose=p)
            for s, p in zip(np.asarray(times, dtype=np.float64).tolist(),
                            pose_msgs(*pose_arrays(np.asarray(dqs, dtype=np.float64))))]


def samples_from_msgs(msgs):
    """``TrajectorySample`` messages to ``(time (N,), pose (N, 8), linear_velocity (N, 3),
    angular_velocity (N, 3))`` (client side, unvalidated)."""
    msgs = list(msgs)
    q, t = poses_to_arrays([m.pose for m in msgs])
    vel = np.array([(m.linear_velocity.x, m.linear_velocity.y, m.linear_velocity.z,
                     m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z)
                    for m in msgs], dtype=np.float64).reshape(-1, 6)
    times = np.array([m.time for m in msgs], dtype=np.float64)
    return times, dq.from_pose(q, t) if len(msgs) else np.zeros((0, 8)), vel[:, :3], vel[:, 3:]


# ---- hand-eye ------------------------------------------------------------------------------------

SETUP_NAMES = {hpb.SETUP_EYE_IN_HAND: "eye_in_hand", hpb.SETUP_EYE_TO_HAND: "eye_to_hand"}
SETUP_ENUMS = {name: code for code, name in SETUP_NAMES.items()}
#: the domain's argument names -> the request's fields (``{}``: the pair's index)
CALIBRATE_FIELDS = {"base_flange": "pairs{}.base_to_flange",
                    "camera_target": "pairs{}.camera_to_target",
                    "camera_covariance": "pairs{}.camera_covariance",
                    "robot_covariance": "pairs{}.robot_covariance",
                    "corners": "pairs{}.corners", "board_points": "target_points"}


class CalibrateArgs(NamedTuple):
    """A ``CalibrateRequest`` as the arguments of :func:`dqpose.handeye.calibrate`."""
    setup: str
    base_flange: np.ndarray      # (n, 8) T_base_flange, unit
    camera_target: np.ndarray    # (n, 8) T_camera_target, unit
    robust: bool
    camera_covariance: np.ndarray | None    # (n, 6, 6)
    robot_covariance: np.ndarray | None     # (n, 6, 6)
    corners: list | None                    # per pair (target_points, image_points, K)
    refine_focal: bool
    pixel_sigma: float | None


#: the fields of a CalibrateRequest an error may start with
CALIBRATE_REQUEST = ("setup", "pairs", "robust", "camera_matrix", "refine_focal", "pixel_sigma")


def calibrate_error(e: ValueError) -> FieldError:
    """A :func:`dqpose.handeye.calibrate` error with the request's field names, wherever the
    message has the domain's (``"base_flange, camera_target: ..."``); Infeasible stays so; one
    from inside NumPy about none of them named ``pairs``."""
    renamed = rename_all(e, CALIBRATE_FIELDS)
    # the domain takes a camera matrix per view; the request has one
    renamed = type(renamed)(re.sub(r"pairs\[\d+\]\.corners\.K\b", "camera_matrix",
                                   str(renamed)))
    return field_named(renamed, CALIBRATE_REQUEST, "pairs")


def _corners(req) -> list | None:
    """Every pair's corners as the domain takes them, or None when no pair has any."""
    has = [p.HasField("corners") for p in req.pairs]
    if not any(has):
        return None
    if not all(has):
        i, given = has.index(False), has.index(True)
        raise FieldError(f"pairs[{i}].corners: required, as pairs[{given}] has corners (on "
                         f"every pair or on none)")
    if len(req.camera_matrix) != 9:
        raise FieldError(f"camera_matrix: {len(req.camera_matrix)} values; 9 (row-major) are "
                         f"needed with corners")
    K = np.array(req.camera_matrix, dtype=np.float64).reshape(3, 3)
    out = []
    for i, p in enumerate(req.pairs):
        c = p.corners
        if len(c.target_points) % 3 or len(c.image_points) % 2:
            bad = "target_points" if len(c.target_points) % 3 else "image_points"
            raise FieldError(f"pairs[{i}].corners.{bad}: {len(getattr(c, bad))} values, not "
                             f"{'3' if bad == 'target_points' else '2'} per corner")
        out.append((np.array(c.target_points, dtype=np.float64).reshape(-1, 3),
                    np.array(c.image_points, dtype=np.float64).reshape(-1, 2), K))
    return out


def _pair_covariances(pairs, name: str) -> np.ndarray | None:
    """The ``name`` covariances of every pair, ``(n, 6, 6)``, or None when no pair has one."""
    counts = [len(getattr(p, name)) for p in pairs]
    if not any(counts):
        return None
    for i, k in enumerate(counts):
        if k != COVARIANCE_SIZE:
            given = next(j for j, c in enumerate(counts) if c)
            raise FieldError(f"pairs[{i}].{name}: {k} values; expected {COVARIANCE_SIZE} "
                             f"(6x6, row-major) on every pair, as pairs[{given}] has, or on none")
    return np.array([getattr(p, name) for p in pairs], dtype=np.float64).reshape(-1, 6, 6)


def calibrate_from_msg(req) -> CalibrateArgs:
    """A ``CalibrateRequest`` to :class:`CalibrateArgs`; errors name the field."""
    setup = SETUP_NAMES.get(req.setup)
    if setup is None:
        if req.setup == hpb.SETUP_UNSPECIFIED:
            raise FieldError("setup: required: SETUP_EYE_IN_HAND (the camera on the flange) or "
                             "SETUP_EYE_TO_HAND (the camera fixed, the target on the flange)")
        raise FieldError(f"setup: unknown Setup value {req.setup}")
    poses = {}
    for name in ("base_to_flange", "camera_to_target"):
        for i, p in enumerate(req.pairs):
            if not p.HasField(name):
                raise FieldError(f"pairs[{i}].{name}: required")
        poses[name] = flat_to_dqs(poses_to_flat([getattr(p, name) for p in req.pairs]), "pairs",
                                  f".{name}")
    robust = req.robust if req.HasField("robust") else True
    corners = _corners(req)
    if corners is None and (req.refine_focal or req.pixel_sigma or req.camera_matrix):
        field = "refine_focal" if req.refine_focal else \
            "pixel_sigma" if req.pixel_sigma else "camera_matrix"
        raise FieldError(f"{field}: only with corners (PosePair.corners)")
    if req.pixel_sigma < 0 or not math.isfinite(req.pixel_sigma):
        raise FieldError(f"pixel_sigma: must be a positive number of pixels (0: estimated), got "
                         f"{req.pixel_sigma!r}")
    return CalibrateArgs(setup, poses["base_to_flange"], poses["camera_to_target"], robust,
                         _pair_covariances(req.pairs, "camera_covariance"),
                         _pair_covariances(req.pairs, "robot_covariance"), corners,
                         req.refine_focal, req.pixel_sigma or None)


def _per_pair(cov, name: str, n: int) -> list | None:
    """Client side: a ``(6, 6)`` or ``(n, 6, 6)`` covariance as n rows of 36 values."""
    if cov is None:
        return None
    c = np.asarray(cov, dtype=np.float64)
    if c.shape == (6, 6):
        c = np.broadcast_to(c, (n, 6, 6))
    if c.shape != (n, 6, 6):
        raise ValueError(f"{name}: expected shape (6, 6) or ({n}, 6, 6), got {c.shape}")
    return c.reshape(n, COVARIANCE_SIZE).tolist()


def calibrate_msg(base_flange, camera_target, setup: str = "eye_in_hand", robust: bool = True,
                  camera_covariance=None, robot_covariance=None, corners=None,
                  refine_focal: bool = False,
                  pixel_sigma: float | None = None) -> "hpb.CalibrateRequest":
    """Client side: the ``CalibrateRequest`` of :func:`dqpose.handeye.calibrate`'s arguments,
    poses as given (the server names what is wrong with them)."""
    if setup not in SETUP_ENUMS:
        raise ValueError(f"setup: unknown {setup!r}; expected one of {', '.join(SETUP_ENUMS)}")
    a = np.asarray(base_flange, dtype=np.float64)
    b = np.asarray(camera_target, dtype=np.float64)
    for name, v in (("base_flange", a), ("camera_target", b)):
        if v.ndim != 2 or v.shape[1] != 8:
            raise ValueError(f"{name}: expected shape (n, 8), got {v.shape}")
    if len(a) != len(b):
        raise ValueError(f"camera_target: {len(b)} poses for {len(a)} base_flange poses")
    pairs = [hpb.PosePair(base_to_flange=f, camera_to_target=c)
             for f, c in zip(pose_msgs(*pose_arrays(a)), pose_msgs(*pose_arrays(b)))]
    for name, cov in (("camera_covariance", camera_covariance),
                      ("robot_covariance", robot_covariance)):
        rows = _per_pair(cov, name, len(pairs))
        for p, row in zip(pairs, rows or ()):
            getattr(p, name).extend(row)
    request = hpb.CalibrateRequest(setup=SETUP_ENUMS[setup], pairs=pairs, robust=bool(robust),
                                   refine_focal=bool(refine_focal),
                                   pixel_sigma=float(pixel_sigma or 0.0))
    if corners is not None:
        _corners_msgs(request, corners)
    return request


def _corners_msgs(request, corners) -> None:
    """Client side: :func:`dqpose.handeye.calibrate`'s ``corners`` (one ``(board_points,
    image_points, K)`` per pair, one K for all) into the request."""
    corners = list(corners)
    if len(corners) != len(request.pairs):
        raise ValueError(f"corners: {len(corners)} views for {len(request.pairs)} pairs")
    Ks = [np.asarray(k, dtype=np.float64) for _, _, k in corners]
    if any(k.shape != (3, 3) or not np.array_equal(k, Ks[0]) for k in Ks):
        raise ValueError("corners: one camera matrix K (3, 3) for every view (the service "
                         "takes one camera)")
    request.camera_matrix.extend(Ks[0].ravel().tolist())
    for p, (b, u, _) in zip(request.pairs, corners):
        p.corners.target_points.extend(np.asarray(b, dtype=np.float64).ravel().tolist())
        p.corners.image_points.extend(np.asarray(u, dtype=np.float64).ravel().tolist())


def calibration_to_msg(c) -> "hpb.CalibrateResponse":
    """A :class:`dqpose.handeye.Calibration` into a ``CalibrateResponse``."""
    msg = hpb.CalibrateResponse(
        covariance_x=np.asarray(c.covariance_x).ravel().tolist(),
        covariance_z=np.asarray(c.covariance_z).ravel().tolist(),
        residuals=np.asarray(c.residuals).ravel().tolist(), warnings=list(c.warnings),
        rejected=[hpb.RejectedPair(index=r.index, reason=r.reason) for r in c.rejected],
        agreement=[float(v) for v in c.agreement], rotation_condition=c.rotation_condition,
        excitation=c.excitation, iterations=c.iterations, noise_model=c.noise_model,
        readings=[hpb.Reading(reading=r, rotation=a, translation=d) for r, a, d in c.readings],
        focal_scale=c.focal_scale, focal_sigma=c.focal_sigma, pixel_sigma=c.pixel_sigma)
    for field, pose in (("x", c.x), ("z", c.z), ("closed_form_x", c.closed_form_x),
                        ("closed_form_z", c.closed_form_z)):
        if pose is not None:
            dq_to_pose(pose, getattr(msg, field))
    for field in ("leave_one_out", "nis", "covariance", "reprojection", "inliers"):
        value = getattr(c, field)
        if value is not None:
            getattr(msg, field).extend(np.asarray(value).ravel().tolist())
    return msg


def calibration_from_msg(msg, setup: str):
    """Client side: a ``CalibrateResponse`` back into the :class:`dqpose.handeye.Calibration`
    it was made from (without the noise model's matrices, which stay on the server)."""
    def pose(p):
        return dq.from_pose((p.orientation.w, p.orientation.x, p.orientation.y,
                             p.orientation.z), (p.position.x, p.position.y, p.position.z))

    def rows(values, width):
        return np.array(values, dtype=np.float64).reshape(-1, width)

    rejected = tuple(handeye.Rejection(r.index, r.reason) for r in msg.rejected)
    covariance = rows(msg.covariance, 12) if msg.covariance else None
    return handeye.Calibration(
        setup=setup, x=pose(msg.x), z=pose(msg.z),
        covariance_x=rows(msg.covariance_x, 6), covariance_z=rows(msg.covariance_z, 6),
        residuals=rows(msg.residuals, 2), warnings=tuple(msg.warnings),
        inliers=np.array(msg.inliers, dtype=bool),
        rejected=rejected, covariance=covariance,
        information=None if covariance is None else np.linalg.inv(covariance),
        noise_model=msg.noise_model, nis=np.array(msg.nis, dtype=np.float64),
        leave_one_out=rows(msg.leave_one_out, 2),
        closed_form_x=pose(msg.closed_form_x) if msg.HasField("closed_form_x") else None,
        closed_form_z=pose(msg.closed_form_z) if msg.HasField("closed_form_z") else None,
        agreement=tuple(msg.agreement), rotation_condition=msg.rotation_condition,
        excitation=msg.excitation, iterations=msg.iterations,
        readings=tuple((r.reading, r.rotation, r.translation) for r in msg.readings),
        reprojection=np.array(msg.reprojection, dtype=np.float64) if msg.reprojection else None,
        focal_scale=msg.focal_scale, focal_sigma=msg.focal_sigma, pixel_sigma=msg.pixel_sigma)
