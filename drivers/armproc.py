"""An arm in its own process: :class:`ArmProcess`, what ``drivers.open_arm(spec, process=True)``
returns.

The child process opens the backend by name (``drivers.open_arm(spec)``, so its connection, its
threads and its Limits are the backend's own) and does two things: it answers the calls of the
:class:`~drivers.base.Arm` interface made on the proxy in the parent (``tool_pose``, ``move``,
``stop``, ``status``, and any other public attribute, e.g. ``URArm.recover``), and it runs an
:class:`~drivers.executor.Executor`'s control loop, the same :class:`~drivers.control.Control`
a thread runs, on set-points the parent writes into a ring in shared memory. The parent keeps the
``Executor`` API: ``push`` resamples and writes the ring, ``cancel`` raises a flag and wakes the
loop through a pipe, feedback comes back through another pipe.

Why a process: a set-point is due every 2 ms at 500 Hz, and a control thread that shares its
interpreter with gRPC, a feeder or a large heap's garbage collector waits for the interpreter
lock after each wait (docs/benchmarks/arms.md#where-a-500-hz-loop-loses-its-cycles).

The parts: :mod:`~dqpose.drivers.armring` the shared ring's layout (and why it needs x86-64's
store order), :mod:`~dqpose.drivers.armchild` what runs in the child (and how it stops when its
parent goes), :mod:`~dqpose.drivers.armrun` the parent's side of one child and its runs; this
module the proxy and its reopen.

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
import multiprocessing as mp
import numbers
import pickle
import threading
import time
import weakref
from typing import Optional

import numpy as np

from dqpose.drivers.armring import check_store_order
from dqpose.drivers.armrun import ChildProcess, RingRun, end_run
from dqpose.drivers.base import Arm, ArmError, ArmState

__all__ = ["ArmProcess", "check_store_order"]

log = logging.getLogger("dqpose.drivers")


def _close_at_exit(ref) -> None:
    proc = ref()
    if proc is not None:
        proc.close()


#: what an arm's process reports once it has opened the arm: the same again when it is reopened
_FIXED = ("period", "limits", "name", "pose_sigma", "options")


def _same(a, b) -> bool:
    try:
        return bool(a == b)
    except ValueError:      # arrays inside (a Limits' box given as arrays): compared as data
        return pickle.dumps(a) == pickle.dumps(b)


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
        self._child = ChildProcess(self._ctx, spec, kwargs, self.start_timeout)
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

    def _live(self) -> ChildProcess:
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
            new = ChildProcess(self._ctx, self.spec, self._kwargs, self.start_timeout)
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

    def request_child(self, op: str, *args, run: Optional[RingRun] = None):
        """The arm process's answer to a request (its error raised here). A request the process
        never got goes to a new one (:meth:`_live`); one it got and did not answer raises
        ``ArmError``, except a run's start (``run``: its RingRun), which from then on ends with a
        final record, not an error."""
        what = f"{args[0]}()" if op in ("call", "attr") else op
        with self._lock:
            if self._closed:
                raise ArmError("arm: closed")
            end = None
            for _ in range(2):
                child = self._live()
                if run is not None:
                    child.adopt(run)
                try:
                    child.conn.send((op, *args))
                except BaseException as e:
                    if run is not None:
                        child.take(run.id)
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
                    status, value, end = "ok", None, child.take(run.id)
                    break
                if run is not None:
                    end = child.answered(run.id, status == "ok")
                break
            else:
                raise ArmError(f"arm: the process of {self.spec!r} ended ({child.how()}) "
                               f"before it took {what}")
        if end is not None:
            end_run(end[0], child.how())
        if status == "error":
            raise value
        return value

    def call(self, name: str, *args, **kwargs):
        """The child arm's method ``name`` with these arguments; its result."""
        return self.request_child("call", name, args, kwargs)

    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)
        kind, value = self.request_child("attr", name)
        if kind == "value":
            return value
        return lambda *a, **kw: self.call(name, *a, **kw)

    def open_run(self, settings, busy_timeout: float, outcome) -> RingRun:
        """An :class:`~drivers.executor.Executor`'s run: its loop in the child."""
        return RingRun(self, settings, busy_timeout, outcome, next(self._ids))

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
