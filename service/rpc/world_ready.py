"""Lookups a world answers from its event loop: a pair of frames asked for at time 0 (the newest
both are known at, tf's ``Time(0)``) is *watched* for :data:`WATCH_FOR` seconds, and each Publish
request that brings a measurement of a watched body makes that pair's answer again, in the worker
pool, after the request's Subscribe answers. A Lookup finding an answer made since the last
measurement of either body (:meth:`dqpose.world.World.stamp`) is answered on the loop without a
fit, the same bytes the fit gives; any other Lookup is fitted in the worker pool. (The world's
own kept answers are read under its lock, which a Publish request's write may hold; these are
read without it, so the loop never waits.)

So a planner or a view polling a body's pose gets it without waiting for a fit, and the fit's
cost moves to the Publish requests that bring the body's measurements: at most
:data:`MAX_WATCHED` pairs a world, each made again at most once a request.
"""
from __future__ import annotations

import threading
import time

from dqpose.rpc._proto.dqpose.v1 import world_pb2 as pb
from dqpose.rpc.world_convert import relative_msg

#: seconds a pair stays watched after a Lookup of it at time 0
WATCH_FOR = 2.0
#: pairs a world watches at most; the one watched longest ago gives way
MAX_WATCHED = 8

_clock = time.monotonic


class Ready:
    """One world's watched pairs and their answers (serialized ``RelativePose`` messages, each
    with the stamp it was made under)."""

    def __init__(self):
        self._lock = threading.Lock()
        self._watched: dict[tuple[str, str], float] = {}   # pair -> watched until (monotonic)
        self._answers: dict[tuple[str, str], tuple[tuple[int, ...], bytes]] = {}
        self.hits = 0                                       # Lookups answered on the loop

    def answer(self, world, request: pb.LookupRequest) -> bytes | None:
        """On the event loop: the kept answer to ``request`` if it is still the answer, else
        None (the caller fits)."""
        if request.time != 0.0:
            return None
        pair = (request.target, request.source)
        kept = self._answers.get(pair)
        if kept is None or kept[0] != world.stamp(*pair):
            return None
        with self._lock:
            if pair in self._watched:
                self._watched[pair] = _clock() + WATCH_FOR
        self.hits += 1
        return kept[1]

    def lookup(self, world, request: pb.LookupRequest) -> bytes:
        """In the worker pool: ``request`` fitted; at time 0 its pair watched and its answer
        kept."""
        if request.time != 0.0:
            return relative_msg(world.relative(request.target, request.source,
                                               request.time)).SerializeToString()
        pair = (request.target, request.source)
        stamp, data = _made(world, pair)
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
        """In the worker pool, after a Publish request brought measurements of ``bodies``: the
        answers of the watched pairs they concern made again; pairs no longer watched
        forgotten."""
        now = _clock()
        touched = set(bodies)
        with self._lock:
            for pair in [p for p, until in self._watched.items() if until < now]:
                del self._watched[pair]
                self._answers.pop(pair, None)
            due = [p for p in self._watched if p[0] in touched or p[1] in touched]
        for pair in due:
            try:
                stamp, data = _made(world, pair)
            except (ValueError, LookupError):
                stamp = None                # the next Lookup fits, and says why
            with self._lock:
                if stamp is None or pair not in self._watched:
                    self._answers.pop(pair, None)
                else:
                    self._answers[pair] = (stamp, data)


def _made(world, pair: tuple[str, str]) -> tuple[tuple[int, ...] | None, bytes]:
    """The answer for ``pair`` at time 0 and the stamp it holds under: None when a measurement
    of either body came in while it was made (the stamps before and after differ)."""
    before = world.stamp(*pair)
    data = relative_msg(world.relative(pair[0], pair[1], 0.0)).SerializeToString()
    return (before if world.stamp(*pair) == before else None), data
