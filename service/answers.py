"""A world's Lookups answered without a fit: a pair of frames asked for at time 0 (the newest
both are known at, tf's ``Time(0)``) is *watched* for :data:`WATCH_FOR` seconds, and each
Publish step that brings a measurement of a watched body makes that pair's answer again, after
the step's Subscribe answers. A Lookup finding an answer made since the last measurement of
either body (:meth:`dqpose.world.World.stamp`) is answered from it (:meth:`Answers.kept`, with no
lock: an event loop may call it), the same bytes the fit gives; any other Lookup is fitted
(:meth:`Answers.lookup`). The world's own kept answers are read under its lock, which a Publish
step's write may hold; these are read without it, so a reader never waits.

So a planner or a view polling a body's pose gets it without waiting for a fit, and the fit's
cost moves to the Publish steps that bring the body's measurements: at most :data:`MAX_WATCHED`
pairs a world, each made again at most once a step. The clock decides only what is kept, never
an answer's bytes. A world's own fits are kept in a :class:`Kept` (bounded).
"""
from __future__ import annotations

import threading
import time
from typing import Callable

#: seconds a pair stays watched after a Lookup of it at time 0
WATCH_FOR = 2.0
#: pairs a world watches at most; the one watched longest ago gives way
MAX_WATCHED = 8

_clock = time.monotonic


class Answers:
    """One world's watched pairs and their answers (``encode`` ``(BodyPose) -> bytes``: the
    transport's ``RelativePose``), each with the stamp it was made under."""

    def __init__(self, encode: Callable):
        self.encode = encode
        self._lock = threading.Lock()
        self._watched: dict[tuple[str, str], float] = {}   # pair -> watched until (monotonic)
        self._answers: dict[tuple[str, str], tuple[tuple[int, ...], bytes]] = {}
        self.hits = 0                                       # Lookups answered from a kept one

    def kept(self, world, target: str, source: str) -> bytes | None:
        """The kept answer to a Lookup of ``(target, source)`` at time 0 if it is still the
        answer, else None (the caller fits). No lock of the world's: an event loop calls it."""
        pair = (target, source)
        kept = self._answers.get(pair)
        if kept is None or kept[0] != world.stamp(*pair):
            return None
        with self._lock:
            if pair in self._watched:
                self._watched[pair] = _clock() + WATCH_FOR
        self.hits += 1
        return kept[1]

    def lookup(self, world, target: str, source: str, time: float) -> bytes:
        """A Lookup fitted; at time 0 its pair watched and its answer kept."""
        if time != 0.0:
            return self.encode(world.relative(target, source, time))
        pair = (target, source)
        stamp, data = self._made(world, pair)
        with self._lock:
            self._watched.pop(pair, None)
            self._watched[pair] = _clock() + WATCH_FOR
            if len(self._watched) > MAX_WATCHED:
                oldest = next(iter(self._watched))
                del self._watched[oldest]
                self._answers.pop(oldest, None)
            if stamp is not None:
                self._answers[pair] = (stamp, data)
        return data

    def refresh(self, world, bodies) -> None:
        """After a Publish step brought measurements of ``bodies``: the answers of the watched
        pairs they concern made again; pairs no longer watched forgotten."""
        if not self._watched:       # no pair watched (most worlds): read without the lock
            return
        now = _clock()
        touched = set(bodies)
        with self._lock:
            for pair in [p for p, until in self._watched.items() if until < now]:
                del self._watched[pair]
                self._answers.pop(pair, None)
            root = world.tree.root      # a static's or source's answer moves with its body
            due = [p for p in self._watched if root(p[0]) in touched or root(p[1]) in touched]
        for pair in due:
            try:
                stamp, data = self._made(world, pair)
            except (ValueError, LookupError):
                stamp = None                # the next Lookup fits, and says why
            with self._lock:
                if stamp is None or pair not in self._watched:
                    self._answers.pop(pair, None)
                else:
                    self._answers[pair] = (stamp, data)

    def _made(self, world, pair: tuple[str, str]) -> tuple[tuple[int, ...] | None, bytes]:
        """The answer for ``pair`` at time 0 and the stamp it holds under: None when a
        measurement of either body came in while it was made (the stamps before and after
        differ)."""
        before = world.stamp(*pair)
        data = self.encode(world.relative(pair[0], pair[1], 0.0))
        return (before if world.stamp(*pair) == before else None), data


# answers kept at most, and the measurements their fits describe at most (a fit keeps ~75
# bytes of each: residuals, distances, NIS...; ~5 MB); beyond either, the cache starts over
_CACHED, _CACHED_ROWS = 4096, 65536


class Kept(dict):
    """Answers kept (a world's fits, by their body, time and window), bounded by their number
    and by the measurements they describe (``rows``)."""

    rows = 0

    def clear(self) -> None:
        super().clear()
        self.rows = 0

    def keep(self, key, value, rows: int = 1) -> None:
        if len(self) >= _CACHED or self.rows + rows > _CACHED_ROWS:
            self.clear()
        self[key] = value
        self.rows += rows
