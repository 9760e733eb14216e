"""The live view (``dqpose serve --live [HOST:PORT]``): Foxglove's WebSocket protocol (subprotocol
``foxglove.sdk.v1``, which Foxglove and Lichtblick open as a "Foxglove WebSocket" connection)
carrying the recording's channels as they are logged, a :class:`~dqpose.record.sink.Sink` of
the writer process, so that neither the server's sockets nor its clients cost the gRPC server
anything. Messages logged while no client subscribes to a channel are not kept, but for a
latched channel's last one (``/tf_static``, :data:`LATCHED`), which a client subscribing later
receives first, as ROS latches ``/tf_static``.

Who may connect is decided before the WebSocket opens (:meth:`LiveServer.refusal`): a browser's
``Origin`` must be one of ``--live-origin``'s, and with the server's bearer token a client gives
it as ``?token=`` in the URL (a browser's WebSocket cannot send headers, and the subprotocol is
fixed); ``--live-insecure`` lifts both. foxglove-sdk's own server takes every client (no hook to
refuse one), so the protocol's server side is here, on ``websockets``: ``serverInfo``,
``advertise``/``unadvertise`` as channels come and go, ``subscribe``/``unsubscribe``, message
data, ``status`` for what it does not take (client publishing, parameters, services).
"""
from __future__ import annotations

import asyncio
import base64
import collections
import itertools
import json
import threading
import time
import urllib.parse

from dqpose import tokens
from dqpose.record.sink import Sink
from dqpose.record.topics import TF_STATIC_TOPIC

SUBPROTOCOL = "foxglove.sdk.v1"
#: messages waiting per client at most; beyond, the oldest are dropped (a slow viewer); a client
#: whose channel announcements reach it is too slow to follow and is disconnected
BACKLOG = 4096
#: clients at once at most (a client beyond is refused 503)
MAX_CLIENTS = 32
#: bytes of one message from a client at most (its subscriptions)
MAX_CLIENT_MESSAGE = 64 << 10
#: a refused client is logged at most this often (s); those in between are counted
REFUSALS_PERIOD = 1.0
_MESSAGE_DATA = b"\x01"
#: the topics whose last message a new subscriber receives (a World's fixed frames, logged once
#: a Configure: a viewer that connects later would never see them)
LATCHED = frozenset({TF_STATIC_TOPIC})


def _status(message: str) -> str:
    return json.dumps({"op": "status", "level": 2, "message": message})


class _Channel:
    """One advertised channel: ``log`` (the writer's thread) sends each subscriber the message
    (``subscribers`` is replaced under the server's lock, never changed, so read without it)."""

    __slots__ = ("server", "id", "advert", "subscribers", "latch", "last")

    def __init__(self, server: "LiveServer", id: int, advert: dict, latch: bool = False):
        self.server, self.id, self.advert = server, id, advert
        self.subscribers: dict[_Client, int] = {}
        # a latched channel's last message, (data, log_time): a new subscriber's first
        self.latch = latch
        self.last: tuple[bytes, int] | None = None

    def log(self, data: bytes, log_time: int) -> None:
        if self.latch:      # under the lock: a subscriber gets the last, then what follows
            with self.server._lock:
                self.last = (data, log_time)
                self._send(self.subscribers, data, log_time)
        else:
            self._send(self.subscribers, data, log_time)

    @staticmethod
    def _send(subscribers: dict, data: bytes, log_time: int) -> None:
        if subscribers:
            stamp = log_time.to_bytes(8, "little")
            for client, sub in subscribers.items():
                client.data(b"".join((_MESSAGE_DATA, sub.to_bytes(4, "little"), stamp, data)))

    def close(self) -> None:
        self.server._unadvertise(self)


class _Client:
    """A connected client: what waits for it (announcements in order, messages at most
    :data:`BACKLOG`, the oldest dropped), filled from any thread, sent by :meth:`send_all`."""

    def __init__(self, ws, loop: asyncio.AbstractEventLoop):
        self.ws, self.loop = ws, loop
        self.control: collections.deque = collections.deque()
        self.messages: collections.deque = collections.deque(maxlen=BACKLOG)
        self.subscriptions: dict[int, _Channel] = {}
        self.wake = asyncio.Event()
        self.woken = self.overflow = False

    def text(self, text: str) -> None:
        if len(self.control) >= BACKLOG:
            self.overflow = True
        else:
            self.control.append(text)
        self._wake()

    def data(self, frame: bytes) -> None:
        self.messages.append(frame)
        self._wake()

    def _wake(self) -> None:
        if not self.woken:
            self.woken = True
            try:
                self.loop.call_soon_threadsafe(self.wake.set)
            except RuntimeError:        # the loop closed: the server is stopping
                pass

    async def send_all(self) -> None:
        while True:
            await self.wake.wait()
            self.wake.clear()
            self.woken = False
            if self.overflow:
                await self.ws.close(1008, "too slow to follow the channels")
                return
            while self.control or self.messages:
                await self.ws.send(self.control.popleft() if self.control
                                   else self.messages.popleft())


class LiveServer(Sink):
    """Serves its channels on ``host:port`` (0: a free port, then :attr:`port` says which) to the
    clients :meth:`refusal` lets in: ``token`` (the server's bearer token, or ``None``) as
    ``?token=``, a browser's ``Origin`` among ``origins``; ``insecure`` lets every client in.
    ``say(**event)`` logs a refused client (at most every :data:`REFUSALS_PERIOD` s).
    ``OSError`` when it cannot listen."""

    def __init__(self, host: str, port: int, token: str | None = None, origins=(),
                 insecure: bool = False, say=None):
        super().__init__()
        self.host = host
        self.token, self.origins, self.insecure = token, frozenset(origins), insecure
        self._say = say or (lambda **event: None)
        self._refused = [0.0, 0]         # when one was last said, how many since
        self._lock = threading.Lock()
        self._ids = itertools.count(1)
        self._live: dict[int, _Channel] = {}
        self._clients: set[_Client] = set()
        self._info = json.dumps({"op": "serverInfo", "name": "dqpose", "capabilities": [],
                                 "metadata": {}, "sessionId": str(time.time_ns())})
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="dqpose-live",
                                        daemon=True)
        self._thread.start()
        try:
            self._server = asyncio.run_coroutine_threadsafe(self._listen(host, port),
                                                            self._loop).result(30)
        except BaseException:
            self._stop_loop()
            raise
        self.port = self._server.sockets[0].getsockname()[1]

    async def _listen(self, host: str, port: int):
        from websockets.asyncio.server import serve

        return await serve(self._serve, host, port, process_request=self._check,
                           subprotocols=[SUBPROTOCOL], compression=None,  # type: ignore[list-item]
                           max_size=MAX_CLIENT_MESSAGE, server_header=None)

    # -- who may connect

    def refusal(self, path: str, headers) -> tuple[int, str] | None:
        """Why a WebSocket request for ``path`` with ``headers`` is refused, as ``(HTTP status,
        reason)``; ``None`` lets it in."""
        offered = {p.strip() for v in headers.get_all("Sec-WebSocket-Protocol")
                   for p in v.split(",")}
        if SUBPROTOCOL not in offered:
            return 400, f"the WebSocket subprotocol {SUBPROTOCOL} is expected"
        if not self.insecure:
            origin = headers.get("Origin")
            if origin is not None and origin not in self.origins:
                return 403, f"origin {origin} is not allowed (dqpose serve --live-origin {origin})"
            if self.token is not None:
                given = urllib.parse.parse_qs(urllib.parse.urlsplit(path).query).get("token")
                if not tokens.matches(given[0] if given else None, self.token):
                    return 401, ("missing or invalid token: connect to ws://HOST:PORT/?token="
                                 "<the server's bearer token>")
        if len(self._clients) >= MAX_CLIENTS:
            return 503, f"{MAX_CLIENTS} clients are connected already"
        return None

    def _check(self, connection, request):
        why = self.refusal(request.path, request.headers)
        if why is None:
            return None
        now = time.monotonic()
        self._refused[1] += 1
        if now - self._refused[0] >= REFUSALS_PERIOD:
            address = connection.remote_address
            self._say(event="live_refused", peer=f"{address[0]}:{address[1]}", status=why[0],
                      reason=why[1], refused=self._refused[1])
            self._refused[:] = [now, 0]
        return connection.respond(why[0], why[1] + "\n")

    # -- the channels (the writer's thread)

    def _open(self, topic: str, message_encoding: str, schema_name: str, schema_encoding: str,
              schema: bytes, metadata: tuple = ()):
        with self._lock:
            ch = _Channel(self, next(self._ids), {}, topic in LATCHED)
            ch.advert = {"id": ch.id, "topic": topic, "encoding": message_encoding,
                         "schemaName": schema_name, "schemaEncoding": schema_encoding,
                         "schema": (base64.b64encode(schema).decode()
                                    if schema_encoding == "protobuf" else schema.decode())}
            self._live[ch.id] = ch
            text = json.dumps({"op": "advertise", "channels": [ch.advert]})
            for client in self._clients:
                client.text(text)
        return ch

    def _unadvertise(self, ch: _Channel) -> None:
        with self._lock:
            if self._live.pop(ch.id, None) is None:
                return
            for client, sub in ch.subscribers.items():
                client.subscriptions.pop(sub, None)
            ch.subscribers = {}
            text = json.dumps({"op": "unadvertise", "channelIds": [ch.id]})
            for client in self._clients:
                client.text(text)

    # -- a client (the server's loop)

    async def _serve(self, ws) -> None:
        from websockets.exceptions import ConnectionClosed

        client = _Client(ws, asyncio.get_running_loop())
        with self._lock:
            self._clients.add(client)
            client.text(self._info)
            client.text(json.dumps({"op": "advertise",
                                    "channels": [c.advert for c in self._live.values()]}))
        sender = asyncio.ensure_future(client.send_all())
        try:
            async for message in ws:
                self._operation(client, message)
        except ConnectionClosed:
            pass
        finally:
            sender.cancel()
            with self._lock:
                self._clients.discard(client)
                for ch in client.subscriptions.values():
                    ch.subscribers = {c: s for c, s in ch.subscribers.items() if c is not client}

    def _operation(self, client: _Client, message) -> None:
        try:
            op = json.loads(message) if isinstance(message, str) else None
        except ValueError:
            op = None
        if not isinstance(op, dict):
            op = {}
        kind = op.get("op")
        if kind == "subscribe" and isinstance(op.get("subscriptions"), list):
            for s in op["subscriptions"]:
                self._subscribe(client, s)
        elif kind == "unsubscribe" and isinstance(op.get("subscriptionIds"), list):
            for sub in op["subscriptionIds"]:
                self._unsubscribe(client, sub)
        else:
            what = "a message that is no JSON operation" if kind is None else repr(kind)
            client.text(_status(f"not taken: {what} (this server takes subscribe and "
                                f"unsubscribe)"))

    def _subscribe(self, client: _Client, s) -> None:
        sub = s.get("id") if isinstance(s, dict) else None
        channel = s.get("channelId") if isinstance(s, dict) else None
        with self._lock:
            ch = self._live.get(channel) if type(channel) is int else None
            if type(sub) is not int or not 0 <= sub < 1 << 32 or ch is None:
                why = f"subscription {s!r}: expected an id within 0..2^32-1 and a channelId " \
                      f"advertised"
            elif sub in client.subscriptions or client in ch.subscribers:
                why = f"subscription {sub}: its id or its channel {channel} is subscribed already"
            else:
                client.subscriptions[sub] = ch
                ch.subscribers = {**ch.subscribers, client: sub}
                if ch.last is not None:
                    ch._send({client: sub}, *ch.last)
                return
        client.text(_status(why))

    def _unsubscribe(self, client: _Client, sub) -> None:
        with self._lock:
            ch = client.subscriptions.pop(sub, None) if type(sub) is int else None
            if ch is not None:
                ch.subscribers = {c: s for c, s in ch.subscribers.items() if c is not client}

    def close(self) -> None:
        self.close_channels()

        async def stop():
            self._server.close()
            await self._server.wait_closed()

        try:
            asyncio.run_coroutine_threadsafe(stop(), self._loop).result(10)
        finally:
            self._stop_loop()

    def _stop_loop(self) -> None:
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(10)
        self._loop.close()
