"""The owner's side of an arm's process (:mod:`dqpose.drivers.armproc`):
:class:`ChildProcess`, one process with its pipes and the thread that reads its feedback, and
:class:`RingRun`, one run handed to it (the :class:`~dqpose.drivers.run.Run` an
:class:`~dqpose.drivers.executor.Executor` drives: ``put`` writes the ring, ``cancel``/``halt``
raise a flag and wake the process's loop through a pipe, ``beat`` stamps the heartbeat).
Feedback comes back through another pipe, written by the process without blocking: an owner
that stops reading loses records, never a set-point. A process that ends under a run ends it
``ERROR`` saying how (:func:`end_run`).
"""
from __future__ import annotations

import os
import pickle
import signal
import threading
import time
from multiprocessing.connection import wait
from typing import TYPE_CHECKING, Optional

import numpy as np

from dqpose.drivers.armchild import child_main
from dqpose.drivers.armring import (
    BEAT,
    CANCEL,
    FINISHED,
    READ,
    REALTIME,
    RUN_ID,
    SENT,
    WRITTEN,
    Ring,
)
from dqpose.drivers.base import ArmError
from dqpose.drivers.control import Feedback, Result, Settings
from dqpose.drivers.run import Outcome, Run

if TYPE_CHECKING:
    from dqpose.drivers.armproc import ArmProcess


class RingRun(Run):
    """The parent's side of one run in the arm's process (``proc``), reporting to ``outcome``."""

    def __init__(self, proc: "ArmProcess", settings: Settings, busy_timeout: float,
                 outcome: Outcome, run_id: int):
        self.proc, self.settings, self.busy_timeout = proc, settings, busy_timeout
        self.outcome, self.id = outcome, run_id
        self.ring: Optional[Ring] = None
        self.child: Optional[ChildProcess] = None     # the process it was handed to
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
            self.ring = Ring(capacity)
            self.ring.head[BEAT] = int(self._beat * 1e9)
            self.ring.head[CANCEL] = int(self._cancel)
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
                w = int(head[WRITTEN])
                n = min(len(slots) - i, cap - (w - int(head[READ])))
                if n > 0:
                    rows = np.array([[t, *p] for t, p in slots[i:i + n]])
                    idx = (w + np.arange(n)) % cap
                    self.ring.slots[idx] = rows
                    head[WRITTEN] = w + n      # after the slots: publishes them
                    i += n
                    continue
            time.sleep(self.settings.period)    # full: the arm makes room, a period a slot

    def _hand_over(self, trajectory) -> None:
        """The run in the child (which waits for the arm and checks the start): on the ring's
        slots, or on ``trajectory``, which the child samples itself (then the ring holds only
        the counters and signals). A refused start frees the ring."""
        try:
            self.proc.request_child("run", self.id, self.settings, self.ring.name,
                               self.ring.capacity, trajectory, self.busy_timeout, run=self)
        except BaseException:
            self.release()
            raise

    def start(self, slots) -> None:
        self.put(slots)
        self._hand_over(None)

    def start_plan(self, trajectory) -> None:
        with self._lock:
            self._make_ring(0)
        self._hand_over(trajectory)

    def finish(self) -> None:
        with self._lock:
            if self.ring is not None and self._final is None:
                self.ring.head[FINISHED] = 1

    def beat(self, now: float) -> None:
        with self._lock:
            self._beat = now
            if self.ring is not None and self._final is None:
                self.ring.head[BEAT] = int(now * 1e9)

    def _signal(self, set_flag) -> None:
        with self._lock:
            if self._final is not None:
                return
            set_flag()
            child = self.child
            if self.ring is None or child is None:
                return      # (the process reads the flags when it starts the run)
        try:
            child.wake.send_bytes(RUN_ID.pack(self.id))
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
                self.ring.head[CANCEL] = 1
        self._signal(flag)

    def _count(self, k: int) -> int:
        with self._lock:
            if self._final is not None:
                return self._final[k]
            if self.ring is None:
                return 0
            h = self.ring.head
            return (int(h[SENT]), int(h[REALTIME]), int(h[WRITTEN] - h[READ]))[k]

    @property
    def sent(self) -> int:
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
            self._final = (int(h[SENT]), int(h[REALTIME]), 0)
            self.ring.close()
            self.ring = None

    def close(self) -> None:
        self.release()


def how_ended(exitcode: Optional[int]) -> str:
    """How a process ended, from its exit code (negative: the signal that killed it)."""
    if exitcode is None:
        return "exit code unknown"
    if exitcode < 0:
        try:
            return f"killed by {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"killed by signal {-exitcode}"
    return f"exit code {exitcode}"


def end_run(run: RingRun, how: str) -> None:
    """A run whose process ended under it: ``ERROR``, where its last record had it."""
    run.release()
    last = run.last
    run.outcome.ended(Feedback(0.0 if last is None else last.time, time.time(),
                       None if last is None else last.commanded,
                       None if last is None else last.actual, Result.ERROR,
                       f"the arm's process ended ({how}) before the run did; it is opened again "
                       f"on the arm's next use"))


class ChildProcess:
    """One process of an :class:`ArmProcess`'s arm: the process, its pipes, the thread that reads
    its feedback, and the runs handed to it (run id -> [run, accepted]). A run is
    accepted once the process has answered its start; until then the request that hands it
    over ends it if the process ends, from then on this reader does (with the process's final
    record, or ``ERROR`` when the process ends first)."""

    def __init__(self, ctx, spec: str, kwargs: dict, start_timeout: float):
        self.spec = spec
        self.conn, child_conn = ctx.Pipe()
        wake_r, self.wake = ctx.Pipe(duplex=False)
        self.fb, fb_w = ctx.Pipe(duplex=False)
        self.process = ctx.Process(target=child_main, name=f"arm {spec}", daemon=False,
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
                return how_ended(None)
            self._how = how_ended(p.exitcode)
        return self._how

    def adopt(self, run: RingRun) -> None:
        """A run about to be handed over; it starts with a fresh heartbeat (the owner may beat
        from the thread that hands it over, which opening the arm again may have held)."""
        with self.lock:
            self.runs[run.id] = [run, False]
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
            entry[1] = True
            return None

    def _read(self) -> None:
        """Feedback records to their runs' outcomes; once the process has ended, each run
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
            run = entry[0]
            fb = Feedback(t, stamp, None if cmd is None else np.asarray(cmd),
                          None if act is None else np.asarray(act), Result(res), msg)
            if fb.result == Result.OK:
                run.last = fb
                run.outcome.emit(fb)
            elif self.take(rid) is not None:
                run.release()
                run.outcome.ended(fb)
        how = self.how()
        with self.lock:
            self.dead = True
            ended = [run for run, accepted in self.runs.values() if accepted]
            for run in ended:
                del self.runs[run.id]
        for run in ended:
            end_run(run, how)
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
