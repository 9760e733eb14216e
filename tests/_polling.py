"""Test helper: wait for something a simulator or driver does in its own thread or process."""
from __future__ import annotations

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
