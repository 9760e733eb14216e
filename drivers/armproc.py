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
lock after each wait (docs/benchmarks/arms.md#where-a-500-hz-loop-loses-its-cycles).

The child dies with the parent, under control: when the parent's end of the command pipe closes
(the parent exited or was killed) or the child finds itself re-parented, a run still going is
treated as a dry buffer (decelerate within the Limits, then ``arm.stop()``, ``STALLED``) and the
arm is closed. A parent that stalls without dying leaves the ring dry: the same stop. The ring
is one writer (the parent), one reader (the child); a slot is written before the count that
publishes it, which x86-64's store order keeps in order. Other processors (aarch64) may make the
count visible before the slot, so there the arm process is refused and the loop runs in a thread.

A child that dies unasked (a crash in the backend's library: ur_rtde's own reconnect can take the
process that writes servoL down) is replaced rather than leaving the arm dead until a restart:
the run it had ends ``ERROR`` saying how the process ended (``killed by SIGSEGV``; the
controller is left with the last set-point it got), its ring is unlinked and its pipes closed,
and the arm's next use opens the arm again in a new child (:class:`ArmProcess`).
"""
from __future__ import annotations

import atexit
import itertools
import json
import logging
import math
import mmap
import multiprocessing as mp
import numbers
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
from multiprocessing.connection import wait
from typing import Optional

import numpy as np

from dqpose.drivers.base import Arm, ArmError, ArmState
from dqpose.drivers.control import Buffer, Control, Feedback, PlanSlots, Result, check_start, claim

__all__ = ["ArmProcess"]

log = logging.getLogger("dqpose.drivers")

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
    # A Ctrl-C, and a SIGTERM sent to the whole process group (systemd's stop, a terminal's
    # hang-up aside), are the parent's to handle: it brings a run to a controlled stop and then
    # closes this process. Killed by it first, the arm would get no stop at all. A parent that
    # is gone is noticed here all the same (a dry ring, a closed pipe, re-parenting).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    from dqpose.drivers import open_arm
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
        self.child: Optional[_Child] = None     # the process it was handed to
        self.last: Optional[Feedback] = None    # its last record from there
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
        try:
            self.proc._request("run", self.id, ex.settings, self.ring.name, self.ring.capacity,
                               trajectory, ex.busy_timeout, run=(self, ex))
        except BaseException:
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
            child = self.child
            if self.ring is None or child is None:
                return      # (the process reads the flags when it starts the run)
        try:
            child.wake.send_bytes(_ID.pack(self.id))
        except OSError:
            pass    # the process is gone; its reader ends the run

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
        """The run has ended: keep the counters, free the ring (and let go of the process)."""
        with self._lock:
            self.child = None
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


def _how(exitcode: Optional[int]) -> str:
    """How a process ended, from its exit code (negative: the signal that killed it)."""
    if exitcode is None:
        return "exit code unknown"
    if exitcode < 0:
        try:
            return f"killed by {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"killed by signal {-exitcode}"
    return f"exit code {exitcode}"


def _end(run: _Run, ex, how: str) -> None:
    """A run whose process ended under it: ``ERROR``, where its last record had it."""
    run.release()
    last = run.last
    ex._ended(Feedback(0.0 if last is None else last.time, time.time(),
                       None if last is None else last.commanded,
                       None if last is None else last.actual, Result.ERROR,
                       f"the arm's process ended ({how}) before the run did; it is opened again "
                       f"on the arm's next use"))


#: what an arm's process reports once it has opened the arm: the same again when it is reopened
_FIXED = ("period", "limits", "name", "pose_sigma", "options")


def _same(a, b) -> bool:
    try:
        return bool(a == b)
    except ValueError:      # arrays inside (a Limits' box given as arrays): compared as data
        return pickle.dumps(a) == pickle.dumps(b)


class _Child:
    """One process of an :class:`ArmProcess`'s arm: the process, its pipes, the thread that reads
    its feedback, and the runs handed to it (run id -> [run, executor, accepted]). A run is
    accepted once the process has answered its start; until then the request that hands it
    over ends it if the process ends, from then on this reader does (with the process's final
    record, or ``ERROR`` when the process ends first)."""

    def __init__(self, ctx, spec: str, kwargs: dict, start_timeout: float):
        self.spec = spec
        self.conn, child_conn = ctx.Pipe()
        wake_r, self.wake = ctx.Pipe(duplex=False)
        self.fb, fb_w = ctx.Pipe(duplex=False)
        self.process = ctx.Process(target=_child, name=f"arm {spec}", daemon=False,
                                   args=(spec, kwargs, child_conn, wake_r, fb_w, os.getpid()))
        self.process.start()
        for c in (child_conn, wake_r, fb_w):
            c.close()
        self.pid = self.process.pid
        self.lock = threading.Lock()        # runs, dead
        self.runs: dict[int, list] = {}
        self.dead = False       # its feedback pipe closed: the process ended, and its runs
        self.lost = False       # a request found it gone (perhaps before the reader did)
        self._how: Optional[str] = None
        self._retired = False
        try:
            self.info = self._opened(start_timeout)
        except BaseException:
            for c in (self.conn, self.wake, self.fb):
                c.close()
            raise
        self._reader = threading.Thread(target=self._read, name=f"arm {spec} feedback",
                                        daemon=True)
        self._reader.start()

    def _opened(self, timeout: float) -> dict:
        """What the process reports once it has opened the arm, else the error saying why not."""
        if not self.conn.poll(timeout):
            self.process.kill()
            self.process.join()
            raise ArmError(f"arm: {self.spec!r} did not open within {timeout:g} s in its process")
        try:
            status, info = self.conn.recv()
        except EOFError:
            raise ArmError(f"arm: the process for {self.spec!r} ended while opening it "
                           f"({self.how()})") from None
        if status == "error":
            self.process.join()
            raise info
        return info

    @property
    def gone(self) -> bool:
        """Whether the process has ended (found so, or its sentinel says so: a request written
        to it now would be lost, yet might not fail while its pipes are being closed)."""
        if not (self.dead or self.lost) and wait([self.process.sentinel], 0):
            self.lost = True
        return self.dead or self.lost

    def how(self, timeout: float = 5.0) -> str:
        """How the process ended, once it has (one that has not within ``timeout`` s of being
        found gone answers no more: it is killed)."""
        if self._how is None:
            p = self.process
            if not wait([p.sentinel], timeout):
                p.kill()
                wait([p.sentinel])
            # another thread's waitpid (the reader's, multiprocessing's cleanup of finished
            # children) may be the one that reaps it: the exit code is set a moment later
            deadline = time.monotonic() + 1.0
            while p.exitcode is None and time.monotonic() < deadline:
                time.sleep(0.005)
            if p.exitcode is None:
                return _how(None)
            self._how = _how(p.exitcode)
        return self._how

    def adopt(self, run: _Run, ex) -> None:
        """A run about to be handed over; it starts with a fresh heartbeat (the owner may beat
        from the thread that hands it over, which opening the arm again may have held)."""
        with self.lock:
            self.runs[run.id] = [run, ex, False]
        run.child = self
        run.beat(time.monotonic())

    def take(self, rid: int) -> Optional[list]:
        with self.lock:
            return self.runs.pop(rid, None)

    def answered(self, rid: int, ok: bool) -> Optional[list]:
        """The process answered a run's start (``ok``, or refused it: no run, no records);
        the run if it is the caller's to end (the process ended before the reader owned it)."""
        with self.lock:
            entry = self.runs.get(rid)
            if entry is None:           # already ended: its final record came first
                return None
            if not ok or self.dead:
                del self.runs[rid]
                return entry if ok else None
            entry[2] = True
            return None

    def _read(self) -> None:
        """Feedback records to their runs' executors; once the process has ended, each run
        it had accepted and not ended ends ``ERROR`` saying how the process ended."""
        while True:
            try:
                data = self.fb.recv_bytes()
            except (EOFError, OSError):
                break
            rid, t, stamp, cmd, act, res, msg = pickle.loads(data)
            entry = self.runs.get(rid)
            if entry is None:
                continue
            run, ex = entry[0], entry[1]
            fb = Feedback(t, stamp, None if cmd is None else np.asarray(cmd),
                          None if act is None else np.asarray(act), Result(res), msg)
            if fb.result == Result.OK:
                run.last = fb
                ex._emit(fb)
            elif self.take(rid) is not None:
                run.release()
                ex._ended(fb)
        how = self.how()
        with self.lock:
            self.dead = True
            ended = [e for e in self.runs.values() if e[2]]
            for run, _, _ in ended:
                del self.runs[run.id]
        for run, ex, _ in ended:
            _end(run, ex, how)
        # the runs are released: no signal goes to this process's wake pipe any more
        self.wake.close()
        self.fb.close()

    def retire(self, timeout: float = 5.0) -> None:
        """Once the process has ended (killed if it has not within ``timeout`` s), its
        request pipe closed (the reader closes the others after ending its runs)."""
        if not self._retired:
            self._retired = True
            self.how(timeout)
            self.conn.close()

    def close(self) -> None:
        """The arm closed in the process (a run still going brakes to a stop first), and the
        process ended."""
        if not self.gone:
            try:
                self.conn.send(("close",))
                if self.conn.poll(10.0):
                    self.conn.recv()
            except (EOFError, OSError):
                pass
        self.retire(10.0)
        self._reader.join(2.0)


class ArmProcess(Arm):
    """``drivers.open_arm(spec, **kwargs)`` run in a child process; this object is the
    :class:`~drivers.base.Arm` in the parent. ``period``, ``limits``, ``name``, ``pose_sigma`` and
    ``options`` (with an attribute per key) are the child arm's; other attributes are read from
    it, methods called in it. An :class:`~drivers.executor.Executor` on this arm runs its control
    loop in the child. ``ring_seconds``: the shared ring's size in seconds of set-points (a push
    beyond it waits for the arm; a first push longer than it sizes the ring). ``process``,
    ``pid``: the child's.

    A child that ends unasked (a crash) is replaced: the run it had ends ``ERROR``, saying how
    the process ended, and the arm's next use (a call, :meth:`state`, a run) opens the arm again
    in a new child, with the same spec and keywords, at most once every ``reopen_every`` s (an
    attribute; a use before then, or after a reopen that failed, raises ``ArmError`` saying so
    and why). The new child must report the same ``period``, ``limits``, ``name``,
    ``pose_sigma`` and ``options`` (else it is closed and the reopen fails). Each reopen is
    logged on ``dqpose.drivers``."""

    def __init__(self, spec: str, *, ring_seconds: float = 120.0, start_timeout: float = 60.0,
                 reopen_every: float = 5.0, **kwargs):
        check_store_order()
        if isinstance(reopen_every, bool) or not (isinstance(reopen_every, numbers.Real)
                                                  and math.isfinite(reopen_every)
                                                  and reopen_every >= 0):
            raise ValueError(f"reopen_every: must be a finite number of seconds >= 0, got "
                             f"{reopen_every!r}")
        self.spec, self._kwargs = spec, kwargs
        self.start_timeout, self.reopen_every = float(start_timeout), float(reopen_every)
        self._ctx = mp.get_context("spawn")     # a fork would copy this process's threads' state
        self._lock = threading.Lock()           # one request at a time (a reopen within one)
        self._closed = False
        self._ids = itertools.count(1)
        self._reopened: Optional[float] = None  # when the last reopen was tried (monotonic)
        self._reopen_error: Optional[str] = None
        self._child = _Child(self._ctx, spec, kwargs, self.start_timeout)
        self._info = info = self._child.info
        self.period, self.limits = info["period"], info["limits"]
        self.name, self.pose_sigma = info["name"], info["pose_sigma"]
        self.options = info["options"]
        for key, value in self.options.items():
            setattr(self, key, value)
        self.ring_slots = max(1, int(round(ring_seconds / self.period)))
        atexit.register(_close_at_exit, weakref.ref(self))

    @property
    def process(self):
        """The arm's process (a ``multiprocessing`` process; a new one after a reopen)."""
        return self._child.process

    @property
    def pid(self) -> int:
        return self._child.pid

    def _live(self) -> _Child:
        """The arm's process, opened again if it has ended (see the class); under ``_lock``."""
        old = self._child
        if not old.gone:
            return old
        old.retire()
        ended = f"arm: the process of {self.spec!r} ended ({old.how()})"
        if self._reopened is not None:
            left = self._reopened + self.reopen_every - time.monotonic()
            if left > 0:
                failed = (f"; the last attempt failed: {self._reopen_error}"
                          if self._reopen_error else "")
                raise ArmError(f"{ended}; it is opened again at most once every "
                               f"{self.reopen_every:g} s, next in {left:.3g} s{failed}")
        new = error = None
        try:
            new = _Child(self._ctx, self.spec, self._kwargs, self.start_timeout)
        except Exception as e:
            error = str(e) or type(e).__name__
        if new is not None:
            changed = [f"{k} {new.info[k]!r} (was {self._info[k]!r})" for k in _FIXED
                       if not _same(new.info[k], self._info[k])]
            if changed:
                new.close()
                new, error = None, (f"it opened with {', '.join(changed)}; an arm in use keeps "
                                    f"these")
        self._reopened, self._reopen_error = time.monotonic(), error
        if new is None:
            log.warning(json.dumps({"event": "arm_reopen_failed", "arm": self.spec,
                                    "ended": old.how(), "error": error}))
            raise ArmError(f"{ended}; opening it again failed: {error}")
        self._child = new
        log.warning(json.dumps({"event": "arm_reopened", "arm": self.spec, "ended": old.how(),
                                "pid": new.pid}))
        return new

    def _request(self, op: str, *args, run: Optional[tuple] = None):
        """The arm process's answer to a request (its error raised here). A request the process
        never got goes to a new one (:meth:`_live`); one it got and did not answer raises
        ``ArmError``, except a run's start (``run``: the _Run and its executor), which from then
        on ends with a final record, not an error."""
        what = f"{args[0]}()" if op in ("call", "attr") else op
        with self._lock:
            if self._closed:
                raise ArmError("arm: closed")
            end = None
            for _ in range(2):
                child = self._live()
                if run is not None:
                    child.adopt(*run)
                try:
                    child.conn.send((op, *args))
                except BaseException as e:
                    if run is not None:
                        child.take(run[0].id)
                    if not isinstance(e, OSError):
                        raise
                    child.lost = True           # not delivered: to a new process
                    continue
                try:
                    status, value = child.conn.recv()
                except (EOFError, OSError):
                    child.lost = True
                    if run is None:
                        raise ArmError(f"arm: the process of {self.spec!r} ended "
                                       f"({child.how()}) during {what}; its next use opens it "
                                       f"again") from None
                    status, value, end = "ok", None, child.take(run[0].id)
                    break
                if run is not None:
                    end = child.answered(run[0].id, status == "ok")
                break
            else:
                raise ArmError(f"arm: the process of {self.spec!r} ended ({child.how()}) "
                               f"before it took {what}")
        if end is not None:
            _end(end[0], end[1], child.how())
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
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._child.close()
