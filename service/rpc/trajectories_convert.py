"""The ``dqpose.v1.Trajectories`` messages <-> :mod:`dqpose.trajectory`: ``Limits``, a
``PlanRequest`` as :func:`dqpose.trajectory.plan`'s arguments (Plan's and, inside an
``ExecuteRequest``, Execute's), and the planned samples as ``TrajectorySample`` s and back (the
client's).
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from dqpose import dq, trajectory
from dqpose.errors import FieldError, Infeasible, rename
from dqpose.names import check_name
from dqpose.rpc._proto.dqpose.v1 import geometry_pb2 as geo
from dqpose.rpc._proto.dqpose.v1 import trajectories_pb2 as tpb
from dqpose.rpc.geometry import (
    INTERPOLATION_ENUMS,
    interpolation_named,
    pose_arrays,
    pose_msgs,
    poses_to_arrays,
    poses_to_dqs,
)

#: Plan's (and Execute's) mode for INTERPOLATION_UNSPECIFIED (trajectories.proto says so)
PLAN_INTERPOLATION = "tool_linear"


def limits_from_msg(msg, field: str = "limits"):
    """A ``Limits`` message to :class:`dqpose.trajectory.Limits`; errors name ``field``."""
    try:
        return trajectory.Limits(**{name: getattr(msg, name) for name in trajectory.LIMIT_FIELDS})
    except ValueError as e:
        raise rename(e, {"limits": field}) from None


def limits_msg(limits) -> tpb.Limits:
    """:class:`dqpose.trajectory.Limits` as a ``Limits`` message."""
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
    mode = interpolation_named(req.interpolation, PLAN_INTERPOLATION, f"{field}interpolation")
    rate = float(req.rate_hz)
    if need_rate and not (math.isfinite(rate) and 0 < rate <= 10_000):
        raise FieldError(f"{field}rate_hz: must be within (0, 10000] samples per second, "
                         f"got {rate:g}")
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


def plan_msg(waypoints, limits, rate_hz: float = 0.0, interpolation: str = PLAN_INTERPOLATION,
             start_velocity=None, frames=None):
    """Client side: the ``PlanRequest`` of :func:`dqpose.trajectory.plan`'s arguments
    (``waypoints``: :class:`~dqpose.trajectory.Waypoint` or ``(8,)`` poses; ``frames``: per
    waypoint a body of the server's world it is given in, "" the base)."""
    if frames is not None and (isinstance(frames, str) or len(frames) != len(waypoints)):
        raise ValueError(f"frames: expected one per waypoint ({len(waypoints)}), got "
                         f"{frames!r}")
    if interpolation not in trajectory.INTERPOLATIONS:
        raise ValueError(f"interpolation: unknown {interpolation!r}; expected one of "
                         f"{', '.join(trajectory.INTERPOLATIONS)}")
    wps = [w if isinstance(w, trajectory.Waypoint) else trajectory.Waypoint(pose=np.asarray(w))
           for w in waypoints]
    flat = np.array([w.pose for w in wps], dtype=np.float64).reshape(-1, 8)
    poses = pose_msgs(*pose_arrays(flat))
    req = tpb.PlanRequest(
        waypoints=[tpb.Waypoint(pose=p, time=w.time, blend_radius=w.blend_radius, frame=f)
                   for p, w, f in zip(poses, wps, frames or [""] * len(wps))],
        limits=limits_msg(limits), rate_hz=rate_hz,
        # protoc's .pyi types Enum.Value() as int, the field as the enum class
        interpolation=INTERPOLATION_ENUMS[interpolation])  # type: ignore[arg-type]
    if start_velocity is not None:
        s = np.asarray(start_velocity, dtype=np.float64).reshape(6).tolist()
        req.start_linear_velocity.CopyFrom(geo.Vector3(x=s[0], y=s[1], z=s[2]))
        req.start_angular_velocity.CopyFrom(geo.Vector3(x=s[3], y=s[4], z=s[5]))
    return req


def plan_info_msg(traj, resolved=()):
    """A :class:`dqpose.trajectory.Trajectory`'s duration and segments as ``PlanInfo`` (with
    the waypoints :func:`resolve_frames` resolved)."""
    return tpb.PlanInfo(duration=traj.duration, segments=[
        tpb.Segment(start=s.start, duration=s.duration, binding=s.binding)
        for s in traj.segments], resolved=list(resolved))


def sample_msgs(samples) -> list:
    """:class:`dqpose.trajectory.Samples` to ``TrajectorySample`` messages."""
    q, t = pose_arrays(samples.pose)
    v = np.asarray(samples.linear_velocity).tolist()
    w = np.asarray(samples.angular_velocity).tolist()
    return [tpb.TrajectorySample(time=time, pose=pose, linear_velocity=geo.Vector3(x=a, y=b, z=c),
                                 angular_velocity=geo.Vector3(x=d, y=e, z=f))
            for time, pose, (a, b, c), (d, e, f)
            in zip(np.asarray(samples.time).tolist(), pose_msgs(q, t), v, w)]


def samples_from_msgs(msgs) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``TrajectorySample`` messages to ``(time (N,), pose (N, 8), linear_velocity (N, 3),
    angular_velocity (N, 3))`` (client side, unvalidated)."""
    msgs = list(msgs)
    q, t = poses_to_arrays([m.pose for m in msgs])
    vel = np.array([(m.linear_velocity.x, m.linear_velocity.y, m.linear_velocity.z,
                     m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z)
                    for m in msgs], dtype=np.float64).reshape(-1, 6)
    times = np.array([m.time for m in msgs], dtype=np.float64)
    return times, dq.from_pose(q, t) if len(msgs) else np.zeros((0, 8)), vel[:, :3], vel[:, 3:]


def world_named(worlds, name: str):
    """``() -> worlds(name)`` (the world a call's ``x-dqpose-world`` names), or None when the
    server has no worlds (``worlds`` None)."""
    return None if worlds is None else (lambda: worlds(name))


def resolve_frames(args: PlanArgs, req, world, field: str = "", arm: str | None = None):
    """``(args, resolved)``: ``args`` with every waypoint given in a body's frame
    (``Waypoint.frame``) resolved through ``world()`` (:func:`dqpose.world_waypoints.resolve`),
    and one ``ResolvedWaypoint`` each for ``PlanInfo.resolved``. The base is ``arm``'s in the
    world when the world's arms name it, else the world frame."""
    framed = [i for i, w in enumerate(req.waypoints) if w.frame]
    if not framed:
        return args, []
    from dqpose.world_waypoints import resolve  # the domain World only when frames are used
    if world is None:
        raise FieldError(f"{field}waypoints[{framed[0]}].frame: this server has no world")
    try:
        world = world()
    except LookupError as e:      # a world the server does not hold
        raise Infeasible(f"{field}waypoints[{framed[0]}].frame: {e}") from None
    base = world.arm_base(arm).pose if arm is not None and arm in world.arms else None
    waypoints = list(args.waypoints)
    resolved = []
    for i in framed:
        w = req.waypoints[i]
        check_name(w.frame, f"{field}waypoints[{i}].frame")
        r = resolve(world, w.frame, waypoints[i].pose, f"{field}waypoints[{i}].frame", base)
        waypoints[i] = trajectory.Waypoint(pose=r.pose, time=waypoints[i].time,
                                           blend_radius=waypoints[i].blend_radius)
        q, t = pose_arrays(r.pose[None])
        msg = tpb.ResolvedWaypoint(index=i, frame=w.frame, time=r.time,
                                   pose=pose_msgs(q, t)[0])
        msg.covariance.extend(np.asarray(r.covariance).ravel().tolist())
        resolved.append(msg)
    return args._replace(waypoints=waypoints), resolved
