"""A World Lookup's answer from its request (:func:`answer`: a Lookup at one time, or tf2's
advanced lookup of :mod:`dqpose.two_times`), and a Lookup that waits (``LookupRequest.wait``,
tf2's ``canTransform``/``waitForTransform`` with a timeout: :class:`Waits`).

A Lookup that cannot be answered for lack of data (a frame not in the world yet,
:class:`dqpose.errors.NotFound`; a time past the newest measurement beyond
``max_extrapolation``, :class:`dqpose.errors.NotYet`) and asks to wait is tried again after
each Publish step that brought a measurement of one of its frames or of a body they hang
from (a source's or a static's chain, :mod:`dqpose.frames`; the hub's ``listeners``,
called under its lock, hand the wake-up to the event loop: nothing polls), each try a fit in
the worker pool as any Lookup's; answered as soon as one succeeds, else after ``wait`` seconds
with the error of its last try (the error it would have had without waiting: the same status
and text). Any other error answers at once, and so does a world the server does not hold
(NOT_FOUND: no steps of it to wait for). A cancelled call stops waiting; the server's stop
answers the waiting ones UNAVAILABLE. Waiting Lookups are bounded per world
(``max_world_waits``) and per peer (``max_peer_waits``): one more is RESOURCE_EXHAUSTED naming
the limit, before it waits.
"""
from __future__ import annotations

import asyncio
import math
from collections import Counter
from typing import Awaitable, Callable

from dqpose import limits as _limits
from dqpose.errors import FieldError, NotFound, NotYet
from dqpose.hub import Hub

#: the longest a Lookup may wait, s (LookupRequest.wait)
MAX_WAIT = 10.0


class Stopped(Exception):
    """The server stops: a waiting Lookup is answered UNAVAILABLE."""


def check(request) -> None:
    """A LookupRequest's numbers: ``FieldError`` naming the first bad one."""
    for name in ("time", "source_time"):
        value = getattr(request, name)
        if not math.isfinite(value):
            raise FieldError(f"{name}: must be finite (0: "
                             f"{'the newest both are known at' if name == 'time' else 'time'})"
                             f", got {value!r}")
    if not (0.0 <= request.wait <= MAX_WAIT):       # NaN too
        raise FieldError(f"wait: must be between 0 and {MAX_WAIT:g} s, got {request.wait!r}")


def plain(request) -> bool:
    """A Lookup at one time (no ``source_time``, no ``fixed_frame``): the kept answers'."""
    return request.source_time == 0.0 and not request.fixed_frame


def answer(world: Hub, request) -> bytes:
    """A ``RelativePose``, serialized (checked first): at one time :meth:`Hub.lookup`'s, else
    :meth:`dqpose.world.World.relative_at`'s."""
    check(request)
    if plain(request):
        return world.lookup(request.target, request.source, request.time)
    return world.encoder.relative(world.world.relative_at(
        request.target, request.time, request.source, request.source_time,
        request.fixed_frame))


def waitable(e: Exception) -> bool:
    """Whether measurements to come may answer a Lookup that failed with ``e``."""
    return isinstance(e, (NotFound, NotYet))


class Waits:
    """The server's waiting Lookups (event loop only): their counts per world and per peer
    (``peers``: :class:`dqpose.rpc.peers.Peers`, who a call comes from), their wake-ups."""

    def __init__(self, limits: _limits.Limits, peers):
        self.limits, self.peers = limits, peers
        self.count: Counter = Counter()
        self.stopped = False
        self._woken: set[asyncio.Event] = set()

    def stop(self) -> None:
        """The server stops: every waiting Lookup answered UNAVAILABLE, no new one waits."""
        self.stopped = True
        for woken in self._woken:
            woken.set()

    async def lookup(self, world: Hub, request, context,
                     attempt: Callable[[], Awaitable[bytes]]) -> bytes:
        """``attempt()`` (a Lookup's answer, fitted in the pool), and while it fails for lack
        of data again after each Publish step bringing one of the request's frames, until
        ``request.wait`` is over (see the module)."""
        check(request)
        if request.wait == 0.0:
            return await attempt()
        loop = asyncio.get_running_loop()
        deadline = loop.time() + request.wait
        # the frames and those they hang from (dqpose.frames: a source's or a static's chain
        # to its root, a body whose step may answer it), in the tree of the wait's start
        tree = world.world.tree
        frames = {f for name in (request.target, request.source, request.fixed_frame) if name
                  for f in tree.chain(name)} - {""}
        woken = asyncio.Event()

        def listener(bodies: tuple) -> None:        # a worker thread, the hub's lock held
            if not frames.isdisjoint(bodies):
                loop.call_soon_threadsafe(woken.set)

        # listening before the first try: a step during it wakes the wait that follows
        world.listeners.add(listener)
        held: list = []
        try:
            while True:
                woken.clear()
                try:
                    return await attempt()
                except Exception as e:
                    if not waitable(e):
                        raise
                    last = e
                if not held:
                    held = self._hold(world.name, context)
                    self._woken.add(woken)
                left = deadline - loop.time()
                if left <= 0.0 or not await _woken(woken, left):
                    raise last
                if self.stopped:
                    raise Stopped("the server is stopping; the Lookup was waiting for data")
        finally:
            world.listeners.discard(listener)
            self._woken.discard(woken)
            for key in held:
                self.count[key] -= 1
                if not self.count[key]:
                    del self.count[key]

    def _hold(self, world: str, context) -> list:
        """A waiting Lookup's counts in its peer's and its world; ``OverLimit`` naming the
        first bound reached (and :class:`Stopped` once the server stops)."""
        if self.stopped:
            raise Stopped("the server is stopping; the Lookup would wait for data")
        keys = [(("peer", self.peers.peer(context)), "max_peer_waits"),
                (("world", world), "max_world_waits")]
        for key, name in keys:
            bound = getattr(self.limits, name)
            if self.count[key] >= bound:
                where = f"world {world!r}" if key[0] == "world" else f"peer {key[1]}"
                raise _limits.over("wait", f"{where} has {bound} Lookups waiting", self.limits,
                                   name)
        for key, _ in keys:
            self.count[key] += 1
        return [key for key, _ in keys]


async def _woken(woken: asyncio.Event, seconds: float) -> bool:
    """Whether ``woken`` is set within ``seconds``."""
    try:
        await asyncio.wait_for(woken.wait(), seconds)
        return True
    except asyncio.TimeoutError:
        return False
