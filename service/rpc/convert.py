"""Protobuf messages <-> NumPy arrays for the gRPC layer, with errors named after proto fields.

The core names its arguments (``q[3]: zero quaternion``); only this layer knows that ``q[3]`` came
from ``poses[3].orientation``, so conversion validates per field and renames.
"""
from __future__ import annotations

import numpy as np

from service import _dqcore, dq
from service.errors import FieldError, rename
from service.rpc._proto.dqpose.v1 import blending_pb2 as pb
from service.rpc._proto.dqpose.v1 import geometry_pb2 as geo

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


def poses_wire(q: np.ndarray, t: np.ndarray, field: int = 1) -> bytes:
    """Rows of ``q (n, 4)`` and ``t (n, 3)`` as repeated ``Pose`` field ``field``, in wire bytes:
    what ``pose_msgs`` plus serialisation gives (values as given), ~20x faster."""
    q, t = np.asarray(q, dtype=np.float64), np.asarray(t, dtype=np.float64)
    r = np.empty(len(q), _POSE_RECORD)
    r["k"], r["n"] = field << 3 | 2, _POSE_RECORD.itemsize - 2
    r["pk"], r["pn"], r["ok"], r["on"] = 0x0A, 27, 0x12, 36
    r["p"]["k"], r["o"]["k"] = [0x09, 0x11, 0x19], [0x09, 0x11, 0x19, 0x21]
    r["p"]["v"], r["o"]["v"] = t, q
    return r.tobytes()


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
INTERPOLATION_NAMES = {pb.INTERPOLATION_UNSPECIFIED: "screw", pb.INTERPOLATION_SCREW: "screw",
                       pb.INTERPOLATION_TOOL_LINEAR: "tool_linear"}
INTERPOLATION_ENUMS = {"screw": pb.INTERPOLATION_SCREW, "tool_linear": pb.INTERPOLATION_TOOL_LINEAR}
