"""The ``dqpose.v1.Trajectories`` service: Plan (:func:`dqpose.trajectory.plan`, streamed as
samples), Smooth (:func:`dqpose.smoothing.smooth`), and the arms' RPCs, Execute, GetArm,
WatchArm and ListArms (:mod:`dqpose.rpc.arms`).
"""
from __future__ import annotations

from typing import Any

import grpc
import numpy as np
from google.protobuf.message import DecodeError

from dqpose import limits, record, smoothing, trajectory
from dqpose.errors import FieldError, rename
from dqpose.rpc._proto.dqpose.v1 import trajectories_pb2 as pb
from dqpose.rpc.arms import Arms
from dqpose.rpc.calls import Calls, refused
from dqpose.rpc.checks import check_count, field_named
from dqpose.rpc.geometry import arrays_to_stamped, stamped_to_arrays
from dqpose.rpc.routing import world_of
from dqpose.rpc.trajectories_convert import (
    limits_from_msg,
    plan_from_msg,
    plan_info_msg,
    resolve_frames,
    sample_msgs,
    world_named,
)

#: the fields of a PlanRequest an error may start with
PLAN_FIELDS = ("waypoints", "limits", "rate_hz", "interpolation", "start_linear_velocity",
               "start_angular_velocity")
#: the largest Smooth.smoothing (a cutoff of 2 mHz): at 1e4 the spline's equations were singular
MAX_SMOOTHING = 1e3
#: samples converted and written per step of the Plan stream (bounds the memory of messages)
CHUNK = 500


def _planned(args, field: str = ""):
    """:func:`trajectory.plan` of :class:`PlanArgs`, its errors named by proto field (the
    domain's start velocity is both vectors: the one its text is about)."""
    try:
        return trajectory.plan(args.waypoints, args.limits, args.interpolation,
                               start_velocity=args.start_velocity)
    except ValueError as e:
        start = "start_angular_velocity" if "angular" in str(e) or "turn" in str(e) \
            else "start_linear_velocity"
        named = rename(e, {"waypoints": f"{field}waypoints{{}}", "limits": f"{field}limits",
                           "start_velocity": f"{field}{start}"})
        raise field_named(named, tuple(field + f for f in PLAN_FIELDS),
                          f"{field}waypoints") from None


class Trajectories:
    NAME = "dqpose.v1.Trajectories"

    def __init__(self, cfg, calls: Calls):
        self.calls = calls
        self.max_poses = cfg.max_poses
        self.limits = cfg.limits
        self.arms = Arms(cfg, calls)
        # name -> the server's dqpose.world.World of that name (server.start hands it over)
        self.world = None

    @property
    def world(self):
        return self.arms.world

    @world.setter
    def world(self, world) -> None:
        self.arms.world = world

    # -- domain, message in, message(s) out

    def plan(self, request: pb.PlanRequest, world: str = ""):
        """``(trajectory, rate, resolved)`` for a PlanRequest (``resolved``: the waypoints given
        in a body's frame of world ``world``, as ``ResolvedWaypoint`` s); FieldError /
        Infeasible naming the field."""
        check_count("waypoints", len(request.waypoints), self.max_poses)
        args, resolved = resolve_frames(plan_from_msg(request), request,
                                        world_named(self.world, world))
        traj = _planned(args)
        n = traj.duration * args.rate_hz + 2
        if not n <= self.limits.max_plan_samples:
            # the waypoint the longest segment ends at, and the limit that sets its pace
            k = max(range(len(traj.segments)), key=lambda i: traj.segments[i].duration)
            seg = traj.segments[k]
            pace = "its time" if seg.binding == "time" else f"limits.{seg.binding}"
            raise limits.over(f"waypoints[{k + 1}]", f"the plan lasts {traj.duration:.6g} s, "
                              f"{seg.duration:.6g} s of it to this waypoint (at {pace}); at "
                              f"rate_hz {args.rate_hz:.6g} that is {n:.6g} samples",
                              self.limits, "max_plan_samples")
        return traj, args.rate_hz, resolved

    def smooth(self, request: pb.SmoothRequest) -> pb.SmoothResponse:
        check_count("poses", len(request.poses), self.max_poses)
        if not request.HasField("limits"):
            raise FieldError("limits: required (velocity and acceleration limits)")
        bounds = limits_from_msg(request.limits)
        times, dqs = stamped_to_arrays(request.poses, "poses")
        span = times.max() - times.min() if len(times) else 0.0
        if request.rate_hz * span >= self.limits.max_plan_samples:
            raise limits.over("rate_hz", f"{request.rate_hz:.6g} Hz over the poses' {span:.6g} "
                                         f"s", self.limits, "max_plan_samples")
        strength = request.smoothing or 1.0
        if strength > MAX_SMOOTHING:
            raise FieldError(f"smoothing: {strength:.6g} is over {MAX_SMOOTHING:g} (the cutoff is "
                             f"2 / smoothing Hz; beyond it the spline's equations are singular)")
        try:
            t, out = smoothing.smooth(times, dqs, bounds, smoothing=strength,
                                       rate_hz=request.rate_hz, free_ends=request.free_ends)
        except np.linalg.LinAlgError as e:     # SciPy's too: the equations of this path
            raise FieldError(f"smoothing: {strength:.6g} leaves the spline's equations for these "
                             f"poses singular ({e}); use a smaller one") from None
        except ValueError as e:
            raise field_named(rename(e, {"times": "poses{}.time", "poses": "poses{}.pose",
                                         "limits": "limits"}),
                              ("poses", "limits", "smoothing", "rate_hz"), "poses") from None
        return pb.SmoothResponse(samples=arrays_to_stamped(t, out))

    def smooth_bytes(self, data: bytes) -> bytes:
        """What Smooth serves: ``SmoothResponse`` bytes for request bytes."""
        return self.smooth(_parsed(pb.SmoothRequest, data)).SerializeToString()

    def planned(self, data: bytes, world: str = ""):
        """What Plan serves, for request bytes (of a call naming ``world``): ``(trajectory, its
        samples at the rate, the resolved waypoints)``."""
        traj, rate, resolved = self.plan(_parsed(pb.PlanRequest, data), world)
        samples = traj.at_rate(rate)
        # for viewing (dqpose.record): at most PLAN_VIEW_POSES of the path, evenly
        step = max(1, -(-len(samples.pose) // record.PLAN_VIEW_POSES))
        self.calls.recorder.plan("Plan", np.concatenate([samples.pose[::step],
                                                          samples.pose[-1:]]))
        return traj, samples, resolved

    @staticmethod
    def sample_chunk(traj, samples, i: int, resolved=()) -> list[bytes]:
        """Samples ``i`` to ``i + CHUNK`` as ``TrajectorySample`` bytes (the plan's segments and
        resolved waypoints on the first)."""
        msgs = sample_msgs(trajectory.Samples(*(a[i:i + CHUNK] for a in samples)))
        if i == 0:
            msgs[0].plan.CopyFrom(plan_info_msg(traj, resolved))
        return [m.SerializeToString() for m in msgs]

    # -- RPCs

    def register(self, server) -> None:
        """Plan and Smooth take (and Smooth returns) bytes, parsed and written in the worker
        pool; Execute, GetArm and ListArms are :attr:`arms`' with the proto's own
        (de)serializers. Every RPC of the proto is in ``handlers`` (tests/rpc check it)."""
        raw = dict(request_deserializer=None, response_serializer=None)
        handlers: dict[str, grpc.RpcMethodHandler[Any, Any]] = {
            "Plan": grpc.unary_stream_rpc_method_handler(self.Plan, **raw),
            "Smooth": grpc.unary_unary_rpc_method_handler(self.Smooth, **raw),
            "Execute": grpc.unary_stream_rpc_method_handler(
                self.Execute, request_deserializer=pb.ExecuteRequest.FromString,
                response_serializer=pb.ExecutionFeedback.SerializeToString),
            "GetArm": grpc.unary_unary_rpc_method_handler(
                self.GetArm, request_deserializer=pb.GetArmRequest.FromString,
                response_serializer=pb.ArmState.SerializeToString),
            "WatchArm": grpc.unary_stream_rpc_method_handler(
                self.WatchArm, request_deserializer=pb.GetArmRequest.FromString,
                response_serializer=pb.ArmState.SerializeToString),
            "ListArms": grpc.unary_unary_rpc_method_handler(
                self.ListArms, request_deserializer=pb.ListArmsRequest.FromString,
                response_serializer=pb.ListArmsResponse.SerializeToString),
        }
        generic = grpc.method_handlers_generic_handler(self.NAME, handlers)
        server.add_generic_rpc_handlers((generic,))
        server.add_registered_method_handlers(self.NAME, handlers)

    async def Smooth(self, request: bytes, context):
        # tens of milliseconds to seconds of solver: off the event loop (the worker pool), so
        # other calls, health and signals are answered meanwhile
        return await self.calls.unary("Smooth", lambda r: self.calls.work(self.smooth_bytes, r),
                                      request, context)

    async def Plan(self, request: bytes, context):
        async with self.calls.stream("Plan", context) as call:
            if call.open() is None:
                return
            try:
                traj, samples, resolved = await self.calls.work(self.planned, request,
                                                                world_of(context))
            except Exception as e:
                await call.refuse(*refused("Plan", e))
            # the samples' messages made in the worker pool too, CHUNK at a time
            for i in range(0, len(samples.time), CHUNK):
                msgs = await self.calls.work(self.sample_chunk, traj, samples, i, resolved)
                for m in msgs:
                    await context.write(m)
                call.messages += len(msgs)

    async def Execute(self, request, context):
        await self.arms.execute(request, context)

    async def GetArm(self, request, context):
        return await self.calls.unary("GetArm", self.arms.get_arm, request, context)

    async def WatchArm(self, request, context):
        await self.arms.watch_arm(request, context)

    async def ListArms(self, request, context):
        return await self.calls.unary("ListArms", self.arms.list_arms, request, context)

    def stopping(self, seconds: float) -> None:
        """The server's shutdown hook (:meth:`Arms.stopping`)."""
        self.arms.stopping(seconds)


def _parsed(message, data: bytes):
    """``data`` parsed as a ``message``; a FieldError when they are not one."""
    try:
        return message.FromString(data)
    except DecodeError:
        raise FieldError(f"request: not a valid {message.DESCRIPTOR.full_name} message") from None
