"""The set-point ring an arm's process and its owner share (:mod:`dqpose.drivers.armproc`):
one run's counters, signals and set-points in shared memory.

Layout: a header of int64 counters and flags (the indices below), then a halt's reason (UTF-8
bytes), then ``capacity`` slots of float64 ``[plan time, pose (8)]``. The ring has one writer
(the owner) and one reader (the arm's process); a slot is written before the count that
publishes it, which x86-64's store order (TSO) keeps in order. Other processors (aarch64) may
make the count visible before the slot: there :func:`check_store_order` refuses the arm process
and the control loop runs in a thread.
"""
from __future__ import annotations

import mmap
import os
import platform
import struct
from multiprocessing import shared_memory
from typing import Optional

import numpy as np

from dqpose.drivers.base import ArmError

# ring header, one int64 each: slots written and read (of a plan: its slots and those taken),
# input finished, cancel, set-points sent, real-time, the last heartbeat (CLOCK_MONOTONIC ns),
# halt (the reason's length + 1, the reason in the bytes after the header)
WRITTEN, READ, FINISHED, CANCEL, SENT, REALTIME, BEAT, HALT = range(8)
HEADER = 8
REASON = 512                    # bytes of a halt's reason
SLOT = 9                        # plan time, then the pose
RUN_ID = struct.Struct("<q")    # a run's id on the wake pipe
# processors whose store order keeps the ring's slot-then-count writes in order (TSO)
_TSO = {"x86_64", "amd64", "i386", "i686"}


def check_store_order(machine: Optional[str] = None) -> None:
    """ArmError unless this processor keeps stores in order, as the ring needs."""
    machine = (machine if machine is not None else platform.machine()).lower()
    if machine not in _TSO:
        raise ArmError(f"process: an arm in its own process needs x86-64's store order for its "
                       f"set-point ring; this is {machine or 'an unknown processor'}: run the "
                       f"control loop in a thread (open_arm(spec), without process=True)")


class Ring:
    """A run's counters and signals and its set-points (plan time + pose; none for a whole
    plan, which the child samples itself), in shared memory: made by the parent (``name``
    None), which alone unlinks it; mapped by name in the child, outside ``multiprocessing``'s
    resource tracker (whose register from the child could come after the parent's unregister
    and count the ring as leaked)."""

    def __init__(self, capacity: int, name: Optional[str] = None):
        self.capacity = int(capacity)
        size = 8 * HEADER + REASON + 8 * SLOT * self.capacity
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
        self.head = np.ndarray((HEADER,), np.int64, buf)
        self.reason = np.ndarray((REASON,), np.uint8, buf, offset=8 * HEADER)
        self.slots = np.ndarray((self.capacity, SLOT), np.float64, buf,
                                offset=8 * HEADER + REASON)
        if name is None:
            self.head[:] = 0

    def halt(self, reason: str) -> None:
        """The reason, then the flag that publishes it (the parent's side)."""
        data = reason.encode("utf-8")[:REASON].decode("utf-8", "ignore").encode("utf-8")
        self.reason[:len(data)] = np.frombuffer(data, np.uint8)
        self.head[HALT] = len(data) + 1

    def halted(self) -> Optional[str]:
        n = int(self.head[HALT])
        return self.reason[:n - 1].tobytes().decode("utf-8") if n else None

    def close(self) -> None:
        """Unmap it; the parent also unlinks it."""
        del self.head, self.slots, self.reason      # no view may outlive the mapping
        if self.shm is None:
            self._map.close()
            return
        self.shm.close()
        self.shm.unlink()
