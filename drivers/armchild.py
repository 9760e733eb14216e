"""What runs in an arm's own process (:mod:`dqpose.drivers.armproc`): :func:`child_main`
opens the arm, answers the owner's calls and starts a control loop per run; :class:`RingBuffer`
is the loop's :class:`~dqpose.drivers.control.Buffer` over the shared ring (or over a whole plan
the process samples itself), woken through a pipe.

The process dies with its owner, under control: when the owner's end of the command pipe closes
(the owner exited or was killed) or the process finds itself re-parented, a run still going is
treated as a dry buffer (decelerate within the Limits, then ``arm.stop()``, ``STALLED``) and the
arm is closed. An owner that stalls without dying leaves the ring dry: the same stop.
"""
from __future__ import annotations

import os
import pickle
import select
import signal
import threading
import time
from typing import Optional

from dqpose.drivers.armring import BEAT, CANCEL, FINISHED, HALT, READ, REALTIME, SENT, WRITTEN, Ring
from dqpose.drivers.base import ArmError
from dqpose.drivers.control import Buffer, Control, PlanSlots, check_start, claim

_SPIN = 0.0003              # s: how much of a period's end the loop spins rather than sleeps


class RingBuffer(Buffer):
    """The child's side of a run: pops the ring (or samples the plan), waits on the wake pipe
    (a cancel or a halt wakes it; end of file: the parent is gone) and on ``gone`` (the child's
    own pipe, written when the child finds the parent gone); the signals themselves are in the
    ring's header."""

    def __init__(self, ring: Ring, run_id: int, wake, feedback, gone: int,
                 plan: Optional[PlanSlots] = None):
        self.ring, self.id, self.wake, self.fb = ring, run_id, wake, feedback
        self.plan = plan
        if plan is not None:
            ring.head[WRITTEN] = plan.count
            ring.head[FINISHED] = 1
        self._fds = [wake.fileno(), gone]
        self._gone_fd = gone
        self._gone = False
        self.dropped = 0

    @property
    def realtime(self):
        return bool(self.ring.head[REALTIME])

    @realtime.setter
    def realtime(self, on):
        self.ring.head[REALTIME] = int(on)

    def _select(self, timeout: float) -> None:
        ready, _, _ = select.select(self._fds, [], [], max(timeout, 0.0))
        for fd in ready:
            if fd == self._gone_fd:
                self._gone = True
                self._fds.remove(fd)
                continue
            try:
                self.wake.recv_bytes()      # a wake-up: the header says what for
            except (EOFError, OSError):
                self._gone = True
                self._fds.remove(fd)

    def ready(self, need, timeout):
        deadline = time.monotonic() + timeout
        head = self.ring.head
        while not (head[WRITTEN] - head[READ] >= need or head[FINISHED] or self.cancelled()
                   or head[HALT] or self._gone):
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            self._select(min(left, 0.002))
        return True

    def first(self):
        if self.plan is not None:
            return self.plan.first()
        head = self.ring.head
        r = int(head[READ])
        return self.ring.slots[r % self.ring.capacity, 1:].copy() if r < head[WRITTEN] else None

    def pop(self):
        head = self.ring.head
        if self.plan is not None:
            slot = self.plan.pop()
            head[READ] = self.plan.taken
            return slot
        r = int(head[READ])
        if r >= head[WRITTEN]:
            return None
        row = self.ring.slots[r % self.ring.capacity].copy()
        head[READ] = r + 1
        return float(row[0]), row[1:]

    def finished(self):
        return bool(self.ring.head[FINISHED])

    def cancelled(self):
        return bool(self.ring.head[CANCEL])

    def halted(self):
        return self.ring.halted()

    def beat_age(self):
        return time.monotonic() - int(self.ring.head[BEAT]) * 1e-9

    def gone(self):
        return self._gone

    def wait(self, end):
        head = self.ring.head
        while not self.cancelled():
            left = end - time.monotonic()
            if left <= _SPIN:
                # the last stretch spinning, as waitPeriod does: a sleeping (virtual) CPU wakes
                # late; a cancel still ends it (the flag is set before the wake is sent)
                while time.monotonic() < end and not head[CANCEL]:
                    pass
                return
            if not self._fds:           # nothing left to wake us: the period's end
                time.sleep(left - _SPIN)
                continue
            self._select(left - _SPIN)

    def sent(self, n):
        self.ring.head[SENT] = n

    def emit(self, fb, final=False):
        data = pickle.dumps((self.id, fb.time, fb.stamp,
                             None if fb.commanded is None else fb.commanded.tolist(),
                             None if fb.actual is None else fb.actual.tolist(),
                             int(fb.result), fb.message))
        deadline = time.monotonic() + 2.0
        while True:
            try:
                self.fb.send_bytes(data)    # one write below PIPE_BUF: all of it or nothing
                return
            except BlockingIOError:
                if not final or time.monotonic() > deadline:
                    self.dropped += 1
                    return
                time.sleep(0.01)        # the last record is worth waiting for a while
            except OSError:
                return                  # the parent is gone


def _picklable(e: BaseException) -> BaseException:
    try:
        pickle.loads(pickle.dumps(e))
        return e
    except Exception:
        return ArmError(f"{type(e).__name__}: {e}")


def _control(arm, settings, buf: RingBuffer, lock: threading.Lock) -> None:
    try:
        try:
            last = Control(arm, settings, buf).run()
        finally:
            lock.release()              # the arm is free before the end is announced
        buf.emit(last, final=True)
    finally:
        buf.ring.close()


def start_control(arm, args, wake, feedback, gone: int) -> threading.Thread:
    """A run's control loop on its own thread, once the arm is free (waiting for a run still
    ending, else ``ArmError("busy ...")``) and the plan starts where the arm is (else the
    ``ValueError``): both answered to the parent's request."""
    run_id, settings, name, capacity, trajectory, busy_timeout = args
    lock = claim(arm, busy_timeout)
    ring = None
    try:
        ring = Ring(capacity, name)
        plan = None if trajectory is None else PlanSlots(trajectory, settings.period)
        buf = RingBuffer(ring, run_id, wake, feedback, gone, plan)
        check_start(arm, buf.first(), settings.start_tolerance)
    except BaseException:
        if ring is not None:
            ring.close()
        lock.release()
        raise
    control = threading.Thread(target=_control, args=(arm, settings, buf, lock),
                               name="control", daemon=True)
    control.start()
    return control


def child_main(spec: str, kwargs: dict, conn, wake, feedback, parent: int) -> None:
    """The arm's process: opens the arm, answers calls, runs control loops; ends (braking a run
    still going, closing the arm) when the parent closes the pipe, dies or asks."""
    # A Ctrl-C, and a SIGTERM sent to the whole process group (systemd's stop, a terminal's
    # hang-up aside), are the parent's to handle: it brings a run to a controlled stop and then
    # closes this process. Killed by it first, the arm would get no stop at all. A parent that
    # is gone is noticed here all the same (a dry ring, a closed pipe, re-parenting).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    from dqpose.drivers.spec import open_here
    try:
        arm = open_here(spec, **kwargs)
    except BaseException as e:
        conn.send(("error", _picklable(e)))
        return
    conn.send(("ok", {"period": arm.period, "limits": arm.limits, "name": arm.name,
                      "pose_sigma": arm.pose_sigma, "options": arm.options}))
    os.set_blocking(feedback.fileno(), False)
    gone_r, gone_w = os.pipe()
    controls: list[threading.Thread] = []
    try:
        while True:
            if not conn.poll(0.1):
                if os.getppid() != parent:
                    return
                continue
            try:
                op, *args = conn.recv()
            except (EOFError, OSError):
                return
            try:
                if op == "call":
                    name, a, kw = args
                    value = getattr(arm, name)(*a, **kw)
                elif op == "attr":
                    v = getattr(arm, args[0])
                    value = ("method", None) if callable(v) else ("value", v)
                elif op == "run":
                    controls = [c for c in controls if c.is_alive()]
                    controls.append(start_control(arm, args, wake, feedback, gone_r))
                    value = None
                elif op == "close":
                    conn.send(("ok", None))
                    return
                else:
                    raise ValueError(f"op: unknown {op!r}")
            except BaseException as e:
                conn.send(("error", _picklable(e)))
                continue
            conn.send(("ok", value))
    finally:
        os.write(gone_w, b"x")          # a run still going brakes to a stop
        for c in controls:
            c.join()
        arm.close()
