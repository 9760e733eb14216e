"""When a body's answers fall due, from the measurements' own times (never the clock): the
pacing of ``StreamFuse`` and of ``World.Subscribe``, pure and deterministic, so that a recording
of the arrivals replays to the same ticks.

With several sources feeding a body (cameras on their hosts, an arm on its controller), the
body's *horizon* is the time up to which its data can be taken as complete: every source that has
fed it has a measurement taken at or after it, or the fastest source is ``max_delay`` of
measurement time past it (a source that stopped, or lags by more than that, is not waited for).
A tick falls due once the horizon reaches it; a measurement arriving for a tick already answered
enters the later ticks' fits only.
"""
from __future__ import annotations

import bisect
import math
import zlib
from typing import Mapping

#: ticks one arrival may make due at most (a jump of the horizon past more is answered for the
#: newest ones only: the older ones' data left the window long ago)
MAX_DUE = 4096


def tick_phase(body: str) -> float:
    """Where ``body``'s ticks sit in the output period, as a fraction of it in [0, 1): from the
    CRC-32 of its name, so that many bodies' ticks spread over the period instead of falling due
    together (one burst of estimates), and a recorded stream replays to the same ticks."""
    return zlib.crc32(body.encode()) / 2.0**32


def tick_time(k: int, rate: float, phase: float) -> float:
    """Tick ``k`` of a body whose ticks have ``phase`` (:func:`tick_phase`)."""
    return (k + phase) / rate


def first_tick(t: float, rate: float, phase: float = 0.0) -> int:
    """The first tick ``k`` (at :func:`tick_time`) at or after ``t``, exactly in floating
    point (a step or two of correction while ``|t| * rate`` is within
    :data:`limits.EXACT_TICKS`, which the stream's limits keep it)."""
    k = math.ceil(t * rate - phase)
    while tick_time(k - 1, rate, phase) >= t:
        k -= 1
    while tick_time(k, rate, phase) < t:
        k += 1
    return k


def horizon(newest: Mapping[str, float], max_delay: float) -> float:
    """The time up to which a body's data are complete, given the newest taken time of each
    source that has fed it: the oldest of them, or ``max_delay`` before the newest, whichever is
    later. ``-inf`` with no source."""
    if not newest:
        return -math.inf
    times = newest.values()
    return max(min(times), max(times) - max_delay)


class Ticks:
    """One body's ticks for one subscription. :meth:`arrive` takes each measurement's source and
    taken time in arrival order and returns the tick times that fell due, in order, each once.

    ``rate`` > 0: ticks at :func:`tick_time` ``(k, rate, phase)`` from the body's first
    measurement on. ``rate`` 0: one tick per distinct taken time (each measurement time of the
    body is answered once its horizon reaches it). ``window``: ticks more than this before the
    horizon when they fall due are skipped (their data left the body's window)."""

    def __init__(self, rate: float, max_delay: float, phase: float = 0.0,
                 window: float = math.inf):
        if not (math.isfinite(rate) and rate >= 0.0):
            raise ValueError(f"rate: must be finite and >= 0, got {rate!r}")
        if not (math.isfinite(max_delay) and max_delay >= 0.0):
            raise ValueError(f"max_delay: must be finite and >= 0, got {max_delay!r}")
        self.rate, self.max_delay, self.phase, self.window = rate, max_delay, phase, window
        self.newest: dict[str, float] = {}
        self.next: int | None = None           # rate > 0: the next tick to fire
        self.pending: list[float] = []         # rate 0: times not yet due, sorted
        self.done = -math.inf                  # the horizon answered up to

    def arrive(self, source: str, taken: float) -> list[float]:
        """The ticks due after a measurement of ``source`` taken at ``taken`` arrived."""
        if taken > self.newest.get(source, -math.inf):
            self.newest[source] = taken
        if self.rate:
            if self.next is None:
                self.next = first_tick(taken, self.rate, self.phase)
        elif taken > self.done:
            i = bisect.bisect_left(self.pending, taken)
            if i == len(self.pending) or self.pending[i] != taken:
                self.pending.insert(i, taken)
                if len(self.pending) > MAX_DUE:    # bounded: the oldest pending time gives way
                    del self.pending[0]
        return self._due(horizon(self.newest, self.max_delay))

    def _due(self, h: float) -> list[float]:
        if h <= self.done:
            return []
        self.done = h
        oldest = h - self.window
        if not self.rate:
            k = bisect.bisect_right(self.pending, h)
            due, self.pending = self.pending[:k], self.pending[k:]
            return [t for t in due if t >= oldest][-MAX_DUE:]
        assert self.next is not None
        if tick_time(self.next, self.rate, self.phase) > h:
            return []           # the common case: no tick reached (the answer below, sooner)
        last = first_tick(h, self.rate, self.phase)
        if tick_time(last, self.rate, self.phase) > h:
            last -= 1
        if last < self.next:
            return []
        start = max(self.next, last - MAX_DUE + 1)
        if math.isfinite(oldest):
            start = max(start, first_tick(oldest, self.rate, self.phase))
        self.next = last + 1
        return [tick_time(k, self.rate, self.phase) for k in range(start, last + 1)]
