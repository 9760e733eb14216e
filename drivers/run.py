"""A run of the control loop (:class:`~dqpose.drivers.control.Control`) as its owner, an
:class:`~dqpose.drivers.executor.Executor`, drives it: the :class:`Run` interface, the
:class:`Outcome` a run reports to, and :class:`LocalRun`, a run whose loop is a thread of this
process.

Where a run's loop goes is the arm's to say, once, when an executor is made on it
(:meth:`Arm.open_run <dqpose.drivers.base.Arm.open_run>`): an arm in its own process runs it
there (:class:`dqpose.drivers.armrun.RingRun`), any other arm in a thread here. A run holds no
reference to its executor: what it reports goes to the :class:`Outcome` both hold.
"""
from __future__ import annotations

import abc
import collections
import threading
import time
from typing import Callable, Optional

import numpy as np

from dqpose.drivers.base import Arm
from dqpose.drivers.control import (
    Buffer,
    Control,
    Feedback,
    PlanSlots,
    Result,
    Settings,
    check_start,
    claim,
    plan_start,
)

__all__ = ["Run", "Outcome", "LocalRun"]

#: a run's set-points: (plan time, pose) one period apart
Slots = list[tuple[float, np.ndarray]]


class Outcome:
    """What a run reports to its owner: its feedback records, to ``callback`` (called on a thread
    of the run's) or else to a queue of at most ``max_feedback`` (:meth:`next`; ``dropped``
    counts the records that fell out of it), and its end, :meth:`ended`: ``result``, ``message``,
    then ``done``."""

    def __init__(self, callback: Optional[Callable[[Feedback], None]], max_feedback: int):
        self._callback = callback
        self._cond = threading.Condition()
        self._queue: collections.deque = collections.deque(maxlen=int(max_feedback))
        self.dropped = 0
        self.result = Result.OK
        self.message = ""
        #: the plan time of the run's first set-point: a last record that commanded nothing
        #: carries it
        self.t0: Optional[float] = None
        self.done = threading.Event()

    def emit(self, fb: Feedback) -> None:
        if self._callback is not None:
            self._callback(fb)
            return
        with self._cond:
            if len(self._queue) == self._queue.maxlen:
                self.dropped += 1
            self._queue.append(fb)
            self._cond.notify_all()

    def ended(self, last: Feedback) -> None:
        """The run's last record: its result is the run's."""
        if last.commanded is None and self.t0 is not None:
            last = Feedback(self.t0, last.stamp, None, last.actual, last.result, last.message)
        with self._cond:
            self.result, self.message = last.result, last.message
        self.emit(last)     # before done: a reader that sees the end has the last record queued
        self.done.set()
        with self._cond:
            self._cond.notify_all()

    def next(self, timeout: Optional[float]) -> Optional[Feedback]:
        """The oldest unread record, waiting up to ``timeout`` s; None when there is none (and,
        once the run ended, none will come)."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._queue or self.done.is_set(), timeout):
                return None
            return self._queue.popleft() if self._queue else None


class Run(abc.ABC):
    """One run of an arm's control loop, as its :class:`~dqpose.drivers.executor.Executor`
    drives it (made by :meth:`Arm.open_run <dqpose.drivers.base.Arm.open_run>` before anything
    is pushed). Its records, and its end, go to its :class:`Outcome`."""

    @abc.abstractmethod
    def start(self, slots: Slots) -> None:
        """The run, on its first ``slots``: the arm claimed for it (waiting ``busy_timeout`` s for
        a run still ending, else ``ArmError("busy ...")``), the first pose checked against the
        arm's actual pose (``ValueError``; the arm is not claimed then), the loop started."""

    @abc.abstractmethod
    def start_plan(self, trajectory) -> None:
        """The run on a whole plan, which the loop samples as it goes (its input finished),
        started as :meth:`start` starts one."""

    @abc.abstractmethod
    def put(self, slots: Slots) -> None:
        """More set-points, after those already put."""

    @abc.abstractmethod
    def finish(self) -> None:
        """No more set-points: the loop settles on the last one."""

    @abc.abstractmethod
    def beat(self, now: float) -> None:
        """The owner's heartbeat (``time.monotonic()``)."""

    @abc.abstractmethod
    def halt(self, reason: str) -> None:
        """Brake to rest and end ``STOPPED`` with ``reason`` (the first reason given stays)."""

    @abc.abstractmethod
    def cancel(self) -> None:
        """Stop the arm at once and end ``STOPPED``."""

    @abc.abstractmethod
    def buffered(self) -> int:
        """Set-points buffered (of a whole plan, left) and not yet sent."""

    @property
    @abc.abstractmethod
    def sent(self) -> int:
        """Set-points sent so far."""

    @property
    @abc.abstractmethod
    def realtime(self) -> bool:
        """Whether the loop got real-time scheduling (False until it runs)."""

    def close(self) -> None:  # noqa: B027 (a run with nothing to release keeps it)
        """Release what the run holds, once it has ended."""


class LocalRun(Run):
    """A run whose loop is a thread of this process, fed from a deque (or sampling its plan)."""

    def __init__(self, arm: Arm, settings: Settings, busy_timeout: float, outcome: Outcome):
        self.arm, self.settings, self.outcome = arm, settings, outcome
        self.busy_timeout = busy_timeout
        self._cond = threading.Condition()      # the slots and the signals
        self._slots: collections.deque = collections.deque()
        self._plan: Optional[PlanSlots] = None
        self._finished = False
        self._cancelled = threading.Event()
        self._halt: Optional[str] = None
        self._beat = time.monotonic()
        self._sent = 0
        self._realtime = False
        self._lock: Optional[threading.Lock] = None     # the arm's, while the run has it

    def _claim(self, first: np.ndarray) -> None:
        """This arm for this run, and the plan's start checked against where it is once ours."""
        lock = claim(self.arm, self.busy_timeout)
        try:
            check_start(self.arm, first, self.settings.start_tolerance)
        except BaseException:
            lock.release()
            raise
        self._lock = lock

    def _go(self) -> None:
        self._beat = time.monotonic()
        threading.Thread(target=self._loop, name="executor", daemon=True).start()

    def start(self, slots: Slots) -> None:
        self._claim(slots[0][1])
        self.put(slots)
        self._go()

    def start_plan(self, trajectory) -> None:
        self._claim(plan_start(trajectory))
        with self._cond:
            self._plan = PlanSlots(trajectory, self.settings.period)
            self._finished = True
        self._go()

    def put(self, slots: Slots) -> None:
        with self._cond:
            self._slots.extend(slots)
            self._cond.notify_all()

    def finish(self) -> None:
        with self._cond:
            self._finished = True
            self._cond.notify_all()

    def beat(self, now: float) -> None:
        self._beat = now

    def halt(self, reason: str) -> None:
        with self._cond:
            if self._halt is None:
                self._halt = reason
            self._cond.notify_all()

    def cancel(self) -> None:
        self._cancelled.set()
        with self._cond:
            self._cond.notify_all()

    def buffered(self) -> int:
        if self._plan is not None:
            return self._plan.left()
        with self._cond:
            return len(self._slots)

    @property
    def sent(self) -> int:
        return self._sent

    @property
    def realtime(self) -> bool:
        return self._realtime

    def _loop(self) -> None:
        try:
            last = Control(self.arm, self.settings, _LocalBuffer(self)).run()
        finally:
            if self._lock is not None:
                self._lock.release()    # the arm is free before the end is announced
        self.outcome.ended(last)


class _LocalBuffer(Buffer):
    """A :class:`LocalRun` as its loop reads it. Made by the loop's thread and dropped with it."""

    def __init__(self, run: LocalRun):
        self.run = run

    @property
    def realtime(self):
        return self.run._realtime

    @realtime.setter
    def realtime(self, on):
        self.run._realtime = on

    def ready(self, need, timeout):
        run = self.run
        with run._cond:
            return run._cond.wait_for(lambda: len(run._slots) >= need or run._finished
                                      or run._cancelled.is_set() or run._halt is not None,
                                      timeout)

    def first(self):
        run = self.run
        if run._plan is not None:
            return run._plan.first()
        with run._cond:
            return run._slots[0][1] if run._slots else None

    def pop(self):
        run = self.run
        if run._plan is not None:
            return run._plan.pop()
        with run._cond:
            return run._slots.popleft() if run._slots else None

    def finished(self):
        return self.run._finished

    def cancelled(self):
        return self.run._cancelled.is_set()

    def halted(self):
        return self.run._halt

    def beat_age(self):
        return time.monotonic() - self.run._beat

    def wait(self, end):
        self.run._cancelled.wait(max(0.0, end - time.monotonic()))

    def sent(self, n):
        self.run._sent = n

    def emit(self, fb, final=False):
        self.run.outcome.emit(fb)
