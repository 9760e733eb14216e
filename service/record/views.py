"""What a recording shows in Foxglove (or Lichtblick, or anything that knows Foxglove's
well-known schemas): a fused pose as ``foxglove.PoseInFrame``, the body's frame on ``/tf``, its
position covariance as an ellipsoid (``foxglove.SceneUpdate``), its scalars for plotting, a plan
as ``foxglove.PosesInFrame``. Each is built from plain values (a body's name, its pose, its
covariance in our convention), so the same views serve a live server and a replayed file.

The ellipsoid: our covariance is of a right perturbation ``T Exp([w, v])``, whose translation is
``R v`` to first order, so ``cov[3:6, 3:6]`` is the position's covariance along the *body's* axes.
The ellipsoid is drawn in the body's frame (``frame_id`` = the body, placed by ``/tf``), centred
on its origin, its axes the eigenvectors of that block and its diameters ``2 n sigma``: no
conversion, hence none to get wrong.
"""
from __future__ import annotations

import numpy as np
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.SpherePrimitive_pb2 import SpherePrimitive
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.timestamp_pb2 import Timestamp

from dqpose import dq, lie

#: the frame every fused pose is in (and an arm's base frame, which plans stand it for)
WORLD = "world"
#: the ellipsoids' size: the position's n-sigma surface
ELLIPSOID_SIGMAS = 3.0


def stamp(ns: int) -> Timestamp:
    return Timestamp(seconds=ns // 1_000_000_000, nanos=ns % 1_000_000_000)


def time_ns(seconds: float) -> int:
    """A pose's own time (``FusedPose.time``, s) as the ns of its views' stamps: Unix time when
    the world's measurements are stamped in it (else near 1970; negative before it)."""
    return round(seconds * 1e9)


def _pose(t, q) -> Pose:
    """Foxglove's Pose from a translation and a scalar-first quaternion (Foxglove's is x, y, z,
    w by field name: no order to confuse)."""
    return Pose(position=Vector3(x=t[0], y=t[1], z=t[2]),
                orientation=Quaternion(w=q[0], x=q[1], y=q[2], z=q[3]))


def pose_in_frame(ns: int, t, q, frame: str = WORLD) -> PoseInFrame:
    return PoseInFrame(timestamp=stamp(ns), frame_id=frame, pose=_pose(t, q))


def poses_in_frame(ns: int, dqs, frame: str = WORLD) -> PosesInFrame:
    """A path (a plan's samples, an arm's actual poses): dual quaternions ``(n, 8)``."""
    q, t = dq.to_pose(np.asarray(dqs, dtype=np.float64).reshape(-1, 8))
    return PosesInFrame(timestamp=stamp(ns), frame_id=frame,
                        poses=[_pose(ti, qi) for ti, qi in zip(t.tolist(), q.tolist())])


def frame_transforms(ns: int, items) -> FrameTransforms:
    """``/tf``: ``items`` of ``(parent, child, t, q)``."""
    return FrameTransforms(transforms=[
        FrameTransform(timestamp=stamp(ns), parent_frame_id=parent, child_frame_id=child,
                       translation=Vector3(x=t[0], y=t[1], z=t[2]),
                       rotation=Quaternion(w=q[0], x=q[1], y=q[2], z=q[3]))
        for parent, child, t, q in items])


def static_transforms(config) -> FrameTransforms:
    """``/tf_static`` of a World's configuration in force (``dqpose.v1.WorldConfig``, Configure's
    answer): each static ``parent → child`` at its pose and each named source in its parent at
    its extrinsic (an unset pose is the identity; the world ``""`` is :data:`WORLD`), stamped 0:
    valid at every time, as tf2 takes a static transform."""
    def edge(parent: str, child: str, pose, given: bool):
        return (parent or WORLD, child, *(pose_of(pose) if given else IDENTITY))
    return frame_transforms(0, [edge(s.parent, s.child, s.pose, s.HasField("pose"))
                                for s in config.statics] +
                            [edge(s.parent, s.name, s.extrinsic, s.HasField("extrinsic"))
                             for s in config.sources if s.name])


def ellipsoid_axes(cov_position) -> tuple[np.ndarray, np.ndarray]:
    """``(sigmas, q)``: the standard deviations along the principal axes of a 3x3 position
    covariance and the rotation (scalar-first quaternion) whose columns are those axes."""
    w, V = np.linalg.eigh(np.asarray(cov_position, dtype=np.float64))
    if np.linalg.det(V) < 0:            # a reflection is not a rotation
        V[:, 2] = -V[:, 2]
    M = np.eye(4)
    M[:3, :3] = V
    q, _ = dq.to_pose(dq.from_matrix(M))
    return np.sqrt(np.clip(w, 0.0, None)), q


def ellipsoid(ns: int, body: str, cov, sigmas: float = ELLIPSOID_SIGMAS) -> SceneEntity:
    """The ``sigmas``-sigma ellipsoid of the position of ``body`` (our 6x6 ``cov``), in the
    body's frame (module docstring)."""
    s, q = ellipsoid_axes(np.asarray(cov, dtype=np.float64).reshape(6, 6)[3:, 3:])
    d = 2.0 * sigmas * s
    return SceneEntity(
        timestamp=stamp(ns), frame_id=body, id=body, frame_locked=True,
        spheres=[SpherePrimitive(pose=_pose((0.0, 0.0, 0.0), q),
                                 size=Vector3(x=d[0], y=d[1], z=d[2]),
                                 color=Color(r=0.2, g=0.6, b=1.0, a=0.35))])


def scene_update(entities) -> SceneUpdate:
    return SceneUpdate(entities=list(entities))


def scalars(fused) -> dict:
    """A fused pose's scalars for plotting (JSON): the fusion time, chi2 and its dof, the
    largest position and rotation standard deviations, each source's mean NIS, the estimated
    latencies. ``fused``: a ``dqpose.v1.FusedPose``."""
    cov = np.asarray(fused.covariance, dtype=np.float64)
    out = {"body": fused.body, "time": fused.time, "chi2": fused.chi2, "dof": fused.dof,
           "iterations": fused.iterations, "measurements": len(fused.measurements),
           "rejected": len(fused.rejected)}
    if cov.size == 36:
        cov = cov.reshape(6, 6)
        out["sigma_rotation"], out["sigma_position"] = map(float, lie.cov_sigmas(cov))
    for s in fused.sources:
        out[f"nis_{s.name or 'world'}"] = s.nis_mean
    for lat in fused.latencies:
        out[f"latency_{lat.source}"] = lat.value
    return out


def tool_frame(arm: str) -> str:
    """The frame of an arm's tool on ``/tf``."""
    return f"{arm}/tool"


#: ``(t, q)`` of the identity
IDENTITY = ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0))


def pose_of(msg) -> tuple[tuple, tuple]:
    """``(t, q)`` (q scalar first) of a ``dqpose.v1.Pose``."""
    p, o = msg.position, msg.orientation
    return (p.x, p.y, p.z), (o.w, o.x, o.y, o.z)


def _state_name(msg, code: int) -> str:
    """An ExecutionState's name without its prefix ("" for UNSPECIFIED)."""
    if code == 0:
        return ""
    enum = msg.DESCRIPTOR.fields_by_name["state"].enum_type
    return enum.values_by_number[code].name.removeprefix("EXECUTION_")


def feedback_scalars(fb) -> dict:
    """An ExecutionFeedback's scalars (JSON): its plan time, state and message, and how far the
    actual pose is from the commanded one (m, rad) when it has both."""
    out = {"time": fb.time, "state": _state_name(fb, fb.state), "message": fb.message}
    if fb.HasField("commanded") and fb.HasField("actual"):
        tc, qc = pose_of(fb.commanded)
        ta, qa = pose_of(fb.actual)
        out["error_position"] = float(np.linalg.norm(np.subtract(ta, tc)))
        dot = abs(float(np.dot(qa, qc)) / (np.linalg.norm(qa) * np.linalg.norm(qc)))
        out["error_rotation"] = 2.0 * float(np.arccos(min(dot, 1.0)))
    return out


def arm_scalars(st) -> dict:
    """An ArmState's scalars (JSON): its run's state, busy, faults, speeds and limits."""
    v, w = st.linear_velocity, st.angular_velocity
    out = {"arm": st.arm, "state": _state_name(st, st.state), "busy": st.busy,
           "faults": "; ".join(st.faults),
           "linear_speed": float(np.linalg.norm([v.x, v.y, v.z])),
           "angular_speed": float(np.linalg.norm([w.x, w.y, w.z]))}
    for f in st.limits.DESCRIPTOR.fields:
        out[f.name] = getattr(st.limits, f.name)
    return out


def json_type(value) -> str:
    """The JSON schema type of a note's value."""
    if isinstance(value, bool):
        return "boolean"
    if isinstance(value, int):
        return "integer"
    if isinstance(value, float):
        return "number"
    return "string"
