"""The ``dqpose.v1.Trajectories`` service: Plan (:func:`service.trajectory.plan`, streamed as
samples), Smooth (:func:`service.smoothing.smooth`) and Execute (a plan run on an arm the server
was started with, fed by the executor at the arm's own period, never paced by the network).

The arms come from whoever starts the server (``ServerConfig.arms`` and ``.executor``; the
``dqpose serve --arm`` command opens them): this package imports no driver.
"""
from __future__ import annotations

import asyncio
import math
from typing import NamedTuple

import grpc
import numpy as np
from google.protobuf.message import DecodeError

from service import limits, smoothing, trajectory
from service.errors import FieldError, Infeasible, rename
from service.rpc.calls import Calls, refused
from service.rpc.convert import (arrays_to_stamped, dq_to_pose, field_named, limits_from_msg,
                                 plan_from_msg, plan_info_msg, sample_msgs, stamped_to_arrays)
from service.rpc._proto.dqpose.v1 import trajectories_pb2 as pb

#: the fields of a PlanRequest an error may start with
PLAN_FIELDS = ("waypoints", "limits", "rate_hz", "interpolation", "start_linear_velocity",
               "start_angular_velocity")
#: the largest Smooth.smoothing (a cutoff of 2 mHz): at 1e4 the spline's equations were singular
MAX_SMOOTHING = 1e3
#: samples converted and written per step of the Plan stream (bounds the memory of messages)
CHUNK = 500
#: an Execute feedback record every this many set-points (50 Hz at 500 Hz), and the last one
FEEDBACK_EVERY = 10


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
        self.arms = dict(cfg.arms)
        self.executor = cfg.executor
        self._busy: set[str] = set()

    # -- domain, message in, message(s) out

    def plan(self, request: pb.PlanRequest):
        """``(trajectory, rate)`` for a PlanRequest; FieldError / Infeasible naming the field."""
        self._check_count("waypoints", len(request.waypoints))
        args = plan_from_msg(request)
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
        return traj, args.rate_hz

    def smooth(self, request: pb.SmoothRequest) -> pb.SmoothResponse:
        self._check_count("poses", len(request.poses))
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
                                       rate_hz=request.rate_hz)
        except np.linalg.LinAlgError as e:     # SciPy's too: the equations of this path
            raise FieldError(f"smoothing: {strength:.6g} leaves the spline's equations for these "
                             f"poses singular ({e}); use a smaller one") from None
        except ValueError as e:
            raise field_named(rename(e, {"times": "poses{}.time", "poses": "poses{}.pose",
                                         "limits": "limits"}),
                              ("poses", "limits", "smoothing", "rate_hz"), "poses") from None
        return pb.SmoothResponse(samples=arrays_to_stamped(t, out))

    def _check_count(self, field: str, n: int) -> None:
        if n > self.max_poses:
            raise FieldError(f"{field}: {n} exceed the server limit of {self.max_poses} per "
                             f"request")

    def smooth_bytes(self, data: bytes) -> bytes:
        """What Smooth serves: ``SmoothResponse`` bytes for request bytes."""
        return self.smooth(_parsed(pb.SmoothRequest, data)).SerializeToString()

    def planned(self, data: bytes):
        """What Plan serves, for request bytes: ``(trajectory, its samples at the rate)``."""
        traj, rate = self.plan(_parsed(pb.PlanRequest, data))
        return traj, traj.at_rate(rate)

    @staticmethod
    def sample_chunk(traj, samples, i: int) -> list[bytes]:
        """Samples ``i`` to ``i + CHUNK`` as ``TrajectorySample`` bytes (the plan's segments on
        the first)."""
        msgs = sample_msgs(trajectory.Samples(*(a[i:i + CHUNK] for a in samples)))
        if i == 0:
            msgs[0].plan.CopyFrom(plan_info_msg(traj))
        return [m.SerializeToString() for m in msgs]

    # -- RPCs

    def register(self, server) -> None:
        """Plan and Smooth take (and Smooth returns) bytes, parsed and written in the worker
        pool; Execute has the proto's own (de)serializers."""
        raw = dict(request_deserializer=None, response_serializer=None)
        handlers = {
            "Plan": grpc.unary_stream_rpc_method_handler(self.Plan, **raw),
            "Smooth": grpc.unary_unary_rpc_method_handler(self.Smooth, **raw),
            "Execute": grpc.unary_stream_rpc_method_handler(
                self.Execute, request_deserializer=pb.ExecuteRequest.FromString,
                response_serializer=pb.ExecutionFeedback.SerializeToString),
        }
        server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(self.NAME, handlers),))
        server.add_registered_method_handlers(self.NAME, handlers)

    async def Smooth(self, request: bytes, context):
        # tens of milliseconds to seconds of solver: off the event loop (the worker pool), so
        # other calls, health and signals are answered meanwhile
        return await self.calls.unary("Smooth", lambda r: self.calls.work(self.smooth_bytes, r),
                                      request, context)

    async def Plan(self, request: bytes, context):
        t0 = self.calls.begin()
        code, sent = "OK", 0
        try:
            try:
                traj, samples = await self.calls.work(self.planned, request)
            except Exception as e:
                status, details = refused("Plan", e)
                code = status.name
                await context.abort(status, details)
            # the samples' messages made in the worker pool too, CHUNK at a time
            for i in range(0, len(samples.time), CHUNK):
                msgs = await self.calls.work(self.sample_chunk, traj, samples, i)
                for m in msgs:
                    await context.write(m)
                sent += len(msgs)
        except asyncio.CancelledError:
            code = "CANCELLED"
            raise
        finally:
            self.calls.done("Plan", code, t0, context, messages=sent)

    async def Execute(self, request, context):
        t0 = self.calls.begin()
        code, sent = "OK", 0
        run = None
        try:
            try:
                run = self._start_execution(request, asyncio.get_running_loop())
            except Exception as e:
                status, details = refused("Execute", e)
                code = status.name
                await context.abort(status, details)
            while True:
                fb = await run.queue.get()
                await context.write(_feedback_msg(fb))
                sent += 1
                if fb.result != 0:         # the last record: how the run ended
                    break
        except asyncio.CancelledError:
            code = "CANCELLED"
            raise
        finally:
            if run is not None:
                run.executor.cancel()    # a client that left stops the arm (no-op once done)
                self._busy.discard(request.arm)
            self.calls.done("Execute", code, t0, context, messages=sent)

    def _start_execution(self, request, loop) -> "_Run":
        name = request.arm
        if name not in self.arms:
            known = ", ".join(sorted(self.arms)) or "none: start the server with --arm NAME=SPEC"
            raise FieldError(f"arm: unknown arm {name!r} (this server's arms: {known})")
        if name in self._busy:
            raise _Precondition(f"arm: {name!r} is executing another plan")
        args = plan_from_msg(request.plan, "plan.", need_rate=False)
        traj = _planned(args, "plan.")
        arm = self.arms[name]
        samples = traj.at_rate(1.0 / arm.period)
        queue: asyncio.Queue = asyncio.Queue()
        # The executor's own thread paces the arm; its records come back through the loop.
        executor = self.executor(
            arm, interpolation=args.interpolation, feedback_every=FEEDBACK_EVERY,
            callback=lambda fb: loop.call_soon_threadsafe(queue.put_nowait, fb))
        try:
            executor.push(samples.time, samples.pose)
        except ValueError as e:        # the plan does not start where the arm is
            raise _Precondition(str(rename(e, {"poses": "plan.waypoints{}.pose"}))) from None
        executor.finish()
        self._busy.add(name)
        return _Run(executor, queue)


def _parsed(message, data: bytes):
    """``data`` parsed as a ``message``; a FieldError when they are not one."""
    try:
        return message.FromString(data)
    except DecodeError:
        raise FieldError(f"request: not a valid {message.DESCRIPTOR.full_name} message") from None


class _Run(NamedTuple):
    executor: object
    queue: asyncio.Queue


class _Precondition(FieldError, Infeasible):
    """The arm is in use, or not where the plan starts: FAILED_PRECONDITION."""


# drivers.executor.Result by name -> ExecutionState
_STATES = {"OK": pb.EXECUTION_WORKING, "FINISHED": pb.EXECUTION_FINISHED,
           "STOPPED": pb.EXECUTION_STOPPED, "STALLED": pb.EXECUTION_STALLED,
           "LIMITED": pb.EXECUTION_LIMITED, "PROTECTIVE_STOP": pb.EXECUTION_PROTECTIVE_STOP,
           "ERROR": pb.EXECUTION_ERROR}


def _feedback_msg(fb) -> pb.ExecutionFeedback:
    msg = pb.ExecutionFeedback(time=fb.time, state=_STATES[fb.result.name],
                               message=fb.message or "")
    if fb.commanded is not None:
        dq_to_pose(fb.commanded, msg.commanded)
    if fb.actual is not None:
        dq_to_pose(fb.actual, msg.actual)
    return msg
