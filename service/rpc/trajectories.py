"""The ``dqpose.v1.Trajectories`` service: Plan (:func:`service.trajectory.plan`, streamed as
samples), Smooth (:func:`service.smoothing.smooth`), and the arms' RPCs, Execute, GetArm and
ListArms (:mod:`service.rpc.arms`).
"""
from __future__ import annotations

import asyncio
import math

from service import smoothing, trajectory
from service.errors import FieldError, rename
from service.rpc.arms import Arms
from service.rpc.calls import Calls, refused
from service.rpc.convert import (arrays_to_stamped, limits_from_msg, plan_from_msg,
                                 plan_info_msg, sample_msgs, stamped_to_arrays)
from service.rpc._proto.dqpose.v1 import trajectories_pb2 as pb
from service.rpc._proto.dqpose.v1 import trajectories_pb2_grpc as pb_grpc

#: how many samples a plan may stream, as a multiple of the server's max poses per request
SAMPLES_PER_MAX_POSES = 10
#: samples converted and written per step of the Plan stream (bounds the memory of messages)
CHUNK = 500


def _planned(args, field: str = ""):
    """:func:`trajectory.plan` of :class:`PlanArgs`, its errors named by proto field."""
    try:
        return trajectory.plan(args.waypoints, args.limits, args.interpolation,
                               start_velocity=args.start_velocity)
    except ValueError as e:
        raise rename(e, {"waypoints": f"{field}waypoints{{}}", "limits": f"{field}limits",
                         "start_velocity": f"{field}start_linear_velocity"}) from None


class Trajectories:
    NAME = "dqpose.v1.Trajectories"

    def __init__(self, cfg, calls: Calls):
        self.calls = calls
        self.max_poses = cfg.max_poses
        self.arms = Arms(cfg, calls)

    # -- domain, message in, message(s) out

    def plan(self, request: pb.PlanRequest):
        """``(trajectory, rate)`` for a PlanRequest; FieldError / Infeasible naming the field."""
        self._check_count("waypoints", len(request.waypoints))
        args = plan_from_msg(request)
        traj = _planned(args)
        n = math.floor(traj.duration * args.rate_hz) + 2
        if n > SAMPLES_PER_MAX_POSES * self.max_poses:
            raise FieldError(f"rate_hz: {args.rate_hz:g} Hz over {traj.duration:.3f} s is {n} "
                             f"samples, over the server's limit of "
                             f"{SAMPLES_PER_MAX_POSES * self.max_poses}")
        return traj, args.rate_hz

    def smooth(self, request: pb.SmoothRequest) -> pb.SmoothResponse:
        self._check_count("poses", len(request.poses))
        if not request.HasField("limits"):
            raise FieldError("limits: required (velocity and acceleration limits)")
        limits = limits_from_msg(request.limits)
        times, dqs = stamped_to_arrays(request.poses, "poses")
        limit = SAMPLES_PER_MAX_POSES * self.max_poses
        if len(times) and request.rate_hz * (times.max() - times.min()) >= limit:
            raise FieldError(f"rate_hz: {request.rate_hz:g} Hz over the poses' "
                             f"{times.max() - times.min():.3f} s is over the server's limit of "
                             f"{limit} samples")
        try:
            t, out = smoothing.smooth(times, dqs, limits, smoothing=request.smoothing or 1.0,
                                       rate_hz=request.rate_hz, free_ends=request.free_ends)
        except ValueError as e:
            raise rename(e, {"times": "poses{}.time", "poses": "poses{}.pose",
                             "limits": "limits"}) from None
        return pb.SmoothResponse(samples=arrays_to_stamped(t, out))

    def _check_count(self, field: str, n: int) -> None:
        if n > self.max_poses:
            raise FieldError(f"{field}: {n} exceed the server limit of {self.max_poses} per "
                             f"request")

    # -- RPCs

    def register(self, server) -> None:
        """The generated registration: every RPC of the proto, with its own (de)serializers;
        Execute, GetArm and ListArms are :attr:`arms`' (any other registration must keep all
        three)."""
        pb_grpc.add_TrajectoriesServicer_to_server(self, server)

    async def Smooth(self, request, context):
        # tens of milliseconds of solver holding the GIL: off the event loop, so other calls'
        # messages keep moving between its steps
        return await self.calls.unary("Smooth", lambda r: asyncio.to_thread(self.smooth, r),
                                      request, context)

    async def Plan(self, request, context):
        t0 = self.calls.begin()
        code, sent = "OK", 0
        try:
            try:
                traj, rate = self.plan(request)
            except Exception as e:
                status, details = refused("Plan", e)
                code = status.name
                await context.abort(status, details)
            samples = traj.at_rate(rate)
            for i in range(0, len(samples.time), CHUNK):
                msgs = sample_msgs(trajectory.Samples(*(a[i:i + CHUNK] for a in samples)))
                if i == 0:
                    msgs[0].plan.CopyFrom(plan_info_msg(traj))
                for m in msgs:
                    await context.write(m)
                sent += len(msgs)
        except asyncio.CancelledError:
            code = "CANCELLED"
            raise
        finally:
            self.calls.done("Plan", code, t0, context, messages=sent)

    async def Execute(self, request, context):
        await self.arms.execute(request, context)

    async def GetArm(self, request, context):
        return await self.calls.unary("GetArm", self.arms.get_arm, request, context)

    async def ListArms(self, request, context):
        return await self.calls.unary("ListArms", self.arms.list_arms, request, context)

    def stopping(self, seconds: float) -> None:
        """The server's shutdown hook (:meth:`Arms.stopping`)."""
        self.arms.stopping(seconds)
