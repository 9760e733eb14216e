"""A lock that many readers hold at once, or one writer alone (:class:`ReadWrite`)."""
from __future__ import annotations

import threading


class ReadWrite:
    """Readers share it (``with lock.read():``); a writer has it alone (``with lock.write():``).
    A writer that waits holds back the readers that come after it, so a steady stream of
    readers never starves the writers."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._readers = 0
        self._writing = False
        self._waiting = 0       # writers waiting
        self._asleep = 0        # readers and writers in a wait on _cond (none: no one to wake)
        # plain objects, not generator context managers: a cached answer costs ~1 µs of lock
        # this way against ~4 µs
        self._read, self._write = _Read(self), _Write(self)

    def read(self) -> _Read:
        return self._read

    def write(self) -> _Write:
        return self._write


class _Side:
    """One side of a :class:`ReadWrite`, as a context manager."""
    __slots__ = ("_rw",)

    def __init__(self, rw: ReadWrite) -> None:
        self._rw = rw


class _Read(_Side):
    __slots__ = ()

    def __enter__(self) -> None:
        rw = self._rw
        with rw._lock:
            while rw._writing or rw._waiting:
                _sleep(rw)
            rw._readers += 1

    def __exit__(self, *exc) -> None:
        rw = self._rw
        with rw._lock:
            rw._readers -= 1
            if not rw._readers and rw._waiting:
                rw._cond.notify_all()


class _Write(_Side):
    __slots__ = ()

    def __enter__(self) -> None:
        rw = self._rw
        with rw._lock:
            rw._waiting += 1
            try:
                while rw._writing or rw._readers:
                    _sleep(rw)
            except BaseException:
                rw._waiting -= 1
                rw._cond.notify_all()       # the readers it held back
                raise
            rw._waiting -= 1
            rw._writing = True

    def __exit__(self, *exc) -> None:
        rw = self._rw
        with rw._lock:
            rw._writing = False
            if rw._asleep:
                rw._cond.notify_all()


def _sleep(rw: ReadWrite) -> None:
    """A wait on ``rw``'s condition (its lock held), counted: a writer's release wakes no one
    when no one waits (a Publish step's common case, where notify_all alone cost ~2 µs)."""
    rw._asleep += 1
    try:
        rw._cond.wait()
    finally:
        rw._asleep -= 1
