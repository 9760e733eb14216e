"""The shared messages of ``geometry.proto`` <-> NumPy: ``Pose`` (``(8,)`` dual quaternions, or
rows ``[qw, qx, qy, qz, x, y, z]``), ``StampedPose``, 6x6 covariances, and the ``Interpolation``
enum. Server side every pose is validated and its error named after its field
(``poses[3].orientation: zero quaternion``); client side poses go out as given, so that the
server's message, naming the field, applies.
"""
from __future__ import annotations

import numpy as np

from dqpose import dq, fusion, trajectory
from dqpose.errors import FieldError, rename
from dqpose.rpc._proto.dqpose.v1 import geometry_pb2 as geo

#: values of a 6x6 covariance field (row-major, rotation first)
COVARIANCE_SIZE = fusion.DOF * fusion.DOF


def poses_to_flat(poses) -> np.ndarray:
    """Repeated ``Pose`` to ``(n, 7)`` rows ``[qw, qx, qy, qz, x, y, z]``, unvalidated."""
    # One flat list through np.array is the cheapest path out of upb messages (no per-pose
    # array objects); the server's hot path avoids even this (wire.decode_blend_request).
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


def pose_from_row(row: np.ndarray, where: str) -> np.ndarray:
    """One ``[qw, qx, qy, qz, x, y, z]`` to ``(8,)``; errors read ``{where}.orientation: ...``."""
    try:
        return dq.from_pose(row[None, :4], row[None, 4:])[0]
    except ValueError as e:
        raise rename(e, {"q": f"{where}.orientation", "t": f"{where}.position"}) from None


def optional_pose(msg, name: str, where: str) -> np.ndarray | None:
    """``msg.name`` as ``(8,)``, None when it is not set; errors read ``{where}.{name}...``."""
    if not msg.HasField(name):
        return None
    o, t = getattr(msg, name).orientation, getattr(msg, name).position
    return pose_from_row(np.array([o.w, o.x, o.y, o.z, t.x, t.y, t.z], dtype=np.float64),
                         f"{where}.{name}")


def pose_to_dq(p) -> np.ndarray:
    """One ``Pose`` to ``(8,)`` (client side: what the server wrote)."""
    o, t = p.orientation, p.position
    return dq.from_pose((o.w, o.x, o.y, o.z), (t.x, t.y, t.z))


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


def dqs_to_poses(dqs: np.ndarray) -> list[geo.Pose]:
    """``(n, 8)`` to a list of ``Pose`` messages."""
    return pose_msgs(*dq.to_pose(np.asarray(dqs, dtype=np.float64).reshape(-1, 8)))


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


# ---- StampedPose ---------------------------------------------------------------------------------

def stamped_to_arrays(stamped, field: str = "keyframes") -> tuple[np.ndarray, np.ndarray]:
    """Repeated ``StampedPose`` to ``(times (n,), dqs (n, 8))``."""
    times = np.array([s.time for s in stamped], dtype=np.float64)
    return times, poses_to_dqs(stamped, field, ".pose")


def arrays_to_stamped(times: np.ndarray, dqs: np.ndarray) -> list[geo.StampedPose]:
    """``(n,)`` times and ``(n, 8)`` poses to ``StampedPose`` messages."""
    return [geo.StampedPose(time=s, pose=p)
            for s, p in zip(np.asarray(times).tolist(), dqs_to_poses(dqs))]


def stamped_msgs(times, dqs) -> list:
    """Client side: ``(n,)`` times and ``(n, 8)`` poses to ``StampedPose`` messages as given (the
    server names what is wrong with them)."""
    return [geo.StampedPose(time=s, pose=p)
            for s, p in zip(np.asarray(times, dtype=np.float64).tolist(),
                            pose_msgs(*pose_arrays(np.asarray(dqs, dtype=np.float64))))]


# ---- Interpolation -------------------------------------------------------------------------------

#: the domain's modes (:data:`dqpose.trajectory.INTERPOLATIONS`) as the proto's enum values; what
#: INTERPOLATION_UNSPECIFIED means is each RPC's own default, beside its servicer
INTERPOLATION_ENUMS = {name: geo.Interpolation.Value(f"INTERPOLATION_{name.upper()}")
                       for name in trajectory.INTERPOLATIONS}
INTERPOLATION_NAMES = {code: name for name, code in INTERPOLATION_ENUMS.items()}


def interpolation_named(code: int, unspecified: str, field: str = "interpolation") -> str:
    """The mode of an ``Interpolation`` value: ``unspecified`` for INTERPOLATION_UNSPECIFIED, a
    FieldError naming ``field`` for a value the proto does not have."""
    if code == geo.INTERPOLATION_UNSPECIFIED:
        return unspecified
    name = INTERPOLATION_NAMES.get(code)
    if name is None:
        raise FieldError(f"{field}: unknown Interpolation value {code}")
    return name
