"""Execute a stream of time-stamped poses on any :class:`~drivers.base.Arm`.

A control loop feeds the arm one set-point per controller period from a buffer; the caller
(a gRPC stream, a planner) only fills the buffer, ahead of time, and never paces the arm: a late
network costs a controlled stop, never a late or doubled set-point. The arm's own
``servo_nowait()`` keeps the absolute cycle schedule (:class:`~drivers.base.Pacer`) and checks
every set-point against its :class:`~drivers.base.Limits`; between two set-points the loop waits
for the cycle's end or a cancel, whichever comes first, so a cancel stops the arm at once rather
than at the end of the period.

Where the loop runs follows the arm (:meth:`Arm.open_run <dqpose.drivers.base.Arm.open_run>`,
asked once: :mod:`dqpose.drivers.run`): in a thread of this process for an arm opened here, and in
the arm's own process for one opened with ``drivers.open_arm(spec, process=True)``
(:class:`dqpose.drivers.armproc.ArmProcess`), where no thread of the caller's (gRPC, the feeder, the
garbage collector of a large heap) can hold the interpreter lock when a set-point is due. Both
run the same loop (:class:`dqpose.drivers.control.Control`) on the same checks; only the buffer
differs (a deque here, a ring in shared memory there). One run at a time per arm: a run started
while another is still ending waits for it (``busy_timeout``), else ``ArmError("busy ...")``.

A plan comes whole (``push_plan(trajectory)``: the loop samples it at the arm's period as it
goes, so its cost to the caller is its waypoints, whatever its duration) or as samples on the
plan's clock, pushed in chunks (``push(times, poses)``) at any rate and resampled at the arm's
period when pushed (:func:`dqpose.interpolate.interpolate`). Every set-point is judged against
the arm's actual pose before it goes (``max_tracking``, ``max_tracking_angle`` and
``tracking_lag``, the arm's keys: :class:`dqpose.drivers.control.Tracking`). Each run ends in one
:class:`Result`, in the style of ruckig's result codes (positive: ended as controlled, negative:
a fault):

* ``FINISHED``: the input was finished, every set-point sent and the arm settled on the last;
* ``STOPPED``: ``cancel()`` (a client gone, a user's stop): ``arm.stop()`` at once, within the
  period under way; or ``halt(reason)``: braked to rest as below, ``reason`` the message;
* ``STALLED``: the buffer ran dry before ``finish()``, the owner missed three heartbeats
  (``heartbeat``: a hung server), or the process that fed an arm process died: the arm
  decelerates along its last step within ``stop_fraction`` of its acceleration limits, then
  stops;
* ``LIMITED``: a set-point broke the arm's Limits; the arm stopped itself, the message is the
  :class:`~drivers.base.LimitError`'s;
* ``PROTECTIVE_STOP``: the arm reports a protective or emergency stop; nothing more is sent
  (the arm has stopped itself, and a stop command would wait on a halted controller);
* ``ERROR``: anything else (lost connection, stale data, the arm moved before the first
  set-point);
* ``TRACKING``: the arm no longer follows its set-points (lost frames, an obstacle): the next
  one is not sent and the arm is stopped where it is (``arm.stop()``), no catch-up.

A feedback record (:class:`Feedback`) per ``feedback_every`` set-points, and always one last with
the final result, goes to ``callback`` (called on a thread of the executor's: hand it on, e.g.
with ``loop.call_soon_threadsafe``) or, without one, to a queue read with
:meth:`Executor.feedback`.

    ex = Executor(arm, heartbeat=arm.heartbeat)
    ex.push_plan(plan(...))
    while not ex.done:          # the owner's heartbeat, e.g. a task on a server's event loop
        ex.beat()
        time.sleep(arm.heartbeat)
    assert ex.wait() == Result.FINISHED
"""
from __future__ import annotations

import math
import numbers
import threading
import time
from typing import Callable, Optional

import numpy as np

from dqpose import dq
from dqpose.drivers.base import Arm
from dqpose.drivers.control import Feedback, Result, Settings
from dqpose.drivers.run import LocalRun, Outcome, Run
from dqpose.drivers.spec import ARM_KEYS
from dqpose.interpolate import interpolate
from dqpose.trajectory import INTERPOLATIONS

__all__ = ["Result", "Feedback", "Executor"]


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


def _key(arm: Arm, name: str) -> float:
    """The arm's value of an arm-spec key (the table's default for an arm without keys)."""
    return float(arm.options.get(name, ARM_KEYS[name].default_for(None)))


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

    ``heartbeat`` (s, None: no heartbeat; an arm's own is ``arm.heartbeat``): the owner calls
    :meth:`beat` at least this often while the run goes, from the thread (or event loop) whose
    health the arm's motion depends on; after three missed beats the loop brakes the arm to
    rest and the run ends ``STALLED``. ``busy_timeout``: how long the start of a run waits for
    the arm's previous run to end (a cancelled run stopping its arm).

    ``realtime``: the control loop's thread asks the OS for real-time scheduling (Linux
    ``SCHED_FIFO`` at this priority, 1-99; None, the default: no), so that other work on the
    machine cannot delay a set-point by a scheduler slice; it needs ``CAP_SYS_NICE`` (root, or
    ``setcap cap_sys_nice+ep`` on the interpreter, or a ``rtprio`` limit). Without it the loop
    runs as before and :attr:`realtime` says so once it runs. Opt-in: a real-time thread takes
    its core from everything of lower priority (on a 2-core machine, a controller simulator
    beside it). docs/benchmarks/arms.md#control-loop and
    docs/benchmarks/arms.md#thread-or-process-for-the-loop measure both, and both places of the
    loop.
    """

    def __init__(self, arm: Arm, *, interpolation: str = "tool_linear", prefill: float = 0.02,
                 stall_timeout: float = 1.0, feedback_every: int = 1,
                 callback: Optional[Callable[[Feedback], None]] = None,
                 start_tolerance: Optional[tuple[float, float]] = None,
                 settle_tolerance: tuple[float, float] = (1e-5, 1e-4),
                 settle_timeout: float = 1.0, stop_fraction: float = 0.5,
                 max_feedback: int = 100_000, realtime: Optional[int] = None,
                 heartbeat: Optional[float] = None, busy_timeout: float = 1.0):
        if not isinstance(arm, Arm):
            raise ValueError(f"arm: expected a drivers.base.Arm, got {type(arm).__name__}")
        if interpolation not in INTERPOLATIONS:
            raise ValueError(f"interpolation: unknown {interpolation!r}; expected one of "
                             f"{', '.join(INTERPOLATIONS)}")
        if not (isinstance(prefill, numbers.Real) and math.isfinite(prefill) and prefill >= 0):
            raise ValueError(f"prefill: must be a finite number >= 0, got {prefill!r}")
        if not (isinstance(busy_timeout, numbers.Real) and math.isfinite(busy_timeout)
                and busy_timeout >= 0):
            raise ValueError(f"busy_timeout: must be a finite number >= 0, got {busy_timeout!r}")
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
        self.busy_timeout = float(busy_timeout)
        self.settings = Settings(
            period=self.period, prefill=float(prefill),
            stall_timeout=_positive("stall_timeout", stall_timeout),
            settle_timeout=_positive("settle_timeout", settle_timeout),
            feedback_every=int(feedback_every), stop_fraction=float(stop_fraction),
            start_tolerance=_tolerance("start_tolerance", start_tolerance)
            if start_tolerance is not None else
            (0.9 * L.max_linear_acceleration * self.period ** 2,
             0.9 * L.max_angular_acceleration * self.period ** 2),
            settle_tolerance=_tolerance("settle_tolerance", settle_tolerance),
            realtime=None if realtime is None else int(realtime),
            heartbeat=None if heartbeat is None else _positive("heartbeat", heartbeat),
            max_tracking=_key(arm, "max_tracking"),
            max_tracking_angle=_key(arm, "max_tracking_angle"),
            tracking_lag=_key(arm, "tracking_lag"))
        self._outcome = Outcome(callback, max_feedback)
        self._cond = threading.Condition()      # guards the input's state below
        self._t0: Optional[float] = None        # plan time of the first set-point
        self._next_slot = 0                     # index of the next slot to resample
        self._tail: Optional[tuple[float, np.ndarray]] = None  # the last pushed sample
        self._finished_input = False
        self._push_lock = threading.Lock()      # one pusher resamples at a time
        self._started = False
        # where the loop runs, the arm's to say (an arm in its own process runs it there; None:
        # a thread of this process)
        run = arm.open_run(self.settings, self.busy_timeout, self._outcome)
        self._run: Run = run if run is not None else LocalRun(
            arm, self.settings, self.busy_timeout, self._outcome)

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
    def heartbeat(self) -> Optional[float]:
        return self.settings.heartbeat

    @property
    def sent(self) -> int:
        """Set-points sent so far."""
        return self._run.sent

    @property
    def realtime(self) -> bool:
        """Whether the control loop got real-time scheduling (False until it runs)."""
        return self._run.realtime

    @property
    def result(self) -> Result:
        """How the run ended (``OK`` while it goes)."""
        return self._outcome.result

    @property
    def message(self) -> str:
        return self._outcome.message

    @property
    def dropped(self) -> int:
        """Feedback records that fell out of the queue."""
        return self._outcome.dropped

    # ------------------------------------------------------------------ caller side
    def push(self, times, poses) -> None:
        """Append samples: ``times`` ``(N,)`` seconds on the plan's clock, strictly increasing
        and after every sample pushed before; ``poses`` ``(N, 8)`` unit dual quaternions
        ``T_base_tool``. The first push starts the run: it waits for the arm's previous run to
        end (``busy_timeout``, else ``ArmError("busy ...")``), then checks that the plan starts
        at the arm's actual pose (``ValueError`` naming the distance and the tolerance). For an
        arm in its own process, a push waits while the ring in shared memory is full."""
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
                self._check_open("push")
                tail, t0, k0 = self._tail, self._t0, self._next_slot
            if tail is not None and t[0] <= tail[0]:
                raise ValueError(f"times[0]: {float(t[0])!r} is not after the last pushed time "
                                 f"{tail[0]!r}")
            first = t0 is None
            if first:
                t0 = self._outcome.t0 = float(t[0])
            slots = self._resample(t0, k0, tail, t, p)
            if first:
                self._run.start(slots)
            else:
                self._run.put(slots)
            with self._cond:
                self._t0 = t0
                self._tail = (float(t[-1]), p[-1])
                self._next_slot = k0 + len(slots)
            self._started = True

    def push_plan(self, trajectory) -> None:
        """The whole plan at once: ``trajectory`` is a :class:`dqpose.trajectory.Trajectory`
        (anything with ``duration`` and ``sample(times)``), sampled by the control loop at the
        arm's period as it goes, from its time 0 (never held whole, here or in an arm's
        process, which gets the trajectory itself: its waypoints). Starts the run as the first
        :meth:`push` does (its start checked against the arm's actual pose before anything else
        is sampled: ``ValueError`` naming ``poses[0]``) and finishes the input."""
        duration = getattr(trajectory, "duration", None)
        if not (callable(getattr(trajectory, "sample", None)) and isinstance(
                duration, numbers.Real) and math.isfinite(duration) and duration >= 0):
            raise ValueError(f"trajectory: expected a dqpose.trajectory.Trajectory, got "
                             f"{type(trajectory).__name__}")
        with self._push_lock:
            with self._cond:
                self._check_open("push_plan")
                if self._t0 is not None:
                    raise ValueError("push_plan: samples were already pushed to this executor")
            self._outcome.t0 = 0.0
            self._run.start_plan(trajectory)
            with self._cond:
                self._t0 = 0.0
                self._finished_input = True
            self._started = True

    def _check_open(self, what: str) -> None:
        if self._finished_input or self._outcome.done.is_set():
            raise ValueError(f"{what}: the plan was already finished or the run has ended "
                             f"({self.result.name})")

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
        with self._push_lock:
            with self._cond:
                if self._t0 is None:
                    raise ValueError("finish: no samples were pushed")
                if self._finished_input:
                    return
                last_slot = self._t0 + self.period * (self._next_slot - 1)
                slot = (self._t0 + self.period * self._next_slot, self._tail[1]) \
                    if self._tail[0] - last_slot > 1e-9 else None
            if slot is not None:
                self._run.put([slot])
                with self._cond:
                    self._next_slot += 1
            with self._cond:
                self._finished_input = True
            self._run.finish()

    def beat(self) -> None:
        """The owner is alive: call at least every ``heartbeat`` seconds while the run goes
        (cheap: a clock reading, in an arm's process one shared-memory write)."""
        self._run.beat(time.monotonic())

    def halt(self, reason: str) -> None:
        """Brake the arm to rest within its limits (as a stall does) and end the run ``STOPPED``,
        its message ``reason`` and how the arm was stopped (a server shutting down). A run not
        started yet ends without moving."""
        if not self.done:
            self._run.halt(str(reason) or "halted")

    def cancel(self) -> None:
        """Stop the arm (``arm.stop()``) at once, within the period under way; the run ends
        ``STOPPED``."""
        if not self.done:
            self._run.cancel()

    def wait(self, timeout: Optional[float] = None) -> Optional[Result]:
        """The final result once the run ended, else None after ``timeout`` seconds."""
        return self.result if self._outcome.done.wait(timeout) else None

    @property
    def done(self) -> bool:
        return self._outcome.done.is_set()

    @property
    def buffered(self) -> float:
        """Seconds of the plan buffered (or, of a whole plan, left) and not yet sent."""
        return self._run.buffered() * self.period

    def feedback(self, timeout: Optional[float] = None) -> Optional[Feedback]:
        """The oldest unread record (without a ``callback``), waiting up to ``timeout`` s;
        None when there is none (and, once the run ended, none will come)."""
        return self._outcome.next(timeout)

    def close(self) -> None:
        """Cancel a run still going and wait for its end."""
        if self._started and not self.done:
            self.cancel()
            self._outcome.done.wait()
        self._run.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
