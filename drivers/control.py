"""The control loop of an :class:`~drivers.executor.Executor` run, the same code in a thread of
the caller's process and in an arm's own process (:mod:`dqpose.drivers.armproc`); only the
:class:`Buffer` differs (a deque there, a ring in shared memory here, or a plan sampled as it
goes, :class:`PlanSlots`).

Every period the loop reads the arm's actual pose and judges the next set-point against it
before sending (:class:`Tracking`): an arm that no longer follows (lost frames, an obstacle, a
slowed controller) ends the run ``TRACKING`` with the arm stopped, instead of a catch-up to a
set-point far ahead. Between set-points it watches the owner: a cancel stops the arm at once; a
halt or three missed heartbeats brake it to rest within the Limits.
"""
from __future__ import annotations

import enum
import math
import os
import threading
import time
from dataclasses import dataclass
from typing import Optional

import numpy as np

from dqpose import dq
from dqpose.drivers.base import Arm, ArmError, LimitError, pose_delta, servo_step
from dqpose.drivers.rotvec import quat_from_rotvec

__all__ = ["Result", "Feedback", "Settings", "Buffer", "PlanSlots", "Tracking", "Control",
           "check_start", "claim", "plan_start", "MISSED_BEATS"]

#: heartbeats an owner may miss before the loop brakes the arm to rest
MISSED_BEATS = 3


class Result(enum.IntEnum):
    OK = 0                  # working
    FINISHED = 1
    STOPPED = 2
    STALLED = 3
    LIMITED = -1
    PROTECTIVE_STOP = -2
    ERROR = -3
    TRACKING = -4


@dataclass(frozen=True)
class Feedback:
    """One step: ``time`` the set-point's time on the plan's clock, ``stamp`` the ``time.time()``
    the actual pose was read, ``commanded`` and ``actual`` ``T_base_tool`` (``actual`` None when
    the arm could not be read), ``result`` ``OK`` while running, else how the run ended, with
    ``message``."""
    time: float
    stamp: float
    commanded: Optional[np.ndarray]
    actual: Optional[np.ndarray]
    result: Result
    message: str = ""


@dataclass(frozen=True)
class Settings:
    """What the control loop needs of an Executor's arguments and of its arm's keys (checked
    there), whole and picklable, for a loop in another process."""
    period: float
    prefill: float
    stall_timeout: float
    settle_timeout: float
    feedback_every: int
    stop_fraction: float
    start_tolerance: tuple
    settle_tolerance: tuple
    realtime: Optional[int]
    heartbeat: Optional[float]
    max_tracking: float
    max_tracking_angle: float
    tracking_lag: float


class Buffer:
    """The set-points as the control loop sees them, and the owner's signals; one per kind of
    transport (a deque in this process, :class:`dqpose.drivers.run.LocalRun`'s;
    :class:`dqpose.drivers.armchild.RingBuffer`)."""

    #: set by the loop: whether it got real-time scheduling
    realtime = False

    def ready(self, need: int, timeout: float) -> bool:
        """Wait until ``need`` set-points are buffered, the input finished, or a cancel; False
        if none of these came within ``timeout`` seconds."""
        raise NotImplementedError

    def first(self) -> Optional[np.ndarray]:
        """The first buffered pose, not taken."""
        raise NotImplementedError

    def pop(self) -> Optional[tuple[float, np.ndarray]]:
        """The next (plan time, pose), or None when the buffer is empty."""
        raise NotImplementedError

    def finished(self) -> bool:
        raise NotImplementedError

    def cancelled(self) -> bool:
        raise NotImplementedError

    def halted(self) -> Optional[str]:
        """The reason given to ``halt``, or None."""
        return None

    def beat_age(self) -> float:
        """Seconds since the owner's last heartbeat (or since the run started)."""
        return 0.0

    def gone(self) -> bool:
        """Whoever fed the buffer is gone (a dead parent process): stop as on a dry buffer."""
        return False

    def wait(self, end: float) -> None:
        """Until ``time.monotonic()`` reaches ``end``, or a cancel, whichever comes first (a halt
        is seen at the period's end: it brakes period by period)."""
        raise NotImplementedError

    def sent(self, n: int) -> None:
        """``n`` set-points have been sent."""

    def emit(self, fb: Feedback, final: bool = False) -> None:
        raise NotImplementedError


class PlanSlots:
    """A plan's set-points one period apart from its start, sampled in chunks as the loop takes
    them, so a long plan is never held whole: slot ``k`` is the plan at ``k * period``, and a
    plan whose end is off the grid gets one more slot, on its last pose (as ``push`` and
    ``finish`` of the same samples would give). ``trajectory``: a
    :class:`dqpose.trajectory.Trajectory` (``duration``, ``sample(times)``)."""

    CHUNK = 64

    def __init__(self, trajectory, period: float):
        self.trajectory, self.period = trajectory, float(period)
        self.duration = float(trajectory.duration)
        self.count = int(math.ceil(self.duration / self.period - 1e-9)) + 1
        self.taken = 0
        self._base, self._poses = 0, np.zeros((0, 8))

    def _chunk(self, k: int) -> None:
        t = self.period * np.arange(k, min(k + self.CHUNK, self.count))
        self._base, self._poses = k, self.trajectory.sample(np.minimum(t, self.duration)).pose

    def first(self) -> Optional[np.ndarray]:
        return self.pose(self.taken) if self.taken < self.count else None

    def pose(self, k: int) -> np.ndarray:
        if not self._base <= k < self._base + len(self._poses):
            self._chunk(k)
        return self._poses[k - self._base]

    def pop(self) -> Optional[tuple[float, np.ndarray]]:
        k = self.taken
        if k >= self.count:
            return None
        pose = self.pose(k)
        self.taken = k + 1
        return k * self.period, pose

    def left(self) -> int:
        return self.count - self.taken


def plan_start(trajectory) -> np.ndarray:
    """The first pose of ``trajectory`` (one sample: a refused plan costs nothing more)."""
    return trajectory.sample(np.zeros(1)).pose[0]


class Tracking:
    """How far the arm is from what it was sent: the distance (and angle) from its actual pose
    to the nearest of the set-points sent over the last ``tracking_lag`` seconds and the one
    about to go. An arm that follows trails its set-points by its servo lag and the age of its
    feedback, which the window covers; one that stopped following (lost frames, an obstacle, a
    slowed controller) leaves the window, and the next set-point is refused once it is more than
    ``max_tracking`` (or ``max_tracking_angle``) away: no set-point the arm has to catch up to
    goes out, so no catch-up exceeds what a normal lag already is
    (``max_tracking + tracking_lag * speed``)."""

    def __init__(self, s: Settings):
        self.s = s
        n = max(1, int(math.ceil(s.tracking_lag / s.period - 1e-9))) + 1
        self._t = np.zeros((n, 3))
        self._q = np.zeros((n, 4))
        self._n = 0

    def add(self, pose: np.ndarray) -> None:
        i = self._n % len(self._t)
        self._t[i], self._q[i] = dq.to_pose(pose)[1], pose[:4]
        self._n += 1

    def error(self, actual: np.ndarray, candidate: np.ndarray) -> tuple[float, float]:
        """(m, rad) from ``actual`` to the nearest recent set-point or ``candidate``."""
        n = min(self._n, len(self._t))
        t, q = dq.to_pose(actual)[1], actual[:4]
        lin = min(float(np.linalg.norm(dq.to_pose(candidate)[1] - t)),
                  float(np.min(np.linalg.norm(self._t[:n] - t, axis=1))) if n else math.inf)
        dots = np.abs(self._q[:n] @ q) if n else np.zeros(0)
        c = max(abs(float(np.dot(candidate[:4], q))), float(dots.max()) if n else 0.0)
        return lin, 2.0 * math.acos(min(1.0, c))

    def check(self, actual: np.ndarray, candidate: np.ndarray) -> Optional[str]:
        """Why ``candidate`` must not be sent, or None."""
        lin, ang = self.error(actual, candidate)
        s = self.s
        for key, value, bound, unit in (("max_tracking", lin, s.max_tracking, "m"),
                                        ("max_tracking_angle", ang, s.max_tracking_angle, "rad")):
            if value > bound:
                return (f"tracking: the arm is {value:.4g} {unit} from its set-points of the last "
                        f"{s.tracking_lag:g} s, more than {key} = {bound:g} {unit} (it does not "
                        f"follow); the arm was stopped")
        return None


class _OffTrack(Exception):
    pass


def claim(arm: Arm, timeout: float) -> threading.Lock:
    """The arm's run lock, held by one run at a time (released when the run ends): waits up to
    ``timeout`` s for a run still ending (a cancelled one stopping its arm), else
    ``ArmError("busy ...")``."""
    lock = arm.__dict__.setdefault("_run_lock", threading.Lock())
    if not lock.acquire(timeout=max(0.0, timeout)):
        raise ArmError(f"busy: another plan is running on this arm and did not end within "
                       f"{timeout:g} s")
    return lock


def check_start(arm: Arm, first: np.ndarray, tolerance: tuple) -> None:
    """``ValueError`` unless ``first`` is within ``tolerance`` (m, rad) of the arm's pose."""
    d, a = pose_delta(arm.tool_pose()[1], first)
    tl, ta = tolerance
    if d > tl or a > ta:
        raise ValueError(f"poses[0]: the plan starts {d:.4g} m and {math.degrees(a):.4g} deg "
                         f"from the arm's actual pose; it must start within {tl:.3g} m and "
                         f"{math.degrees(ta):.3g} deg of it (start_tolerance); the arm was "
                         "not moved")


def _realtime(priority: Optional[int]) -> bool:
    """The calling thread to SCHED_FIFO at ``priority``; False where not permitted (or None)."""
    if priority is None:
        return False
    try:        # this thread only: the caller's other threads keep their scheduling
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return True
    except (AttributeError, OSError):     # not Linux, or not permitted: as before
        return False


class Control:
    """One run: the arm fed from ``buffer`` until a :class:`Result`."""

    def __init__(self, arm: Arm, settings: Settings, buffer: Buffer):
        self.arm, self.s, self.buf = arm, settings, buffer
        self.period = settings.period
        self.track = Tracking(settings)
        self._last: Optional[tuple[float, np.ndarray]] = None   # the last set-point sent
        self._step = np.zeros(6)
        self._returned = self._called = 0.0     # monotonic: the last servo returned, began
        self._end: Optional[float] = None       # when the cycle of the last set-point ends
        self.sent = 0

    def run(self) -> Feedback:
        """Runs to the end; the last record (the result, its message)."""
        self.buf.realtime = _realtime(self.s.realtime)
        try:
            result, message = self._execute()
        except _OffTrack as e:
            self._stop_arm()
            result, message = Result.TRACKING, str(e)
        except LimitError as e:
            result, message = Result.LIMITED, str(e)
            late = self._called - self._returned
            if self._returned and late > 10 * self.period:
                # a starved control loop, not the plan: the arm's watchdog stopped it meanwhile
                message += (f" (this control loop was {late * 1e3:.0f} ms late for the "
                            "set-point; a stream that pauses is stopped by the arm's watchdog)")
        except ArmError as e:
            result, message = self._fault(e)
        except Exception as e:  # the run must end with a result, whatever broke
            result, message = Result.ERROR, f"{type(e).__name__}: {e}"
            self._stop_arm()
        stamp, actual = self._actual()
        t, pose = self._last if self._last is not None else (math.nan, None)
        return Feedback(t, stamp, pose, actual, result, message)

    def _actual(self) -> tuple[float, Optional[np.ndarray]]:
        try:
            return self.arm.tool_pose()
        except ArmError:
            return time.time(), None

    def _fault(self, e: ArmError) -> tuple[Result, str]:
        # A controller may refuse a command (a paused program) a cycle or two before its status
        # data says why: give the report a few periods to arrive.
        deadline = time.monotonic() + max(10 * self.period, 0.05)
        while True:
            try:
                st = self.arm.status()
            except ArmError:
                return Result.ERROR, str(e)
            if st.protective_stop or st.emergency_stop:
                what = "emergency stop" if st.emergency_stop else "protective stop"
                msg = str(e) if what in str(e) else f"{what}: {e}"
                return Result.PROTECTIVE_STOP, msg
            if time.monotonic() > deadline:
                break
            time.sleep(self.period)
        self._stop_arm()
        return Result.ERROR, str(e)

    def _stop_arm(self) -> None:
        try:
            self.arm.stop()
        except ArmError:
            pass   # the arm is gone or faulted; it stops itself then

    def _send(self, t: float, pose: np.ndarray) -> bool:
        """Judges ``pose`` against the arm's actual pose (:class:`Tracking`), waits out the
        cycle under way, then sends; False (nothing sent) if a cancel came meanwhile."""
        stamp, actual = self.arm.tool_pose()
        why = self.track.check(actual, pose)
        if why is not None:
            age = time.time() - stamp
            if age > self.s.tracking_lag:   # not the arm: its feedback stopped
                raise ArmError(f"stale feedback: the arm's pose is {age:.3g} s old, more than "
                               f"tracking_lag = {self.s.tracking_lag:g} s, so whether it "
                               "follows cannot be told; the arm was stopped")
            raise _OffTrack(why)
        if self._end is not None:
            self.buf.wait(self._end)
            if self.buf.cancelled():
                return False
        self._called = time.monotonic()
        self._end = self.arm.servo_nowait(pose)
        self._returned = time.monotonic()
        self.track.add(pose)
        if self._last is not None:
            self._step = servo_step(pose, self._last[1])
        self._last = (t, pose)
        self.sent += 1
        self.buf.sent(self.sent)
        if self.sent % self.s.feedback_every == 0:
            self.buf.emit(Feedback(t, stamp, pose, actual, Result.OK))
        return True

    def _cancelled(self, when: str = "") -> tuple[Result, str]:
        self._stop_arm()
        return Result.STOPPED, f"cancelled{when}; the arm was stopped"

    def _stop_reason(self) -> Optional[tuple[Result, str]]:
        """A halt or a heartbeat missed too long: (the result, why), else None."""
        reason = self.buf.halted()
        if reason is not None:
            return Result.STOPPED, reason
        hb = self.s.heartbeat
        if hb is not None:
            age = self.buf.beat_age()
            if age > MISSED_BEATS * hb:
                return Result.STALLED, (f"heartbeat: none for {age:.3g} s ({MISSED_BEATS} "
                                        f"beats of {hb:g} s missed)")
        return None

    def _execute(self) -> tuple[Result, str]:
        s, buf = self.s, self.buf
        need = int(math.ceil(s.prefill / self.period - 1e-9)) + 1
        ready = buf.ready(need, s.stall_timeout)
        if buf.cancelled():
            return Result.STOPPED, "cancelled before the first set-point; the arm was not moved"
        stop = self._stop_reason()
        if stop is not None:
            return stop[0], f"{stop[1]}; the arm was not moved"
        if not ready or buf.first() is None:
            return Result.STALLED, (f"fewer than {s.prefill:g} s of the plan arrived within "
                                    f"{s.stall_timeout:g} s; the arm was not moved")
        # The arm may have moved since the first push.
        try:
            check_start(self.arm, buf.first(), s.start_tolerance)
        except ValueError as e:
            return Result.ERROR, str(e)
        while True:
            if buf.cancelled():
                return self._cancelled()
            stop = self._stop_reason()
            if stop is not None:
                return self._decelerate(*stop)
            if buf.gone():
                return self._decelerate(Result.STALLED, "the process that fed the arm is gone")
            finished = buf.finished()       # read first: once set, every slot is in
            slot = buf.pop()
            if slot is not None:
                if not self._send(*slot):
                    return self._cancelled()
            elif finished:
                return self._settle()
            else:
                return self._decelerate()

    def _settle(self) -> tuple[Result, str]:
        t, goal = self._last
        tl, ta = self.s.settle_tolerance
        deadline = time.monotonic() + self.s.settle_timeout
        while True:
            if self.buf.cancelled():
                return self._cancelled(" while settling")
            stop = self._stop_reason()
            if stop is not None:        # at the end already: the arm's own stop is gentle
                self._stop_arm()
                return stop[0], f"{stop[1]}; the arm was stopped while settling on the last pose"
            d, a = pose_delta(self.arm.tool_pose()[1], goal)
            if d <= tl and a <= ta:
                self._stop_arm()
                return Result.FINISHED, ""
            if time.monotonic() > deadline:
                self._stop_arm()
                return Result.ERROR, (f"the last pose was not reached within "
                                      f"{self.s.settle_timeout:g} s ({d:.4g} m and "
                                      f"{math.degrees(a):.4g} deg away); the arm was stopped")
            if not self._send(t, goal):
                return self._cancelled(" while settling")

    def _decelerate(self, result: Result = Result.STALLED, why: str = "") -> tuple[Result, str]:
        """Brake along the last step, shortening it by ``stop_fraction`` of the acceleration
        limits each period, so the stop passes the same Limits (and tracking) as the plan."""
        if self._last is None:
            return result, f"{why}; the arm was not moved"
        L, P = self.arm.limits, self.period
        dl = self.s.stop_fraction * L.max_linear_acceleration * P * P
        da = self.s.stop_fraction * L.max_angular_acceleration * P * P
        t, pose = self._last
        lin, ang = self._step[:3].copy(), self._step[3:].copy()
        n = 0
        while True:
            nl, na = float(np.linalg.norm(lin)), float(np.linalg.norm(ang))
            if nl == 0 and na == 0:
                break
            if self.buf.cancelled():
                return self._cancelled(" while braking to a stop")
            lin = lin * (max(nl - dl, 0.0) / nl) if nl > 0 else lin
            ang = ang * (max(na - da, 0.0) / na) if na > 0 else ang
            q, p = dq.to_pose(pose)
            pose = dq.from_pose(dq.mul(dq.from_pose(quat_from_rotvec(ang), [0, 0, 0]),
                                       dq.from_pose(q, [0, 0, 0]))[:4], p + lin)
            t += P
            if not self._send(t, pose):
                return self._cancelled(" while braking to a stop")
            n += 1
        if self._end is not None:
            self.buf.wait(self._end)        # the last braking step's cycle
        self._stop_arm()
        what = why or f"the buffer ran dry at plan time {t - n * P:.4f} s before finish()"
        return result, f"{what}; the arm was brought to rest in {n} set-points and stopped"
