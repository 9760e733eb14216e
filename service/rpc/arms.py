"""The arms of the ``dqpose.v1.Trajectories`` service: Execute (a plan run on an arm the server
was started with), GetArm, WatchArm and ListArms.

The arms and the executor come from whoever starts the server (``ServerConfig.arms`` and
``.executor``; ``dqpose serve --arm`` opens them): this module imports no driver, and does
nothing an arm's control loop does. It hands the loop a whole plan (``push_plan``: the loop
samples it at the arm's period, so nothing here grows with the plan's duration), beats the run's
heartbeat from the event loop (a server whose loop hangs stops its arms), and turns how a run
ended into the call's status.

A run holds its arm from the call's start until the control loop's last record, not until the
call ends: after a cancel the arm brakes, and a new Execute waits (up to :data:`FREE_WAIT`) for
it rather than starting a second run beside the first.
"""
from __future__ import annotations

import asyncio
import contextlib
import math
import re
import time
from typing import Optional

import grpc
import numpy as np

from dqpose import limits, record, trajectory
from dqpose.errors import FieldError, Infeasible, rename
from dqpose.names import check_name
from dqpose.record.topics import arm_topic
from dqpose.rpc._proto.dqpose.v1 import geometry_pb2 as geo
from dqpose.rpc._proto.dqpose.v1 import trajectories_pb2 as pb
from dqpose.rpc.calls import Calls, refused
from dqpose.rpc.geometry import dq_to_pose
from dqpose.rpc.peers import SUBSCRIPTION, FellBehind, Slot, exhausted
from dqpose.rpc.routing import world_of
from dqpose.rpc.trajectories_convert import plan_from_msg, resolve_frames, world_named

#: an Execute feedback record every this many set-points (50 Hz at 500 Hz), and the last one
FEEDBACK_EVERY = 10
#: records waiting for a slow client (20 s of them); WORKING ones beyond are dropped, so that a
#: client that stops reading costs nothing that grows with the plan's duration
MAX_PENDING = 1000
#: how long a new Execute waits for its arm: a run braking after a cancel, an arm settling
FREE_WAIT = 1.0
#: the arm's heartbeat is beaten this many times per period it asks for (margin for a busy loop)
BEATS_PER_PERIOD = 2
#: the fields of the proto's Limits an arm bounds, with their units: an arm's Limits
#: (drivers.base.Limits) has them by the same names; its jerk limits are 0 (it bounds none)
ARM_LIMITS = {"max_linear_velocity": "m/s", "max_angular_velocity": "rad/s",
              "max_linear_acceleration": "m/s^2", "max_angular_acceleration": "rad/s^2"}

_OK, _CANCELLED = grpc.StatusCode.OK, grpc.StatusCode.CANCELLED
_ABORTED, _UNAVAILABLE = grpc.StatusCode.ABORTED, grpc.StatusCode.UNAVAILABLE
# drivers.executor.Result by name -> (ExecutionState, the call's status when a run ends so)
RESULTS = {"OK": (pb.EXECUTION_WORKING, None),
           "FINISHED": (pb.EXECUTION_FINISHED, _OK),
           "STOPPED": (pb.EXECUTION_STOPPED, _CANCELLED),
           "STALLED": (pb.EXECUTION_STALLED, _ABORTED),
           "LIMITED": (pb.EXECUTION_LIMITED, _ABORTED),
           "PROTECTIVE_STOP": (pb.EXECUTION_PROTECTIVE_STOP, _ABORTED),
           "TRACKING": (pb.EXECUTION_TRACKING_ERROR, _ABORTED),
           "ERROR": (pb.EXECUTION_ERROR, _UNAVAILABLE)}
#: WatchArm: states a second when the request says 0, and at most (an arm is read at most this
#: often however many watch it: they share a reading)
WATCH_HZ, MAX_WATCH_HZ = 50.0, 100.0
#: WatchArm streams open at once on one server
MAX_WATCHERS = 64
#: why a run the server halted on shutdown ended (its call ends UNAVAILABLE, as calls refused then)
SHUTDOWN = "the server is shutting down"


class Precondition(FieldError, Infeasible):
    """The arm is busy, moving, faulted, not where the plan starts, or slower than the plan:
    FAILED_PRECONDITION."""


class _Run:
    """One Execute's run, from the call's start to the control loop's last record."""

    def __init__(self):
        self.executor = None          # set once made (in a worker thread)
        self.queue: asyncio.Queue = asyncio.Queue()
        self.duration = 0.0
        self.started: Optional[float] = None    # loop time the plan was handed over
        self.halted: Optional[str] = None       # why the server brought it to a stop
        self.abandoned = False        # the call ended before the run started
        self.ended = False


class _Arm:
    """An arm as the service keeps it: its run, and how the last one ended."""

    def __init__(self, name: str, arm):
        self.name, self.arm = name, arm
        self.run: Optional[_Run] = None
        self.state = pb.EXECUTION_STATE_UNSPECIFIED
        self.free = asyncio.Event()
        self.free.set()
        self.reading: Optional[asyncio.Future] = None    # the watchers' shared reading
        self.read_at = 0.0                               # loop time it began


class Arms:
    """Execute, GetArm and ListArms over the arms of a :class:`~dqpose.rpc.server.ServerConfig`;
    :meth:`stopping` is the server's shutdown hook."""

    NAME = "dqpose.v1.Trajectories"

    def __init__(self, cfg, calls: Calls):
        self.calls = calls
        self.limits = cfg.limits
        self.executor = cfg.executor
        self._arms = {name: _Arm(name, arm) for name, arm in sorted(cfg.arms.items())}
        self._stop_at: Optional[float] = None     # loop time the server stops, once known
        self._stopping: Optional[asyncio.Event] = None    # set once the server stops
        self.watchers = 0
        self.world = None      # name -> the server's dqpose.world.World, for Waypoint.frame

    def _slot(self, name: str) -> _Arm:
        slot = self._arms.get(name)
        if slot is None:
            check_name(name, "arm")      # the refusal quotes it
            known = ", ".join(self._arms) or "none: start the server with --arm NAME=SPEC"
            raise FieldError(f"arm: unknown arm {name!r} (this server's arms: {known})")
        return slot

    # ------------------------------------------------------------------ GetArm, ListArms

    async def get_arm(self, request) -> pb.ArmState:
        return await self._state(self._slot(request.arm))

    async def list_arms(self, request) -> pb.ListArmsResponse:
        states = await asyncio.gather(*(self._state(s) for s in self._arms.values()))
        return pb.ListArmsResponse(arms=states)

    async def _state(self, slot: _Arm) -> pb.ArmState:
        # a run holds its arm until its last record, which sets how it ended: until then WORKING
        running = slot.run is not None
        msg = pb.ArmState(arm=slot.name, state=pb.EXECUTION_WORKING if running else slot.state,
                          busy=running)
        for name in ARM_LIMITS:
            setattr(msg.limits, name, float(getattr(slot.arm.limits, name)))
        try:    # an arm in its own process answers through a pipe: not on the loop
            st = await asyncio.to_thread(slot.arm.state)
        except Exception as e:      # a dead arm is a fault to report, not a failed call
            msg.faults.append(f"cannot read the arm: {e}")
            return msg
        if st.pose is not None:             # None: unreadable, and the faults say why
            dq_to_pose(st.pose, msg.pose)
        if st.linear_velocity is not None:
            msg.linear_velocity.CopyFrom(geo.Vector3(**_xyz(st.linear_velocity)))
        if st.angular_velocity is not None:
            msg.angular_velocity.CopyFrom(geo.Vector3(**_xyz(st.angular_velocity)))
        msg.faults.extend(st.faults)
        return msg

    # ------------------------------------------------------------------ WatchArm

    async def watch_arm(self, request, context) -> None:
        rec = self.calls.recorder.call(f"{self.NAME}/WatchArm", pb.GetArmRequest, pb.ArmState)
        rec.request(request)
        loop = asyncio.get_running_loop()
        if self._stopping is None:
            self._stopping = asyncio.Event()
        async with self.calls.stream("WatchArm", context, rec) as call:
            try:
                slot = self._slot(request.arm)
                period = 1.0 / self._watch_rate(request.rate_hz)
                if self.watchers >= MAX_WATCHERS:
                    raise limits.OverLimit(f"WatchArm: {MAX_WATCHERS} watches are open, the "
                                           f"server's most")
            except Exception as e:
                await call.refuse(*refused("WatchArm", e))
            watch = call.open(SUBSCRIPTION)
            if watch is None:
                return
            self.watchers += 1
            call.on_end(lambda: self._unwatch(watch))
            due = loop.time()
            while not self._stopping.is_set():
                state = await self._shared_state(slot)
                try:
                    await self.calls.peers.write(context, state, "WatchArm")
                except FellBehind as e:
                    call.code, call.details = await exhausted(context, str(e), watch), str(e)
                    return
                rec.answer(state)
                call.messages += 1
                # paced on the loop's clock; a client slower than the rate gets fewer states
                due = max(due + period, loop.time())
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(self._stopping.wait(), due - loop.time())
            call.set(_UNAVAILABLE, SHUTDOWN)

    def _unwatch(self, watch: Slot) -> None:
        self.watchers -= 1
        watch.end()         # its server slot free at once, its client reading or not

    @staticmethod
    def _watch_rate(rate: float) -> float:
        if not (math.isfinite(rate) and rate >= 0.0):
            raise FieldError(f"rate_hz: must be finite and >= 0 (0: {WATCH_HZ:g} Hz), got "
                             f"{rate!r}")
        if rate > MAX_WATCH_HZ:
            raise limits.OverLimit(f"rate_hz: {rate:.6g} Hz is above WatchArm's most, "
                                   f"{MAX_WATCH_HZ:g} Hz")
        return rate or WATCH_HZ

    async def _shared_state(self, slot: _Arm) -> pb.ArmState:
        """The arm's state, read at most :data:`MAX_WATCH_HZ` times a second for all its
        watchers together (one watcher leaving never cancels the others' reading)."""
        loop = asyncio.get_running_loop()
        r = slot.reading
        if r is None or (r.done() and loop.time() - slot.read_at >= 1.0 / MAX_WATCH_HZ):
            slot.read_at = loop.time()
            r = slot.reading = asyncio.ensure_future(self._state(slot))
        return await asyncio.shield(r)

    # ------------------------------------------------------------------ Execute

    async def execute(self, request, context) -> None:
        # the execution feedback recorded (dqpose.record): commanded and actual, the state
        rec = self.calls.recorder.call(f"{self.NAME}/Execute", pb.ExecuteRequest,
                                       pb.ExecutionFeedback)
        rec.request(request)
        async with self.calls.stream("Execute", context, rec) as call:
            if call.open() is None:
                return
            try:
                slot, args = await self._check(request, world_of(context))
                deadline = time.monotonic() + FREE_WAIT     # for the arm: free, at rest
                run = await self._claim(slot, deadline)
                call.on_end(lambda: _abandon(run))
                beat = asyncio.create_task(self._beat(run))
                call.on_end(beat.cancel)
                await self._start(slot, run, args, request, deadline)
            except Exception as e:
                await call.refuse(*refused("Execute", e))
            while True:
                fb = await run.queue.get()
                msg = _feedback_msg(fb)
                await context.write(msg)
                rec.answer(msg)
                call.messages += 1
                if fb.result != 0:         # the last record: how the run ended
                    break
            state, status = _result(fb)
            if run.halted is not None and state == pb.EXECUTION_STOPPED:
                status = _UNAVAILABLE
            if status is not _OK:
                call.set(status, f"{fb.result.name}: {fb.message}")

    async def _check(self, request, world: str = ""):
        """The request's own checks, before the arm is waited for: the arm, the waypoint count
        (before anything is made of them), the plan's fields and its limits against the arm's."""
        slot = self._slot(request.arm)
        n = len(request.plan.waypoints)
        if n > self.limits.max_execute_waypoints:
            raise limits.over("plan.waypoints", f"{n} waypoints", self.limits,
                              "max_execute_waypoints")
        # converting up to max_execute_waypoints messages is work that grows with the request
        args = await asyncio.to_thread(self._plan_args, request.plan, request.arm, world)
        for name, unit in ARM_LIMITS.items():
            want, bound = getattr(args.limits, name), float(getattr(slot.arm.limits, name))
            if want > bound:
                raise Precondition(
                    f"plan.limits.{name}: {want:.6g} {unit} is above the limits.{name} of "
                    f"arm {slot.name!r}, {bound:.6g} {unit}; plan within the arm's limits "
                    f"(GetArm lists them)")
        return slot, args

    def _plan_args(self, plan, arm: str, world: str = ""):
        """The plan's arguments with its waypoints in bodies' frames resolved through the
        server's world ``world`` (one hop to a thread for both: a second one made a cancel's
        next Execute lose its race against the run's end)."""
        return resolve_frames(plan_from_msg(plan, "plan.", False), plan,
                              world_named(self.world, world), "plan.", arm)[0]

    async def _claim(self, slot: _Arm, deadline: float) -> _Run:
        """The arm for a new run, once its last run has ended; FAILED_PRECONDITION if that takes
        past ``deadline`` (monotonic)."""
        while slot.run is not None:
            try:
                await asyncio.wait_for(slot.free.wait(), max(deadline - time.monotonic(), 0))
            except asyncio.TimeoutError:
                raise Precondition(f"arm: {slot.name!r} is still running another plan after "
                                   f"{FREE_WAIT:g} s") from None
        run = slot.run = _Run()
        slot.free.clear()
        return run

    async def _start(self, slot: _Arm, run: _Run, args, request, deadline: float) -> None:
        """The plan handed to a new executor on the arm (in a worker thread: it plans, and an
        arm in its own process answers through a pipe); the arm released if that fails. A call
        cancelled meanwhile cancels the run it started."""
        loop = asyncio.get_running_loop()

        def record(fb):
            try:
                loop.call_soon_threadsafe(self._record, slot, run, fb)
            except RuntimeError:    # the loop has closed: the server, and the call, are gone
                pass

        work = asyncio.ensure_future(asyncio.to_thread(
            self._hand_over, slot, run, args, request.from_current, record, deadline))
        try:
            await asyncio.shield(work)
        except asyncio.CancelledError:
            work.add_done_callback(lambda w: self._abandoned(slot, run, w))
            raise
        except BaseException:
            self._release(slot, run)
            raise
        run.started = loop.time()
        self._halt_if_late(run)

    def _abandoned(self, slot: _Arm, run: _Run, work) -> None:
        if work.exception() is not None:
            self._release(slot, run)
        elif not run.ended:
            run.executor.cancel()

    def _hand_over(self, slot: _Arm, run: _Run, args, from_current: bool, record,
                   deadline: float) -> None:
        arm = slot.arm
        waypoints = args.waypoints
        if from_current:
            waypoints = [trajectory.Waypoint(_at_rest(slot, deadline))] + list(waypoints)
        try:
            traj = trajectory.plan(waypoints, args.limits, args.interpolation,
                                   start_velocity=args.start_velocity)
        except ValueError as e:
            raise _plan_error(e, from_current) from None
        run.duration = traj.duration
        if self.calls.recorder.recording:
            self._record_plan(slot, traj, args.limits)
        # The arm is ours once its last run's final record came (_claim); its control loop may
        # take a moment more to end, which the executor waits for, within the same second.
        ex = run.executor = self.executor(
            arm, interpolation=args.interpolation, feedback_every=FEEDBACK_EVERY,
            callback=record, heartbeat=arm.heartbeat,
            busy_timeout=max(deadline - time.monotonic(), 0.0))
        try:
            ex.push_plan(traj)
        except ValueError as e:        # the plan does not start where the arm is
            ex.close()
            raise Precondition(str(rename(e, {"poses": "plan.waypoints{}.pose"}))) from None
        except RuntimeError as e:      # drivers.base.ArmError: busy, faulted
            ex.close()
            raise Precondition(f"arm: {slot.name!r} cannot run a plan now: {e}") from None
        if run.abandoned:
            ex.cancel()

    def _record_plan(self, slot: _Arm, traj, planned) -> None:
        """What a recording shows beside the run's feedback: the plan's path (``/plans/<arm>``,
        :data:`record.PLAN_VIEW_POSES` poses at most, the last on the plan's end) and the
        limits, the arm's own and the plan's (``/arms/<arm>/limits``)."""
        n = max(2, min(record.PLAN_VIEW_POSES, int(traj.duration * 100) + 2))
        self.calls.recorder.plan(slot.name, traj.sample(np.linspace(0.0, traj.duration, n)).pose)
        data: dict = {"arm": slot.name}
        for name in ARM_LIMITS:
            data[name] = float(getattr(slot.arm.limits, name))
        for name in trajectory.LIMIT_FIELDS:
            data[f"plan_{name}"] = float(getattr(planned, name))
        self.calls.recorder.note(arm_topic(slot.name, "limits"), "dqpose.record.ArmLimits", data)

    def _record(self, slot: _Arm, run: _Run, fb) -> None:
        """A record of the run's control loop, on the event loop; the last frees the arm."""
        if fb.result == 0 and run.queue.qsize() >= MAX_PENDING:
            return
        run.queue.put_nowait(fb)
        if fb.result != 0:
            slot.state = _result(fb)[0]
            self._release(slot, run)

    def _release(self, slot: _Arm, run: _Run) -> None:
        run.ended = True
        if slot.run is run:
            slot.run = None
            slot.free.set()

    async def _beat(self, run: _Run) -> None:
        """The run's heartbeat, from the event loop: if the loop hangs, the beats stop and the
        arm's control loop brings the arm to a stop by itself."""
        period = None
        while True:
            ex = run.executor       # made in a worker thread: beaten from when it exists
            if ex is not None:
                ex.beat()
                period = period or ex.heartbeat / BEATS_PER_PERIOD
            await asyncio.sleep(period or 0.005)

    # ------------------------------------------------------------------ shutdown

    def stopping(self, seconds: float) -> None:
        """The server stops in ``seconds``: a run whose plan cannot end by then is brought to a
        controlled stop now (and one still being handed over, once it is), so that its call
        still ends with a last record and a status instead of being cut (one that settles past
        the grace is cut, and its arm stopped)."""
        self._stop_at = asyncio.get_running_loop().time() + seconds
        if self._stopping is None:
            self._stopping = asyncio.Event()
        self._stopping.set()        # watches end at once: nothing to finish
        for slot in self._arms.values():
            if slot.run is not None and slot.run.started is not None:
                self._halt_if_late(slot.run)

    def _halt_if_late(self, run: _Run) -> None:
        if (self._stop_at is not None and not run.ended and run.halted is None
                and run.started + run.duration > self._stop_at):
            run.halted = SHUTDOWN
            run.executor.halt(SHUTDOWN)


def _at_rest(slot: _Arm, deadline: float):
    """The arm's actual pose once it is at rest and its reading is fresh (younger than the
    arm's ``tracking_lag``: a pose that stopped updating reads as at rest); FAILED_PRECONDITION
    if that is not so by ``deadline``, or the arm is faulted."""
    fresh = slot.arm.tracking_lag
    while True:
        st = slot.arm.state()
        if st.faults:
            raise Precondition(f"from_current: arm {slot.name!r} is faulted: "
                               f"{'; '.join(st.faults)}")
        age = time.time() - st.stamp
        if st.at_rest and age <= fresh:
            return st.pose
        if time.monotonic() >= deadline:
            if age > fresh:
                raise Precondition(f"from_current: arm {slot.name!r} reported no pose for "
                                   f"{age:.6g} s (more than its tracking_lag, {fresh:.6g} s)")
            v = float(sum(x * x for x in st.linear_velocity) ** 0.5)
            w = float(sum(x * x for x in st.angular_velocity) ** 0.5)
            raise Precondition(f"from_current: arm {slot.name!r} is moving ({v:.6g} m/s, "
                               f"{w:.6g} rad/s) after {FREE_WAIT:g} s; it must be at rest")
        time.sleep(0.01)


_WAYPOINT = re.compile(r"\bwaypoints\[(\d+)\]")


def _plan_error(e: ValueError, from_current: bool) -> FieldError:
    """The planner's error named by the request's fields; with ``from_current`` the planner's
    waypoint k is the request's k - 1, and its waypoint 0 the arm's pose."""
    if not from_current:
        return rename(e, {"waypoints": "plan.waypoints{}", "limits": "plan.limits",
                          "start_velocity": "plan.start_linear_velocity"})
    text = str(e)
    if not _WAYPOINT.match(text):       # about the limits or the start velocity
        return rename(e, {"limits": "plan.limits",
                          "start_velocity": "plan.start_linear_velocity"})

    def name(m):
        k = int(m.group(1))
        return "the arm's pose (from_current)" if k == 0 else f"plan.waypoints[{k - 1}]"

    text = _WAYPOINT.sub(name, text)
    return (Precondition if isinstance(e, Infeasible) else FieldError)(text)


def _abandon(run) -> None:
    """A run whose call ended before the run did: a client that left stops the arm."""
    if not run.ended:
        run.abandoned = True
        if run.executor is not None:
            run.executor.cancel()


def _result(fb) -> tuple:
    """(ExecutionState, status) of a record; a result this server does not know is an error
    (the arm is still released)."""
    return RESULTS.get(fb.result.name, (pb.EXECUTION_ERROR, _UNAVAILABLE))


def _xyz(v) -> dict:
    x, y, z = (float(c) for c in v)
    return {"x": x, "y": y, "z": z}


def _feedback_msg(fb) -> pb.ExecutionFeedback:
    msg = pb.ExecutionFeedback(time=fb.time, state=_result(fb)[0],
                               message=fb.message or "")
    if fb.commanded is not None:
        dq_to_pose(fb.commanded, msg.commanded)
    if fb.actual is not None:
        dq_to_pose(fb.actual, msg.actual)
    return msg
