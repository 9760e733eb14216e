"""An arm in its own process: :class:`ArmProcess`, what ``drivers.open_arm(spec, process=True)``
returns.

The child process opens the backend by name (``drivers.open_arm(spec)``, so its connection, its
threads and its Limits are the backend's own) and does two things: it answers the calls of the
:class:`~drivers.base.Arm` interface made on the proxy in the parent (``tool_pose``, ``move``,
``stop``, ``status``, and any other public attribute, e.g. ``URArm.recover``), and it runs an
:class:`~drivers.executor.Executor`'s control loop, the same :class:`~drivers.executor._Control`
a thread runs, on set-points the parent writes into a ring in shared memory. The parent keeps the
``Executor`` API: ``push`` resamples and writes the ring, ``cancel`` raises a flag and wakes the
loop through a pipe, feedback comes back through another pipe (written without blocking: a
parent that stops reading loses records, never a set-point).

Why a process: a set-point is due every 2 ms at 500 Hz, and a control thread that shares its
interpreter with gRPC, a feeder or a large heap's garbage collector waits for the interpreter
lock after each wait (BENCHMARKS.md "Issue 10: execution in its own process").

The child dies with the parent, under control: when the parent's end of the command pipe closes
(the parent exited or was killed) or the child finds itself re-parented, a run still going is
treated as a dry buffer (decelerate within the Limits, then ``arm.stop()``, ``STALLED``) and the
arm is closed. A parent that stalls without dying leaves the ring dry: the same stop. The ring
is one writer (the parent), one reader (the child); a slot is written before the count that
publishes it, which x86-64's store order keeps in order. Other processors (aarch64) may make the
count visible before the slot, so there the arm process is refused and the loop runs in a thread.
"""
from __future__ import annotations

import atexit
import itertools
import mmap
import multiprocessing as mp
import os
import pickle
import platform
import select
import signal
import struct
import threading
import time
import weakref
from multiprocessing import shared_memory
from typing import Optional

import numpy as np

from drivers.base import Arm, ArmError, ArmState
from drivers.control import Buffer, Control, Feedback, PlanSlots, Result, check_start, claim

__all__ = ["ArmProcess"]

# ring header, one int64 each: slots written and read (of a plan: its slots and those taken),
# input finished, cancel, set-points sent, real-time, the last heartbeat (CLOCK_MONOTONIC ns),
# halt (the reason's length + 1, the reason in the bytes after the header)
_WRITTEN, _READ, _FINISHED, _CANCEL, _SENT, _REALTIME, _BEAT, _HALT = range(8)
_HEADER = 8
_REASON = 512               # bytes of a halt's reason
_SLOT = 9                   # plan time, then the pose
_ID = struct.Struct("<q")   # a run's id on the wake pipe
_SPIN = 0.0003              # s: how much of a period's end the loop spins rather than sleeps
# processors whose store order keeps the ring's slot-then-count writes in order (TSO)
_TSO = {"x86_64", "amd64", "i386", "i686"}


def check_store_order(machine: Optional[str] = None) -> None:
    """ArmError unless this processor keeps stores in order, as the ring needs."""
    machine = (machine if machine is not None else platform.machine()).lower()
    if machine not in _TSO:
        raise ArmError(f"process: an arm in its own process needs x86-64's store order for its "
                       f"set-point ring; this is {machine or 'an unknown processor'}: run the "
                       f"control loop in a thread (open_arm(spec), without process=True)")


class _Ring:
    """A run's counters and signals and its set-points (plan time + pose; none for a whole
    plan, which the child samples itself), in shared memory: made by the parent (``name``
    None), which alone unlinks it; mapped by name in the child, outside ``multiprocessing``'s
    resource tracker (whose register from the child could come after the parent's unregister
    and count the ring as leaked)."""

    def __init__(self, capacity: int, name: Optional[str] = None):
        self.capacity = int(capacity)
        size = 8 * _HEADER + _REASON + 8 * _SLOT * self.capacity
        if name is None:
            self.shm = shared_memory.SharedMemory(create=True, size=size)
            self.name, buf = self.shm.name, self.shm.buf
        else:
            import _posixshmem
            self.shm, self.name = None, name
            fd = _posixshmem.shm_open("/" + name, os.O_RDWR, mode=0o600)
            try:
                self._map = mmap.mmap(fd, size)
            finally:
                os.close(fd)
            buf = memoryview(self._map)
        self.head = np.ndarray((_HEADER,), np.int64, buf)
        self.reason = np.ndarray((_REASON,), np.uint8, buf, offset=8 * _HEADER)
        self.slots = np.ndarray((self.capacity, _SLOT), np.float64, buf,
                                offset=8 * _HEADER + _REASON)
        if name is None:
            self.head[:] = 0

    def halt(self, reason: str) -> None:
        """The reason, then the flag that publishes it (the parent's side)."""
        data = reason.encode("utf-8")[:_REASON].decode("utf-8", "ignore").encode("utf-8")
        self.reason[:len(data)] = np.frombuffer(data, np.uint8)
        self.head[_HALT] = len(data) + 1

    def halted(self) -> Optional[str]:
        n = int(self.head[_HALT])
        return self.reason[:n - 1].tobytes().decode("utf-8") if n else None

    def close(self) -> None:
        """Unmap it; the parent also unlinks it."""
        del self.head, self.slots, self.reason      # no view may outlive the mapping
        if self.shm is None:
            self._map.close()
            return
        self.shm.close()
        self.shm.unlink()


class _RingBuffer(Buffer):
    """The child's side of a run: pops the ring (or samples the plan), waits on the wake pipe
    (a cancel or a halt wakes it; end of file: the parent is gone) and on ``gone`` (the child's
    own pipe, written when the child finds the parent gone); the signals themselves are in the
    ring's header."""

    def __init__(self, ring: _Ring, run_id: int, wake, feedback, gone: int,
                 plan: Optional[PlanSlots] = None):
        self.ring, self.id, self.wake, self.fb = ring, run_id, wake, feedback
        self.plan = plan
        if plan is not None:
            ring.head[_WRITTEN] = plan.count
            ring.head[_FINISHED] = 1
        self._fds = [wake.fileno(), gone]
        self._gone_fd = gone
        self._gone = False
        self.dropped = 0

    @property
    def realtime(self):
        return bool(self.ring.head[_REALTIME])

    @realtime.setter
    def realtime(self, on):
        self.ring.head[_REALTIME] = int(on)

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
        while not (head[_WRITTEN] - head[_READ] >= need or head[_FINISHED] or self.cancelled()
                   or head[_HALT] or self._gone):
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            self._select(min(left, 0.002))
        return True

    def first(self):
        if self.plan is not None:
            return self.plan.first()
        head = self.ring.head
        r = int(head[_READ])
        return self.ring.slots[r % self.ring.capacity, 1:].copy() if r < head[_WRITTEN] else None

    def pop(self):
        head = self.ring.head
        if self.plan is not None:
            slot = self.plan.pop()
            head[_READ] = self.plan.taken
            return slot
        r = int(head[_READ])
        if r >= head[_WRITTEN]:
            return None
        row = self.ring.slots[r % self.ring.capacity].copy()
        head[_READ] = r + 1
        return float(row[0]), row[1:]

    def finished(self):
        return bool(self.ring.head[_FINISHED])

    def cancelled(self):
        return bool(self.ring.head[_CANCEL])

    def halted(self):
        return self.ring.halted()

    def beat_age(self):
        return time.monotonic() - int(self.ring.head[_BEAT]) * 1e-9

    def gone(self):
        return self._gone

    def wait(self, end):
        head = self.ring.head
        while not self.cancelled():
            left = end - time.monotonic()
            if left <= _SPIN:
                # the last stretch spinning, as waitPeriod does: a sleeping (virtual) CPU wakes
                # late; a cancel still ends it (the flag is set before the wake is sent)
                while time.monotonic() < end and not head[_CANCEL]:
                    pass
                return
            if not self._fds:           # nothing left to wake us: the period's end
                time.sleep(left - _SPIN)
                continue
            self._select(left - _SPIN)

    def sent(self, n):
        self.ring.head[_SENT] = n

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


def _control(arm, settings, buf: _RingBuffer, lock: threading.Lock) -> None:
    try:
        try:
            last = Control(arm, settings, buf).run()
        finally:
            lock.release()              # the arm is free before the end is announced
        buf.emit(last, final=True)
    finally:
        buf.ring.close()


def _start_control(arm, args, wake, feedback, gone: int) -> threading.Thread:
    """A run's control loop on its own thread, once the arm is free (waiting for a run still
    ending, else ``ArmError("busy ...")``) and the plan starts where the arm is (else the
    ``ValueError``): both answered to the parent's request."""
    run_id, settings, name, capacity, trajectory, busy_timeout = args
    lock = claim(arm, busy_timeout)
    ring = None
    try:
        ring = _Ring(capacity, name)
        plan = None if trajectory is None else PlanSlots(trajectory, settings.period)
        buf = _RingBuffer(ring, run_id, wake, feedback, gone, plan)
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


def _child(spec: str, kwargs: dict, conn, wake, feedback, parent: int) -> None:
    """The arm's process: opens the arm, answers calls, runs control loops; ends (braking a run
    still going, closing the arm) when the parent closes the pipe, dies or asks."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)   # a Ctrl-C is the parent's to handle
    from drivers import open_arm
    try:
        arm = open_arm(spec, **kwargs)
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
                    controls.append(_start_control(arm, args, wake, feedback, gone_r))
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


class _Run:
    """The parent's side of one run (what :class:`~drivers.executor.Executor` calls)."""

    def __init__(self, proc: "ArmProcess", ex, run_id: int):
        # the executor holds this run; this run holds it weakly (no cycle: see _DequeBuffer),
        # and the arm process strongly while the run goes
        self.proc, self._ex, self.id = proc, weakref.ref(ex), run_id
        self.ring: Optional[_Ring] = None
        self._lock = threading.Lock()
        self._final = None          # (sent, realtime, 0) once the ring is released
        self._beat = time.monotonic()
        self._halt: Optional[str] = None
        self._cancel = False

    def _make_ring(self, capacity: int) -> None:
        """The ring, with the signals that came before it (under ``_lock``)."""
        if self._final is not None:
            raise ValueError("push: the run has ended")
        if self.ring is None:
            self.ring = _Ring(capacity)
            self.ring.head[_BEAT] = int(self._beat * 1e9)
            self.ring.head[_CANCEL] = int(self._cancel)
            if self._halt is not None:
                self.ring.halt(self._halt)

    def put(self, slots) -> None:
        if not slots:
            return
        with self._lock:
            self._make_ring(max(self.proc.ring_slots, 2 * len(slots)))
        i = 0
        while i < len(slots):
            with self._lock:
                if self._final is not None:
                    raise ValueError("push: the run has ended")
                head, cap = self.ring.head, self.ring.capacity
                w = int(head[_WRITTEN])
                n = min(len(slots) - i, cap - (w - int(head[_READ])))
                if n > 0:
                    rows = np.array([[t, *p] for t, p in slots[i:i + n]])
                    idx = (w + np.arange(n)) % cap
                    self.ring.slots[idx] = rows
                    head[_WRITTEN] = w + n      # after the slots: publishes them
                    i += n
                    continue
            time.sleep(self.ex.period)       # full: the arm makes room, a period a slot

    @property
    def ex(self):
        return self._ex()

    def start(self, trajectory=None) -> None:
        """The run in the child (which waits for the arm and checks the start): on the ring's
        slots, or on ``trajectory``, which the child samples itself (then the ring holds only
        the counters and signals). A refused start frees the ring."""
        ex = self.ex
        with self._lock:
            if trajectory is not None:
                self._make_ring(0)
            self._beat = time.monotonic()
            self.ring.head[_BEAT] = int(self._beat * 1e9)
        self.proc._runs[self.id] = (self, ex)
        try:
            self.proc._request("run", self.id, ex.settings, self.ring.name, self.ring.capacity,
                               trajectory, ex.busy_timeout)
        except BaseException:
            self.proc._runs.pop(self.id, None)
            self.release()
            raise

    def start_plan(self, trajectory) -> None:
        self.start(trajectory)

    def finish(self) -> None:
        with self._lock:
            if self.ring is not None and self._final is None:
                self.ring.head[_FINISHED] = 1

    def beat(self, now: float) -> None:
        with self._lock:
            self._beat = now
            if self.ring is not None and self._final is None:
                self.ring.head[_BEAT] = int(now * 1e9)

    def _signal(self, set_flag) -> None:
        with self._lock:
            if self._final is not None:
                return
            set_flag()
            if self.ring is None:
                return
        try:
            self.proc._wake.send_bytes(_ID.pack(self.id))
        except OSError:
            pass    # the child is gone; the reader reports it

    def halt(self, reason: str) -> None:
        def flag():
            if self._halt is None:
                self._halt = reason
                if self.ring is not None:
                    self.ring.halt(reason)
        self._signal(flag)

    def cancel(self) -> None:
        def flag():
            self._cancel = True
            if self.ring is not None:
                self.ring.head[_CANCEL] = 1
        self._signal(flag)

    def _count(self, k: int) -> int:
        with self._lock:
            if self._final is not None:
                return self._final[k]
            if self.ring is None:
                return 0
            h = self.ring.head
            return (int(h[_SENT]), int(h[_REALTIME]), int(h[_WRITTEN] - h[_READ]))[k]

    def sent_count(self) -> int:
        return self._count(0)

    @property
    def realtime(self) -> bool:
        return bool(self._count(1))

    def buffered(self) -> int:
        return self._count(2)

    def release(self) -> None:
        """The run has ended: keep the counters, free the ring."""
        with self._lock:
            if self._final is not None or self.ring is None:
                self._final = self._final or (0, 0, 0)
                return
            h = self.ring.head
            self._final = (int(h[_SENT]), int(h[_REALTIME]), 0)
            self.ring.close()
            self.ring = None

    def close(self) -> None:
        self.release()


def _close_at_exit(ref) -> None:
    proc = ref()
    if proc is not None:
        proc.close()


class ArmProcess(Arm):
    """``drivers.open_arm(spec, **kwargs)`` run in a child process; this object is the
    :class:`~drivers.base.Arm` in the parent. ``period``, ``limits``, ``name``, ``pose_sigma`` and
    ``options`` (with an attribute per key) are the child arm's; other attributes are read from it, methods called in it. An
    :class:`~drivers.executor.Executor` on this arm runs its control loop in the child.
    ``ring_seconds``: the shared ring's size in seconds of set-points (a push beyond it waits for
    the arm; a first push longer than it sizes the ring). ``pid``: the child's."""

    def __init__(self, spec: str, *, ring_seconds: float = 120.0, start_timeout: float = 60.0,
                 **kwargs):
        check_store_order()
        ctx = mp.get_context("spawn")   # a fork would copy this process's threads' state
        self._conn, child_conn = ctx.Pipe()
        wake_r, self._wake = ctx.Pipe(duplex=False)
        self._fb, fb_w = ctx.Pipe(duplex=False)
        self.spec = spec
        self.process = ctx.Process(target=_child, name=f"arm {spec}", daemon=False,
                                   args=(spec, kwargs, child_conn, wake_r, fb_w, os.getpid()))
        self.process.start()
        for c in (child_conn, wake_r, fb_w):
            c.close()
        self.pid = self.process.pid
        self._lock = threading.Lock()
        self._closed = False
        self._runs: dict[int, _Run] = {}
        self._ids = itertools.count(1)
        if not self._conn.poll(start_timeout):
            self.process.kill()
            raise ArmError(f"arm: {spec!r} did not open within {start_timeout:g} s in its process")
        try:
            status, info = self._conn.recv()
        except EOFError:
            self.process.join()
            raise ArmError(f"arm: the process for {spec!r} ended while opening it (exit code "
                           f"{self.process.exitcode})") from None
        if status == "error":
            self.process.join()
            raise info
        self.period, self.limits = info["period"], info["limits"]
        self.name, self.pose_sigma = info["name"], info["pose_sigma"]
        self.options = info["options"]
        for key, value in self.options.items():
            setattr(self, key, value)
        self.ring_slots = max(1, int(round(ring_seconds / self.period)))
        self._reader = threading.Thread(target=self._read_feedback, name=f"arm {spec} feedback",
                                        daemon=True)
        self._reader.start()
        atexit.register(_close_at_exit, weakref.ref(self))

    def _request(self, op: str, *args):
        with self._lock:
            if self._closed:
                raise ArmError("arm: closed")
            try:
                self._conn.send((op, *args))
                status, value = self._conn.recv()
            except (EOFError, OSError):
                raise ArmError(f"arm: the process of {self.spec!r} is gone (exit code "
                               f"{self.process.exitcode})") from None
        if status == "error":
            raise value
        return value

    def call(self, name: str, *args, **kwargs):
        """The child arm's method ``name`` with these arguments; its result."""
        return self._request("call", name, args, kwargs)

    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)
        kind, value = self._request("attr", name)
        if kind == "value":
            return value
        return lambda *a, **kw: self.call(name, *a, **kw)

    def _read_feedback(self) -> None:
        while True:
            try:
                data = self._fb.recv_bytes()
            except (EOFError, OSError):
                break
            rid, t, stamp, cmd, act, res, msg = pickle.loads(data)
            run, ex = self._runs.get(rid, (None, None))
            if run is None:
                continue
            fb = Feedback(t, stamp, None if cmd is None else np.asarray(cmd),
                          None if act is None else np.asarray(act), Result(res), msg)
            if fb.result == Result.OK:
                ex._emit(fb)
                continue
            self._runs.pop(rid, None)
            run.release()
            ex._ended(fb)
        for rid in list(self._runs):     # the child died without a last word
            run, ex = self._runs.pop(rid)
            run.release()
            ex._ended(Feedback(float("nan"), time.time(), None, None, Result.ERROR,
                                   f"the arm's process ended (exit code "
                                   f"{self.process.exitcode}) before the run did"))

    def start_run(self, ex) -> _Run:
        """What an :class:`~drivers.executor.Executor` calls: its run in the child."""
        return _Run(self, ex, next(self._ids))

    # ------------------------------------------------------------------ the Arm interface
    def tool_pose(self):
        return self.call("tool_pose")

    def servo_nowait(self, pose) -> float:
        return self.call("servo_nowait", np.asarray(pose))

    def servo(self, pose) -> None:
        self.call("servo", np.asarray(pose))

    def move(self, pose, speed: float, accel: float) -> None:
        self.call("move", np.asarray(pose), speed, accel)

    def stop(self) -> None:
        self.call("stop")

    def status(self) -> ArmState:
        try:
            return self.call("status")
        except ArmError as e:
            return ArmState(connected=False, faults=(str(e),))

    def state(self) -> ArmState:
        try:
            return self.call("state")
        except ArmError as e:
            return ArmState(connected=False, faults=(str(e),))

    def velocity(self):
        return self.call("velocity")

    def close(self) -> None:
        """Close the arm in the child (a run still going brakes to a stop first) and end it."""
        if self._closed:
            return
        try:
            self._request("close")
        except ArmError:
            pass
        with self._lock:
            self._closed = True
        self.process.join(10.0)
        if self.process.is_alive():
            self.process.kill()
            self.process.join()
        for c in (self._conn, self._wake):
            c.close()
        self._reader.join(2.0)
        self._fb.close()
