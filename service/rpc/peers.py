"""Who a stream comes from and what each client holds open: the one count of per-client streams,
and the rule that ends a subscription whose client stopped reading.

A peer is the bearer token when the server has one (every holder of it is one peer), else the
client's host (its address without the port; behind a proxy, the proxy's). Every streaming RPC
takes a slot (:meth:`Peers.open`) before it allocates anything for its client, and is refused
RESOURCE_EXHAUSTED naming the bound (a ``dqpose serve`` flag, :mod:`dqpose.limits`) when one
is reached:

* any stream: ``max_peer_streams`` a peer;
* a subscription (World Subscribe and SubscribeBatches, WatchArm: streams the server writes as
  things happen, whose client only reads): ``max_peer_subscriptions`` a peer,
  ``max_subscriptions`` a server, and a World one ``max_world_subscriptions`` a world.

A subscription's server and world slots are freed the moment the server ends it
(:meth:`Slot.end`), whatever its client does. A peer's slots are freed when the call is done
(its client read the status, cancelled or went away): a client that never reads keeps the
stream's last message in the server's transport until then, so what a peer holds stays bounded
by its own counts, and other peers never wait for it.

:meth:`Peers.write` is how a subscription writes: a write its client leaves waiting for
``max_write_wait`` raises :class:`FellBehind`. The stream then ends with :func:`exhausted`
(its status handed over, not waited for: it waits behind the unread message in HTTP/2 flow
control, and reaches the client if it ever reads).
"""
from __future__ import annotations

import asyncio
import hashlib
import urllib.parse
from collections import Counter

import grpc

from dqpose import limits
from dqpose.limits import OverLimit

#: the kinds of slot :meth:`Peers.open` gives
STREAM, SUBSCRIPTION = "stream", "subscription"


class FellBehind(OverLimit):
    """A subscription whose client fell behind its bound: RESOURCE_EXHAUSTED with this text."""


def host_of(peer: str) -> str:
    """The client's host in gRPC's ``context.peer()`` (``ipv4:10.0.0.7:51234`` -> ``10.0.0.7``,
    ``ipv6:[::1]:5555`` -> ``::1``); anything else (``unix:...``) as it is."""
    kind, _, rest = peer.partition(":")
    if kind == "ipv4":
        return rest.rpartition(":")[0] or rest
    if kind == "ipv6":      # gRPC writes the brackets %-encoded: ipv6:%5B::1%5D:5555
        rest = urllib.parse.unquote(rest)
        return rest.rpartition("]")[0].lstrip("[") or rest
    return peer


class Slot:
    """What one stream holds: its counts, each released once (``end``: the server and world
    ones; the call's end, or its last status's, :func:`exhausted`: the peer's)."""

    __slots__ = ("_peers", "_now", "_later", "_sending")

    def __init__(self, peers: "Peers", now: list, later: list):
        self._peers, self._now, self._later = peers, now, later
        self._sending: asyncio.Future | None = None

    def end(self) -> None:
        """The stream is over for the server: its server and world slots free at once."""
        self._peers._release(self._now)
        self._now = []

    def _done(self, _context=None) -> None:
        self.end()
        if self._sending is not None and not self._sending.done():
            self._sending.add_done_callback(self._done)
            return
        self._peers._release(self._later)
        self._later = []


class Peers:
    """The open streams of one server, by peer, world and kind (event loop only: no lock)."""

    def __init__(self, bounds: limits.Limits = limits.DEFAULT, token: str | None = None):
        self.limits = bounds
        # the token itself is never a key or a text: a refusal names the peer
        self._token = (f"token sha256:{hashlib.sha256(token.encode()).hexdigest()[:8]}"
                       if token else None)
        self.open_count: Counter = Counter()      # (kind, scope, name) -> streams open

    def peer(self, context, authenticated: bool = True) -> str:
        """The peer a call comes from: with a token, every call that presented it is the
        token's; a call open to anyone (``authenticated=False``: health) is its host's, so that
        clients without the token cannot use up the token holders' slots."""
        return (self._token if authenticated else None) or host_of(context.peer())

    def open(self, rpc: str, context, kind: str = STREAM, world: str | None = None,
             authenticated: bool = True) -> Slot:
        """A slot for a stream of ``rpc`` from ``context``'s peer (``world``: a World
        subscription's; ``authenticated``: :meth:`peer`'s), released when the call is done;
        :class:`OverLimit` naming the bound when one is reached, before anything is counted."""
        peer = self.peer(context, authenticated)
        now: list = []
        later = [(STREAM, "peer", peer, "max_peer_streams")]
        if kind == SUBSCRIPTION:
            later.append((SUBSCRIPTION, "peer", peer, "max_peer_subscriptions"))
            now.append((SUBSCRIPTION, "server", "", "max_subscriptions"))
            if world is not None:
                now.append((SUBSCRIPTION, "world", world, "max_world_subscriptions"))
        for key in later + now:
            bound = getattr(self.limits, key[3])
            if self.open_count[key[:3]] >= bound:
                raise limits.over(rpc, f"{_held(key)} {bound} {_noun(key)} open", self.limits,
                                  key[3])
        for key in later + now:
            self.open_count[key[:3]] += 1
        slot = Slot(self, now, later)
        context.add_done_callback(slot._done)
        return slot

    async def write(self, context, message, rpc: str) -> None:
        """``context.write(message)``, or :class:`FellBehind` once it has waited
        ``max_write_wait`` for the client to read (the message may still go, if it ever
        reads)."""
        waiting = _Waiting(self.limits.max_write_wait)
        try:
            await context.write(message)
        except asyncio.CancelledError:
            if not waiting.over:        # the client left, or the server stops
                raise
            raise FellBehind(str(limits.over(
                rpc, f"ended: the client read nothing for {waiting.wait:.6g} s (a write "
                     f"waited)", self.limits, "max_write_wait"))) from None
        finally:
            waiting.timer.cancel()

    def _release(self, keys: list) -> None:
        for key in keys:
            self.open_count[key[:3]] -= 1
            if not self.open_count[key[:3]]:
                del self.open_count[key[:3]]


#: how often a waiting write adds up how long it has waited: a look that comes late (the server's
#: own loop held up, a loaded machine) counts this much at most, so that a client is never ended
#: for the server's pause
WAIT_STEP = 0.1


class _Waiting:
    """The wait of one write, on the event loop's clock, looked at every :data:`WAIT_STEP`:
    once it reaches ``wait``, the writing task is cancelled and ``over`` set (a timer, not
    ``asyncio.wait_for``, which makes a task per write)."""

    def __init__(self, wait: float):
        self.wait, self.waited, self.over = wait, 0.0, False
        self.task = asyncio.current_task()
        self.loop = asyncio.get_running_loop()
        self.at = self.loop.time()
        self.timer = self.loop.call_later(min(WAIT_STEP, wait), self._look)

    def _look(self) -> None:
        now = self.loop.time()
        self.waited += min(now - self.at, WAIT_STEP)
        self.at = now
        if self.waited >= self.wait - 1e-9:
            self.over = True
            assert self.task is not None
            self.task.cancel()
        else:
            self.timer = self.loop.call_later(min(WAIT_STEP, self.wait - self.waited),
                                              self._look)


def _held(key: tuple) -> str:
    kind, scope, name = key[:3]
    if scope == "peer":
        return f"peer {name!r} has"
    if scope == "world":
        return f"world {name!r} has"
    return "the server has"


def _noun(key: tuple) -> str:
    return "subscriptions" if key[0] == SUBSCRIPTION else "streams"


async def exhausted(context, details: str, slot: Slot) -> str:
    """Ends a stream whose client fell behind RESOURCE_EXHAUSTED with ``details``, at once: the
    status is handed to gRPC (an abort in a task of its own) and the handler returns without
    waiting for it to be sent, which happens when the client reads what was written before it,
    or never. gRPC takes the handler's return after an abort as the abort (its end is checked
    for one), so nothing else is sent, and a client that then leaves fails no send the server
    would log. ``slot``'s peer counts stay taken until the status is sent or the client has
    gone; the status code's name."""
    sending = asyncio.ensure_future(context.abort(grpc.StatusCode.RESOURCE_EXHAUSTED, details))
    _sending.add(sending)
    sending.add_done_callback(_sent)
    slot._sending = sending
    await asyncio.sleep(0)      # the abort's first step: the status handed to gRPC
    return grpc.StatusCode.RESOURCE_EXHAUSTED.name


def _sent(task: asyncio.Task) -> None:
    _sending.discard(task)
    if not task.cancelled():
        task.exception()        # the AbortError, or the client's leaving: expected, both


#: the statuses being sent to clients that fell behind (a task needs a reference until done)
_sending: set = set()


class ReadAhead:
    """A stream's requests read ahead of its replies (:func:`read_all` puts them): at most
    ``most`` of them and ``most_bytes`` (one more request when it alone is larger), so that
    HTTP/2 flow control stays the client's backpressure and what a client that stops reading
    leaves here stays small."""

    def __init__(self, most: int, most_bytes: int):
        self.most, self.most_bytes = most, most_bytes
        self._queue: asyncio.Queue = asyncio.Queue(maxsize=most)
        self._bytes = 0
        self._room = asyncio.Event()
        self._room.set()

    async def put(self, item) -> None:
        await self._room.wait()
        if isinstance(item, bytes):
            self._bytes += len(item)
            if self._bytes >= self.most_bytes:
                self._room.clear()
        await self._queue.put(item)

    async def get(self):
        return self._taken(await self._queue.get())

    async def take(self) -> list:
        """The next request (waited for) and every one read behind it, up to the first that
        is not a request (``grpc.aio.EOF``, or a read's exception), which ends the list."""
        items = [await self.get()]
        while isinstance(items[-1], bytes) and not self._queue.empty():
            items.append(self._taken(self._queue.get_nowait()))
        return items

    def _taken(self, item):
        if isinstance(item, bytes):
            self._bytes -= len(item)
            if self._bytes < self.most_bytes:
                self._room.set()
        return item


async def read_all(context, pending: ReadAhead) -> None:
    """Puts every request of a stream into ``pending``, then ``grpc.aio.EOF``; a read that
    fails puts its exception instead, for the writer to raise."""
    try:
        while True:
            request = await context.read()
            await pending.put(request)
            if request is grpc.aio.EOF:
                return
    except Exception as e:   # the writer is still consuming, so this put finds room
        await pending.put(e)
