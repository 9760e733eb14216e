"""Execute a stream of time-stamped poses on any :class:`~drivers.base.Arm`.

A control loop feeds the arm one set-point per controller period from a buffer; the caller
(a gRPC stream, a planner) only fills the buffer, ahead of time, and never paces the arm: a late
network costs a controlled stop, never a late or doubled set-point. The arm's own
``servo_nowait()`` keeps the absolute cycle schedule (:class:`~drivers.base.Pacer`) and checks
every set-point against its :class:`~drivers.base.Limits`; between two set-points the loop waits
for the cycle's end or a cancel, whichever comes first, so a cancel stops the arm at once rather
than at the end of the period.

Where the loop runs follows the arm: in a thread of this process for an arm opened here, and in
the arm's own process for one opened with ``drivers.open_arm(spec, process=True)``
(:class:`drivers.armproc.ArmProcess`), where no thread of the caller's (gRPC, the feeder, the
garbage collector of a large heap) can hold the interpreter lock when a set-point is due. Both
run the same loop (:class:`_Control`) on the same checks; only the buffer differs (a deque here,
a ring in shared memory there).

The buffer holds samples on the plan's clock, pushed in chunks (``push(times, poses)``) at any
rate; they are resampled at the arm's period when pushed (:func:`service.interpolate.interpolate`),
so the control loop only pops. Each run ends in one :class:`Result`, in the style of ruckig's
result codes (positive: ended as controlled, negative: a fault):

* ``FINISHED``: ``finish()`` was called, every sample was sent and the arm settled on the last;
* ``STOPPED``: ``cancel()`` (a client gone, a user's stop): ``arm.stop()`` at once, within the
  period under way;
* ``STALLED``: the buffer ran dry before ``finish()``, or the process that fed an arm process
  died: the arm decelerates along its last step within ``stop_fraction`` of its acceleration
  limits, then stops;
* ``LIMITED``: a set-point broke the arm's Limits; the arm stopped itself, the message is the
  :class:`~drivers.base.LimitError`'s;
* ``PROTECTIVE_STOP``: the arm reports a protective or emergency stop; nothing more is sent
  (the arm has stopped itself, and a stop command would wait on a halted controller);
* ``ERROR``: anything else (lost connection, the arm moved before the first set-point).

A feedback record (:class:`Feedback`) per ``feedback_every`` set-points, and always one last with
the final result, goes to ``callback`` (called on a thread of the executor's: hand it on, e.g.
with ``loop.call_soon_threadsafe``) or, without one, to a queue read with
:meth:`Executor.feedback`.

    ex = Executor(arm)
    traj = plan(...).at_rate(1 / arm.period)
    ex.push(traj.time, traj.pose)
    ex.finish()
    assert ex.wait() == Result.FINISHED
"""
from __future__ import annotations

import collections
import enum
import math
import numbers
import os
import threading
import time
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from drivers.base import Arm, ArmError, LimitError, pose_delta, servo_step
from drivers.rotvec import quat_from_rotvec
from service import dq
from service.interpolate import MODES, interpolate

__all__ = ["Result", "Feedback", "Executor"]


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
    commanded: np.ndarray
    actual: Optional[np.ndarray]
    result: Result
    message: str = ""


def _positive(name: str, v) -> float:
    if isinstance(v, bool) or not (isinstance(v, numbers.Real) and math.isfinite(v) and v > 0):
        raise ValueError(f"{name}: must be a positive finite number, got {v!r}")
    return float(v)


def _tolerance(name: str, v) -> tuple[float, float]:
    try:
        lin, ang = v
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected (metres, radians), got {v!r}") from None
    return _positive(f"{name}[0]", lin), _positive(f"{name}[1]", ang)


@dataclass(frozen=True)
class Settings:
    """What the control loop needs of an :class:`Executor`'s arguments (checked there), whole
    and picklable, for a loop in another process."""
    period: float
    prefill: float
    stall_timeout: float
    settle_timeout: float
    feedback_every: int
    stop_fraction: float
    start_tolerance: tuple
    settle_tolerance: tuple
    realtime: Optional[int]


class Buffer:
    """The set-points as the control loop sees them; one per kind of transport (a deque in this
    process, :class:`drivers.armproc.RingBuffer` in shared memory)."""

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

    def gone(self) -> bool:
        """Whoever fed the buffer is gone (a dead parent process): stop as on a dry buffer."""
        return False

    def wait(self, end: float) -> None:
        """Until ``time.monotonic()`` reaches ``end``, or a cancel, whichever comes first."""
        raise NotImplementedError

    def sent(self, n: int) -> None:
        """``n`` set-points have been sent."""

    def emit(self, fb: Feedback, final: bool = False) -> None:
        raise NotImplementedError


def _realtime(priority: Optional[int]) -> bool:
    """The calling thread to SCHED_FIFO at ``priority``; False where not permitted (or None)."""
    if priority is None:
        return False
    try:        # this thread only: the caller's other threads keep their scheduling
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return True
    except (AttributeError, OSError):     # not Linux, or not permitted: as before
        return False


class _Control:
    """One run: the arm fed from ``buffer`` until a :class:`Result`. The same code in a thread
    (:class:`Executor`) and in an arm's own process (:mod:`drivers.armproc`)."""

    def __init__(self, arm: Arm, settings: Settings, buffer: Buffer):
        self.arm, self.s, self.buf = arm, settings, buffer
        self.period = settings.period
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

    def _check_start(self, first: np.ndarray) -> None:
        check_start(self.arm, first, self.s.start_tolerance)

    def _send(self, t: float, pose: np.ndarray) -> bool:
        """Waits out the cycle under way, then sends; False (nothing sent) if a cancel came
        meanwhile."""
        if self._end is not None:
            self.buf.wait(self._end)
            if self.buf.cancelled():
                return False
        self._called = time.monotonic()
        self._end = self.arm.servo_nowait(pose)
        self._returned = time.monotonic()
        if self._last is not None:
            self._step = servo_step(pose, self._last[1])
        self._last = (t, pose)
        self.sent += 1
        self.buf.sent(self.sent)
        if self.sent % self.s.feedback_every == 0:
            stamp, actual = self._actual()
            self.buf.emit(Feedback(t, stamp, pose, actual, Result.OK))
        return True

    def _cancelled(self, when: str = "") -> tuple[Result, str]:
        self._stop_arm()
        return Result.STOPPED, f"cancelled{when}; the arm was stopped"

    def _execute(self) -> tuple[Result, str]:
        s, buf = self.s, self.buf
        need = int(math.ceil(s.prefill / self.period - 1e-9)) + 1
        ready = buf.ready(need, s.stall_timeout)
        if buf.cancelled():
            return Result.STOPPED, "cancelled before the first set-point; the arm was not moved"
        if not ready or buf.first() is None:
            return Result.STALLED, (f"fewer than {s.prefill:g} s of the plan arrived within "
                                    f"{s.stall_timeout:g} s; the arm was not moved")
        # The arm may have moved since the first push.
        try:
            self._check_start(buf.first())
        except ValueError as e:
            return Result.ERROR, str(e)
        while True:
            if buf.cancelled():
                return self._cancelled()
            if buf.gone():
                return self._decelerate("the process that fed the arm is gone")
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

    def _decelerate(self, why: str = "") -> tuple[Result, str]:
        """Brake along the last step, shortening it by ``stop_fraction`` of the acceleration
        limits each period, so the stop passes the same Limits as the plan."""
        L, P = self.arm.limits, self.period
        dl = self.s.stop_fraction * L.max_linear_accel * P * P
        da = self.s.stop_fraction * L.max_angular_accel * P * P
        t, pose = self._last
        lin, ang = self._step[:3].copy(), self._step[3:].copy()
        n = 0
        while True:
            nl, na = float(np.linalg.norm(lin)), float(np.linalg.norm(ang))
            if nl == 0 and na == 0:
                break
            if self.buf.cancelled():
                return self._cancelled(" while stopping after a stall")
            lin = lin * (max(nl - dl, 0.0) / nl) if nl > 0 else lin
            ang = ang * (max(na - da, 0.0) / na) if na > 0 else ang
            q, p = dq.to_pose(pose)
            pose = dq.from_pose(dq.mul(dq.from_pose(quat_from_rotvec(ang), [0, 0, 0]),
                                       dq.from_pose(q, [0, 0, 0]))[:4], p + lin)
            t += P
            if not self._send(t, pose):
                return self._cancelled(" while stopping after a stall")
            n += 1
        if self._end is not None:
            self.buf.wait(self._end)        # the last braking step's cycle
        self._stop_arm()
        what = why or f"the buffer ran dry at plan time {t - n * P:.4f} s before finish()"
        return Result.STALLED, (f"{what}; the arm was brought to rest in {n} set-points and "
                                "stopped")


def check_start(arm: Arm, first: np.ndarray, tolerance: tuple) -> None:
    """``ValueError`` unless ``first`` is within ``tolerance`` (m, rad) of the arm's pose."""
    d, a = pose_delta(arm.tool_pose()[1], first)
    tl, ta = tolerance
    if d > tl or a > ta:
        raise ValueError(f"poses[0]: the plan starts {d:.4g} m and {math.degrees(a):.4g} deg "
                         f"from the arm's actual pose; it must start within {tl:.3g} m and "
                         f"{math.degrees(ta):.3g} deg of it (start_tolerance); the arm was "
                         "not moved")


class _DequeBuffer(Buffer):
    """The buffer of a loop in the caller's process: the :class:`Executor`'s own deque. Made by
    the loop's thread and dropped with it: held by the executor it would make a reference
    cycle, and an arm kept alive by a cycle is freed by the garbage collector whenever it runs
    (``ur_rtde``'s destructors then sleep a second with the interpreter lock held)."""

    def __init__(self, ex: "Executor"):
        self.ex = ex

    @property
    def realtime(self):
        return self.ex._realtime

    @realtime.setter
    def realtime(self, on):
        self.ex._realtime = on

    def ready(self, need, timeout):
        ex = self.ex
        with ex._cond:
            return ex._cond.wait_for(lambda: len(ex._slots) >= need or ex._finished_input
                                     or ex._cancel.is_set(), timeout)

    def first(self):
        with self.ex._cond:
            return self.ex._slots[0][1] if self.ex._slots else None

    def pop(self):
        with self.ex._cond:
            return self.ex._slots.popleft() if self.ex._slots else None

    def finished(self):
        return self.ex._finished_input

    def cancelled(self):
        return self.ex._cancel.is_set()

    def wait(self, end):
        self.ex._cancel.wait(max(0.0, end - time.monotonic()))

    def sent(self, n):
        self.ex._sent = n

    def emit(self, fb, final=False):
        self.ex._emit(fb)


class Executor:
    """Feeds ``arm`` from a buffer, one set-point per ``arm.period``: in a thread of this
    process, or in the arm's own process for an arm opened with ``process=True``
    (:func:`drivers.open_arm`).

    ``interpolation`` resamples pushed samples onto the arm's period (``"tool_linear"`` or
    ``"screw"``; samples already at the arm's rate come out unchanged). The first set-point goes
    out once ``prefill`` seconds of the plan are buffered (or ``finish()`` was called); if they do
    not arrive within ``stall_timeout`` seconds of the first push the run ends ``STALLED`` without
    moving. ``start_tolerance`` (m, rad): how far the plan's first pose may be from the arm's
    actual pose; by default what one set-point from rest may move under the arm's acceleration
    limits (90 % of ``max_*_accel * period**2``), since anything more would be refused by
    the Limits anyway. At the end the last pose is held until the arm is within
    ``settle_tolerance`` (m, rad) of it, for at most ``settle_timeout`` s, then ``arm.stop()``.

    ``realtime``: the control loop's thread asks the OS for real-time scheduling (Linux
    ``SCHED_FIFO`` at this priority, 1-99; None, the default: no), so that other work on the
    machine cannot delay a set-point by a scheduler slice; it needs ``CAP_SYS_NICE`` (root, or
    ``setcap cap_sys_nice+ep`` on the interpreter, or a ``rtprio`` limit). Without it the loop
    runs as before and :attr:`realtime` says so once it runs. Opt-in: a real-time thread takes
    its core from everything of lower priority (on a 2-core machine, a controller simulator
    beside it). BENCHMARKS.md "Issue 10: execution" and "Issue 10: execution in its own
    process" measure both, and both places of the loop.
    """

    def __init__(self, arm: Arm, *, interpolation: str = "tool_linear", prefill: float = 0.02,
                 stall_timeout: float = 1.0, feedback_every: int = 1,
                 callback: Optional[Callable[[Feedback], None]] = None,
                 start_tolerance: Optional[tuple[float, float]] = None,
                 settle_tolerance: tuple[float, float] = (1e-5, 1e-4),
                 settle_timeout: float = 1.0, stop_fraction: float = 0.5,
                 max_feedback: int = 100_000, realtime: Optional[int] = None,
                 heartbeat: Optional[float] = None):
        if not isinstance(arm, Arm):
            raise ValueError(f"arm: expected a drivers.base.Arm, got {type(arm).__name__}")
        if interpolation not in MODES:
            raise ValueError(f"interpolation: unknown {interpolation!r}; expected one of "
                             f"{', '.join(MODES)}")
        if not (isinstance(prefill, numbers.Real) and math.isfinite(prefill) and prefill >= 0):
            raise ValueError(f"prefill: must be a finite number >= 0, got {prefill!r}")
        for name, v in (("feedback_every", feedback_every), ("max_feedback", max_feedback)):
            if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < 1:
                raise ValueError(f"{name}: must be a whole number >= 1, got {v!r}")
        if not (isinstance(stop_fraction, numbers.Real) and 0 < stop_fraction <= 1):
            raise ValueError(f"stop_fraction: must be within (0, 1], got {stop_fraction!r}")
        if realtime is not None and (isinstance(realtime, bool) or not isinstance(
                realtime, numbers.Integral) or not 1 <= realtime <= 99):
            raise ValueError(f"realtime: must be a priority within 1..99 or None, got {realtime!r}")
        self.arm = arm
        self.period = float(arm.period)
        L = arm.limits
        self.interpolation = interpolation
        self.settings = Settings(
            period=self.period, prefill=float(prefill),
            stall_timeout=_positive("stall_timeout", stall_timeout),
            settle_timeout=_positive("settle_timeout", settle_timeout),
            feedback_every=int(feedback_every), stop_fraction=float(stop_fraction),
            start_tolerance=_tolerance("start_tolerance", start_tolerance)
            if start_tolerance is not None else
            (0.9 * L.max_linear_accel * self.period ** 2,
             0.9 * L.max_angular_accel * self.period ** 2),
            settle_tolerance=_tolerance("settle_tolerance", settle_tolerance),
            realtime=None if realtime is None else int(realtime))
        self._callback = callback
        self.heartbeat = None if heartbeat is None else _positive("heartbeat", heartbeat)
        self._beat = time.monotonic()
        self._halt_reason: Optional[str] = None

        self._cond = threading.Condition()      # guards the buffer and the run state
        self._slots: collections.deque = collections.deque()   # (plan time, pose) per period
        self._t0: Optional[float] = None        # plan time of the first set-point
        self._next_slot = 0                     # index of the next slot to resample
        self._tail: Optional[tuple[float, np.ndarray]] = None  # the last pushed sample
        self._finished_input = False
        self._cancel = threading.Event()
        self._push_lock = threading.Lock()      # one pusher resamples at a time
        self._feedback: collections.deque = collections.deque(maxlen=int(max_feedback))
        self.dropped = 0                        # feedback records that fell out of the queue
        self.result = Result.OK
        self.message = ""
        self._sent = 0
        self._done = threading.Event()
        self._started = False
        # an arm in its own process runs the loop there, on a ring in shared memory
        self._remote = arm.start_run(self) if hasattr(arm, "start_run") else None
        self._realtime = False

    @property
    def prefill(self) -> float:
        return self.settings.prefill

    @property
    def stall_timeout(self) -> float:
        return self.settings.stall_timeout

    @property
    def settle_tolerance(self) -> tuple:
        return self.settings.settle_tolerance

    @property
    def start_tolerance(self) -> tuple:
        return self.settings.start_tolerance

    @property
    def sent(self) -> int:
        """Set-points sent so far."""
        return self._remote.sent_count() if self._remote is not None else self._sent

    @property
    def realtime(self) -> bool:
        """Whether the control loop got real-time scheduling (False until it runs)."""
        return self._remote.realtime if self._remote is not None else self._realtime

    # ------------------------------------------------------------------ caller side
    def push(self, times, poses) -> None:
        """Append samples: ``times`` ``(N,)`` seconds on the plan's clock, strictly increasing
        and after every sample pushed before; ``poses`` ``(N, 8)`` unit dual quaternions
        ``T_base_tool``. The first push checks that the plan starts at the arm's actual pose
        (``ValueError`` naming the distance and the tolerance) and starts the run. For an arm in
        its own process, a push waits while the ring in shared memory is full."""
        t = np.asarray(times, dtype=np.float64)
        p = np.asarray(poses, dtype=np.float64)
        if t.ndim != 1 or t.size == 0:
            raise ValueError(f"times: expected a non-empty 1-D array, got shape {t.shape}")
        if p.shape != (t.size, 8):
            raise ValueError(f"poses: expected shape ({t.size}, 8) to match times, got {p.shape}")
        bad = np.flatnonzero(~np.isfinite(t))
        if bad.size:
            raise ValueError(f"times[{bad[0]}]: contains NaN or infinity")
        bad = np.flatnonzero(~np.all(np.isfinite(p), axis=1))
        if bad.size:
            raise ValueError(f"poses[{bad[0]}]: contains NaN or infinity")
        norms = np.linalg.norm(p[:, :4], axis=1)
        bad = np.flatnonzero(np.abs(norms - 1.0) > dq.UNIT_TOL)
        if bad.size:
            raise ValueError(f"poses[{bad[0]}]: quaternion norm {norms[bad[0]]:.6g} is not unit "
                             f"(tolerance {dq.UNIT_TOL})")
        p = dq.normalize(p)
        bad = np.flatnonzero(np.diff(t) <= 0)
        if bad.size:
            i = bad[0] + 1
            raise ValueError(f"times[{i}]: {float(t[i])!r} is not after the previous time "
                             f"{float(t[i - 1])!r}")
        with self._push_lock:
            with self._cond:
                if self._finished_input or self._done.is_set():
                    raise ValueError("push: the plan was already finished or the run has ended "
                                     f"({self.result.name})")
                tail, t0, k0 = self._tail, self._t0, self._next_slot
            if tail is not None and t[0] <= tail[0]:
                raise ValueError(f"times[0]: {float(t[0])!r} is not after the last pushed time "
                                 f"{tail[0]!r}")
            if t0 is None:
                check_start(self.arm, p[0], self.start_tolerance)
                t0 = float(t[0])
            slots = self._resample(t0, k0, tail, t, p)
            if self._remote is not None:
                self._remote.put(slots)
            with self._cond:
                self._t0 = t0
                self._tail = (float(t[-1]), p[-1])
                self._next_slot = k0 + len(slots)
                if self._remote is None:
                    self._slots.extend(slots)
                self._cond.notify_all()
            if not self._started:
                self._started = True
                if self._remote is not None:
                    self._remote.start()
                else:
                    threading.Thread(target=self._run, name="executor", daemon=True).start()

    def push_plan(self, trajectory) -> None:
        """The whole plan at once, sampled by the control loop at the arm's period as it goes:
        ``trajectory`` is a :class:`service.trajectory.Trajectory` (anything with ``duration``
        and ``sample(times)``). Its start is checked against the arm's actual pose
        (``ValueError`` naming ``poses[0]``, as :meth:`push`), then the input is finished."""
        start = trajectory.sample(np.zeros(1)).pose[0]
        check_start(self.arm, start, self.start_tolerance)
        samples = trajectory.sample(
            np.append(np.arange(0.0, trajectory.duration, self.period), trajectory.duration))
        self.push(samples.time, samples.pose)
        self.finish()

    def beat(self) -> None:
        """The owner is alive: call at least every ``heartbeat`` seconds while the run goes."""
        self._beat = time.monotonic()

    def halt(self, reason: str) -> None:
        """Bring the arm to a controlled stop; the run ends ``STOPPED`` with ``reason`` as its
        message."""
        self._halt_reason = str(reason)
        self.cancel()

    def _resample(self, t0, k0, tail, t, p) -> list[tuple[float, np.ndarray]]:
        """The period slots from index ``k0`` on that the samples (after ``tail``) cover."""
        if tail is not None:
            t = np.concatenate([[tail[0]], t])
            p = np.concatenate([tail[1][None], p])
        k1 = int(math.floor((t[-1] - t0) / self.period + 1e-9)) + 1
        if k1 <= k0:
            return []
        st = t0 + self.period * np.arange(k0, k1)
        if t.size == 1:   # the very first sample alone: it is slot 0
            return [(float(st[0]), p[0])]
        # rounding may put the last slot a hair past the last sample
        poses = interpolate(t, p, np.minimum(st, t[-1]), self.interpolation)
        return list(zip(st.tolist(), poses))

    def finish(self) -> None:
        """No more samples: the run ends ``FINISHED`` after the last one. A plan whose end is
        not on the period grid gets one more set-point, on its last pose."""
        with self._push_lock, self._cond:
            if self._tail is None:
                raise ValueError("finish: no samples were pushed")
            if self._finished_input:
                return
            last_slot = self._t0 + self.period * (self._next_slot - 1)
            if self._tail[0] - last_slot > 1e-9:
                slot = (self._t0 + self.period * self._next_slot, self._tail[1])
                if self._remote is not None:
                    self._remote.put([slot])
                else:
                    self._slots.append(slot)
                self._next_slot += 1
            self._finished_input = True
            if self._remote is not None:
                self._remote.finish()
            self._cond.notify_all()

    def cancel(self) -> None:
        """Stop the arm (``arm.stop()``) at once, within the period under way; the run ends
        ``STOPPED``."""
        self._cancel.set()
        if self._remote is not None and not self._done.is_set():
            self._remote.cancel()
        with self._cond:
            self._cond.notify_all()

    def wait(self, timeout: Optional[float] = None) -> Optional[Result]:
        """The final result once the run ended, else None after ``timeout`` seconds."""
        return self.result if self._done.wait(timeout) else None

    @property
    def done(self) -> bool:
        return self._done.is_set()

    @property
    def buffered(self) -> float:
        """Seconds of the plan buffered and not yet sent."""
        if self._remote is not None:
            return self._remote.buffered() * self.period
        with self._cond:
            return len(self._slots) * self.period

    def feedback(self, timeout: Optional[float] = None) -> Optional[Feedback]:
        """The oldest unread record (without a ``callback``), waiting up to ``timeout`` s;
        None when there is none (and, once the run ended, none will come)."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._feedback or self._done.is_set(), timeout):
                return None
            return self._feedback.popleft() if self._feedback else None

    def close(self) -> None:
        """Cancel a run still going and wait for its end."""
        if self._started and not self._done.is_set():
            self.cancel()
            self._done.wait()
        if self._remote is not None:
            self._remote.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ results
    def _emit(self, fb: Feedback) -> None:
        if self._callback is not None:
            self._callback(fb)
            return
        with self._cond:
            if len(self._feedback) == self._feedback.maxlen:
                self.dropped += 1
            self._feedback.append(fb)
            self._cond.notify_all()

    def _ended(self, last: Feedback) -> None:
        """The run's last record: its result is the executor's."""
        if last.commanded is None and self._t0 is not None:
            last = Feedback(self._t0, last.stamp, None, last.actual, last.result, last.message)
        with self._cond:
            self.result, self.message = last.result, last.message
        self._emit(last)    # before done: a reader that sees the end has the last record queued
        self._done.set()
        with self._cond:
            self._cond.notify_all()

    def _run(self) -> None:
        self._ended(_Control(self.arm, self.settings, _DequeBuffer(self)).run())
