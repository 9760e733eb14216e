"""A client stream that survives its replica: reopened with backoff, its unanswered requests sent
again, its first request's settings sent again on every new stream.

gRPC retries no stream once it has started, so a stream whose replica died (or drained) ends
UNAVAILABLE. Behind a load balancer that hashes ``x-dqpose-world`` the reopened stream reaches
the replica the hash now picks; that replica holds none of the world's soft state (windows,
latency estimates, the world's configuration) and rebuilds it from what the client sends: a call
made before each reopening (``before``: the client's last World.Configure), then the requests the
old replica never acknowledged.

The stream's requests are numbered for the caller across reopenings (the index of the item the
caller's iterator gave); an answer acknowledges every request up to the one it names
(``acked(answer)``: StreamFuse's ``FusedPose.request``; World.Publish answers each request with
one ack, in order, whose ``acked_through`` is that request's sequence), and only unacknowledged
ones are sent again. A server-streaming call (World.Subscribe) is reopened the same way by
:func:`reopened`, its one request sent again.
"""
from __future__ import annotations

import json
import logging
import math
import random
import threading
import time
from collections import deque
from contextlib import closing
from typing import Any, Callable, Generator, Iterable, Iterator, Optional

import grpc

from dqpose.rpc.routing import REPLICA_HEADER, WORLD_HEADER

log = logging.getLogger("dqpose.client")

#: requests kept for resending at most: a stream further ahead of its answers than this loses the
#: oldest (said in a log line), so memory stays bounded
MAX_UNACKED = 4096
#: the first wait before reopening, doubled after each failed attempt up to BACKOFF_MAX (s)
BACKOFF_FIRST = 0.05
BACKOFF_MAX = 1.0


def resumable(e: grpc.RpcError) -> bool:
    """Whether a broken stream is worth reopening: its server went away (UNAVAILABLE: refused,
    reset, shutting down) or the proxy in front of it cut the stream when its replica died:
    HAProxy resets a stream the client still sends on (RST_STREAM CANCEL, which gRPC reports as
    CANCELLED, unlike a cancel of our own: "Locally cancelled") and ends one the client has
    half-closed (a Subscribe) with END_STREAM and no status, which gRPC reports as UNKNOWN
    "Stream removed" (a server's own UNKNOWN comes with its status and its text)."""
    code, details = e.code(), e.details() or ""
    if code == grpc.StatusCode.UNAVAILABLE:
        return True
    if code == grpc.StatusCode.UNKNOWN:
        return details.startswith("Stream removed")
    return (code in (grpc.StatusCode.INTERNAL, grpc.StatusCode.CANCELLED)
            and "RST_STREAM" in details)


def _world(metadata) -> Optional[str]:
    return next((v for k, v in metadata or () if k == WORLD_HEADER), None)


def replica_of(call) -> Optional[str]:
    """The replica that answered ``call`` (a call, a future or grpc's error): its
    ``x-dqpose-replica``, from the initial metadata or, for an answer that had none (a call
    refused before its handler ran, an error), the trailers; None when no dqpose server
    answered (nothing listens, a proxy's own refusal)."""
    for read in ("initial_metadata", "trailing_metadata"):
        if read == "trailing_metadata" and not _ended(call):
            break       # a stream's trailers wait for its end: a server without the header
        try:
            metadata = getattr(call, read)()
        except (grpc.RpcError, AttributeError):     # an error without metadata of that kind
            continue
        for key, value in metadata or ():
            if key == REPLICA_HEADER:
                return value
    return None


def _ended(call) -> bool:
    # grpc's calls are RpcErrors too: only done() tells a live stream from an ended one
    done = getattr(call, "done", None)
    return done is None or done()


class ReplicaLost(grpc.RpcError):
    """A stream broken because its server went away (:func:`resumable`), not reopened: grpc's
    error (HAProxy's cut reads ``UNKNOWN: Stream removed``) said as what it is, and how to have
    such a stream reopened. UNAVAILABLE: a server that went away is what that code is for."""

    def __init__(self, e: grpc.RpcError, reconnect: float):
        self.cause = e
        what = f"{e.code().name}: {e.details()}"
        self._details = (
            f"the stream's server went away (its replica was lost, {what}); a Client made with "
            f"reconnect=SECONDS reopens such a stream on the replica that takes its world over"
            if reconnect <= 0 else
            f"the stream's server went away ({what}) and reopening it found no server to "
            f"answer within reconnect={reconnect:g} s")

    def code(self) -> grpc.StatusCode:
        return grpc.StatusCode.UNAVAILABLE

    def details(self) -> str:
        return self._details

    def trailing_metadata(self):
        return self.cause.trailing_metadata()

    def __str__(self) -> str:
        return f"UNAVAILABLE: {self._details}"


def retry_config(seconds: float, services: Iterable[str]) -> str:
    """gRPC's service config that retries a call of ``services`` (full names) refused before any
    answer, with backoff, within about ``seconds``; the balancer sends the retry to another
    replica. UNAVAILABLE: the replica is gone or draining. CANCELLED: a proxy cut the call as
    its replica closed (nginx). Both are safe to retry: gRPC retries only calls without response
    headers, and every dqpose handler sends its headers (x-dqpose-replica) before it does
    anything, so a call retried never ran."""
    attempts = max(2, min(5, 1 + int(math.log2(1 + seconds / 0.2))))   # gRPC caps it at 5
    policy = {"maxAttempts": attempts, "initialBackoff": "0.2s", "maxBackoff": "1s",
              "backoffMultiplier": 2, "retryableStatusCodes": ["UNAVAILABLE", "CANCELLED"]}
    names = [{"service": s} for s in services]
    return json.dumps({"methodConfig": [{"name": names, "retryPolicy": policy}]})


class Resuming:
    """``answers()`` yields ``(index, answer bytes)`` of a stream opened by ``open_call(requests,
    metadata=...)``: ``index`` is the caller's index of the request the answer acknowledges. The
    requests are ``items`` (bytes each; an exception raised by it ends the stream and is raised
    after the answers before it), ``first`` prefixed to the first request of every stream;
    ``acked(answer)`` the index in its stream of the last request an answer acknowledges (None:
    each request has one answer, in order, World.Publish's). A stream that breaks
    :func:`resumable`-ly is reopened with backoff for up to ``reconnect`` s without an answer
    (0: never; the error is raised), ``before()`` called first (:class:`Reconnecting`)."""

    def __init__(self, open_call: Callable, items: Iterator[bytes], first: bytes,
                 acked: Optional[Callable[[bytes], int]], *, metadata=None,
                 reconnect: float = 0.0, before: Optional[Callable[[], object]] = None,
                 seen: Optional[Callable[[Optional[str]], object]] = None):
        self._open, self._items, self._first = open_call, items, first
        self._acked, self._metadata = acked, metadata
        self.link = Reconnecting(reconnect, before, _world(metadata), seen)
        self._lock = threading.Lock()
        self._source = threading.Lock()
        self._generation = 0
        self._taken = 0
        self._unacked: deque[tuple[int, bytes]] = deque()
        self._resend: deque[tuple[int, bytes]] = deque()
        self.failed: list[Exception] = []

    def _requests(self, generation: int, indices: list[int]):
        k = 0
        while True:
            taken = self._take(generation)
            if taken is None:
                return
            index, data = taken
            indices.append(index)
            yield self._first + data if k == 0 else data
            k += 1

    def _take(self, generation: int) -> Optional[tuple[int, bytes]]:
        """The next request for the stream of ``generation``: one not acknowledged by a stream
        before it, else the caller's next; None when the caller's are done or the stream was
        replaced. The caller's iterator is read outside ``_lock`` (it may wait for an answer, a
        producer in lockstep, and answers take ``_lock`` to acknowledge), and a request to
        resend is taken without waiting for it (a replaced stream's thread may still be inside
        it, waiting for the answer to what is resent)."""
        resent = self._resent(generation)
        if resent is not False:
            return resent
        with self._source:       # one stream's thread at a time reads the caller's iterator
            resent = self._resent(generation)    # again: came while this one waited
            if resent is not False:
                return resent
            try:
                data = next(self._items)
            except StopIteration:
                return None
            except Exception as e:    # raised to the caller, not lost in grpc's thread
                self.failed.append(e)
                return None
            with self._lock:
                index, self._taken = self._taken, self._taken + 1
                if generation != self._generation:
                    # replaced while the caller's iterator ran: the next stream sends it
                    self._resend.append((index, data))
                    return None
                if len(self._unacked) >= MAX_UNACKED:
                    lost = self._unacked.popleft()[0]
                    log.warning(json.dumps({"event": "stream_unacked_dropped",
                                            "request": lost}))
                self._unacked.append((index, data))
                return index, data

    def _resent(self, generation: int):
        """None when the stream was replaced, a request to send again, or False (none)."""
        with self._lock:
            if generation != self._generation:
                return None
            if self._resend:
                taken = self._resend.popleft()
                self._unacked.append(taken)
                return taken
        return False

    def _ack(self, index: int) -> None:
        with self._lock:
            while self._unacked and self._unacked[0][0] <= index:
                self._unacked.popleft()

    def _reopen(self) -> None:
        with self._lock:
            self._generation += 1
            self._resend = deque(self._unacked)
            self._unacked.clear()

    def answers(self) -> Generator[tuple[int, bytes], None, None]:
        indices: list[int] = []      # the open stream's requests, by their number in it

        def open_call():
            nonlocal indices
            indices = []
            return self._open(self._requests(self._generation, indices), metadata=self._metadata)
        with closing(self.link.streams(open_call, lambda: bool(self.failed), self._reopen)) as each:
            for k, data in each:
                index = indices[k if self._acked is None else self._acked(data)]
                self._ack(index)
                yield index, data


class Reconnecting:
    """What every reopened stream does between its streams: the backoff, the log lines (naming
    the stream's ``world``, None without one), the replica it is on (``seen(replica)`` told on
    the first answer and on each move), and ``before`` (a call made before each reopening:
    Configure again)."""

    def __init__(self, reconnect: float, before: Optional[Callable[[], object]] = None,
                 world: Optional[str] = None,
                 seen: Optional[Callable[[Optional[str]], object]] = None):
        self.reconnect, self.before, self.world, self.seen = reconnect, before, world, seen
        self.replica: Optional[str] = None     # the replica of the stream open now
        self.reopened = 0
        self._broken_at: Optional[float] = None
        self._wait = BACKOFF_FIRST

    def reopening(self) -> None:
        """Before a stream opens: after a break, ``before``; its errors are a break too."""
        if self._broken_at is not None and self.before is not None:
            self.before()

    def answered(self, call) -> None:
        """On each answer: the first after a break logs the move."""
        if self._broken_at is not None:
            self._moved(replica_of(call), time.monotonic() - self._broken_at)
            self._broken_at, self._wait = None, BACKOFF_FIRST
        elif self.replica is None:
            self.replica = replica_of(call)
        else:
            return
        if self.seen is not None:
            self.seen(self.replica)

    def given_up(self, e: grpc.RpcError) -> grpc.RpcError:
        """What a break not reopened raises: :class:`ReplicaLost` when the stream's server went
        away, ``e`` itself otherwise."""
        return ReplicaLost(e, self.reconnect) if resumable(e) else e

    def broke(self, e: grpc.RpcError) -> bool:
        """Whether to reopen after ``e`` (:func:`resumable`, and the next try within
        ``reconnect`` s of the break)."""
        now = time.monotonic()
        self._broken_at = self._broken_at if self._broken_at is not None else now
        if not resumable(e) or now - self._broken_at + self._wait > self.reconnect:
            return False
        log.info(json.dumps({"event": "stream_broken", "world": self.world,
                             "replica": self.replica,
                             "code": e.code().name, "retry_in_s": round(self._wait, 3)}))
        return True

    def back_off(self) -> None:
        time.sleep(self._wait * random.uniform(0.5, 1.0))   # jitter: reopenings spread out
        self._wait = min(2 * self._wait, BACKOFF_MAX)

    def streams(self, open_call: Callable[[], Any],
                failed: Callable[[], bool] = lambda: False,
                after: Callable[[], object] = lambda: None
                ) -> Generator[tuple[int, bytes], None, None]:
        """``(k, answer)``: the k-th answer of the stream ``open_call()`` opened, opened again
        after each break (:meth:`broke`) once backed off and ``after()`` was called, until a
        stream ends; a break not reopened raises :meth:`given_up`'s error (the break itself
        when ``failed()``). The stream open is cancelled however this ends."""
        while True:
            call = None
            try:
                self.reopening()
                call = open_call()
                for k, data in enumerate(call):
                    self.answered(call)
                    yield k, data
                return
            except grpc.RpcError as e:
                if failed():
                    raise
                if not self.broke(e):
                    raise self.given_up(e) from None
            finally:
                if call is not None:
                    call.cancel()
            self.back_off()
            after()

    def _moved(self, replica: Optional[str], gap: float) -> None:
        """A log line when the stream came back, naming the replica it left and the one it
        reached (its world moved when they differ)."""
        self.reopened += 1
        log.info(json.dumps({"event": "stream_resumed", "world": self.world,
                             "from": self.replica, "to": replica, "moved": replica != self.replica,
                             "gap_s": round(gap, 3)}))
        self.replica = replica


def reopened(open_call: Callable, reconnect: float,
             before: Optional[Callable[[], object]] = None, world: Optional[str] = None,
             seen: Optional[Callable[[Optional[str]], object]] = None
             ) -> Generator[bytes, None, None]:
    """The answers of a server-streaming call ``open_call()`` (World.Subscribe), opened again
    after a :func:`resumable` break with backoff for up to ``reconnect`` s without an answer
    (``before()`` first each time); the answers of each stream as they come (none is resent:
    the request is the call's one message)."""
    with closing(Reconnecting(reconnect, before, world, seen).streams(open_call)) as each:
        for _, data in each:
            yield data
