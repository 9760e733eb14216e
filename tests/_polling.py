"""Test helpers for a loaded machine: wait for something a simulator or driver does in its own
thread or process, and measure how much slower than an idle core work runs meanwhile."""
from __future__ import annotations

import threading
import time


def wait_until(pred, timeout: float = 2.0, poll: float = 0.001):
    """Calls ``pred`` every ``poll`` seconds until it returns something truthy or ``timeout``
    seconds pass; returns its last value (so ``assert wait_until(...)`` fails on a timeout)."""
    deadline = time.monotonic() + timeout
    while True:
        v = pred()
        if v or time.monotonic() > deadline:
            return v
        time.sleep(poll)


class Slowdown:
    """How much slower than on an idle core CPU-bound work runs on this machine now: from
    :meth:`start` to :meth:`stop` a thread alternates ``BURST`` s of its own CPU time spinning
    with ``REST`` s asleep (so that it measures the machine without taking a core from what it
    measures), and :meth:`stop` returns the wall time of its bursts over their CPU time (at
    least 1). Work that needs an idle core for a second needs about this many seconds now."""

    BURST, REST = 0.002, 0.008

    def __init__(self):
        self._stop = threading.Event()
        self._wall = self._cpu = 0.0
        self._thread = threading.Thread(target=self._spin, daemon=True)

    def _spin(self):
        while not self._stop.is_set():
            wall, cpu = time.monotonic(), time.thread_time()
            while time.thread_time() - cpu < self.BURST:
                pass
            self._wall += time.monotonic() - wall
            self._cpu += time.thread_time() - cpu
            self._stop.wait(self.REST)

    def start(self) -> "Slowdown":
        self._thread.start()
        return self

    def stop(self) -> float:
        self._stop.set()
        self._thread.join()
        return max(1.0, self._wall / max(self._cpu, 1e-9))
