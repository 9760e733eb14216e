"""When a body's answers fall due, from the measurements' own times (never the clock): the
pacing of ``StreamFuse`` and of ``World.Subscribe``, pure and deterministic, so that a recording
of the arrivals replays to the same ticks.

With several sources feeding a body (cameras on their hosts, an arm on its controller), the
body's *horizon* is the time up to which its data can be taken as complete: every source that has
fed it has a measurement taken at or after it, or the fastest source is ``max_delay`` of
measurement time past it (a source that stopped, or lags by more than that, is not waited for).
A tick falls due once the horizon reaches it (:class:`Schedule`); a measurement arriving for a
tick already answered enters the later ticks' fits only.
"""
from __future__ import annotations

import math
import zlib
from typing import Mapping


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


class Schedule:
    """One subscription's ticks (``rate`` > 0): each body's next tick, counted in closed form
    (StreamFuse's: a body whose time leapt gives a range, not a loop over every tick between).
    :meth:`due` takes a body's horizon and the oldest measurement of its window after a step
    and gives the ticks that fell due, each once, in order: those at or before the horizon,
    none before the window (its data gone)."""

    def __init__(self, rate: float):
        if not (math.isfinite(rate) and rate > 0.0):
            raise ValueError(f"rate: must be finite and > 0, got {rate!r}")
        self.rate = rate
        self.next: dict[str, int] = {}
        self.next_time: dict[str, float] = {}      # the time of each body's next tick
        self._phase: dict[str, float] = {}

    def phase(self, body: str) -> float:
        p = self._phase.get(body)
        if p is None:
            p = self._phase[body] = tick_phase(body)
        return p

    def due(self, body: str, horizon: float, floor: float) -> range:
        """``body``'s ticks (numbers ``k``, :meth:`time` ``(body, k)``) due now that its data
        are complete up to ``horizon``, not before ``floor``."""
        rate, phase = self.rate, self.phase(body)
        k = self.next.get(body)
        # a next tick at or after the floor is at or after the floor's first: not looked for
        if k is None or self.next_time[body] < floor:
            first = first_tick(floor, rate, phase)
            k = first if k is None else max(k, first)
        end = first_tick(horizon, rate, phase)
        if tick_time(end, rate, phase) <= horizon:
            end += 1
        self.next[body] = max(k, end)
        self.next_time[body] = tick_time(max(k, end), rate, phase)
        return range(k, end)

    def waiting(self, body: str, horizon: float) -> bool:
        """Whether ``body``'s next tick (once it has had one) is beyond ``horizon``: no tick
        due, and :meth:`due` not asked (StreamFuse's test before its ticks are counted)."""
        return self.next_time.get(body, -math.inf) > horizon

    def time(self, body: str, k: int) -> float:
        """The time of ``body``'s tick ``k``."""
        return tick_time(k, self.rate, self.phase(body))
