"""A replay's calls fed to a server (:class:`Remote`, :func:`dqpose.rpc.replay.replay`'s
target): each call a gRPC call of its own with the recorded named world (``x-dqpose-world``),
its answers collected by a thread of its own as they come.

The World's calls are fed in the order the recorded world applied them, each step only once the
server has applied the one before: a Configure's answer and a Publish request's ack are waited
for; a subscription is taken as started once its response headers arrive, which the server sends
right before it adds the subscription to its world, with nothing between that yields to another
call (``routing.ReplicaHeaders``, ``World.Subscribe``); a subscription that ended in the
recording is cancelled once it has given as many answers as were recorded (what it would send
beyond is not compared).
"""
from __future__ import annotations

import collections
import queue
import threading
from typing import Any, Optional

import grpc

from dqpose.rpc import replay_world
from dqpose.rpc.fusion import FUSE, STREAM_FUSE
from dqpose.rpc.routing import WORLD_HEADER

#: how long one World step (an ack, a subscription's headers, its recorded answers) is waited
#: for before the replay goes on without it (the comparison then names what is missing)
STEP_SECONDS = 30.0


class _Call:
    """What every call fed to a server has: its answers as they come, its status once done."""

    def __init__(self, channel: grpc.Channel, rpc: str, metadata, timeout: float):
        self.channel, self.rpc, self.metadata, self.timeout = channel, rpc, metadata, timeout
        self.given: collections.deque = collections.deque()
        self.status: Optional[tuple[str, str]] = ("OK", "")
        self.done = threading.Event()
        self.arrived = threading.Condition()
        self.count = 0              # answers received
        self.call: Any = None       # the grpc call, to cancel
        self.thread: Optional[threading.Thread] = None

    def _collect(self, answers) -> None:
        try:
            for a in answers:
                with self.arrived:
                    self.given.append(a)
                    self.count += 1
                    self.arrived.notify_all()
        except grpc.RpcError as e:
            self.status = (e.code().name, e.details() or "")
        finally:
            with self.arrived:
                self.done.set()
                self.arrived.notify_all()

    def _wait_for(self, n: int) -> None:
        """Until ``n`` answers have come, the call has ended or a step's time is over."""
        with self.arrived:
            self.arrived.wait_for(lambda: self.count >= n or self.done.is_set(), STEP_SECONDS)

    def end(self, recorded: int) -> None:
        pass

    def result(self) -> Optional[tuple[str, str]]:
        if self.thread is not None:
            self.thread.join(self.timeout)
        return self.status

    def cancel(self) -> None:
        if self.call is not None:
            self.call.cancel()


class _Unary(_Call):
    """Fuse, and the World's Configure (its answer waited for: a World step)."""

    def send(self, data: bytes) -> None:
        try:
            call: Any = self.channel.unary_unary(f"/{self.rpc}")
            self.given.append(call(data, timeout=self.timeout, metadata=self.metadata))
        except grpc.RpcError as e:
            self.status = (e.code().name, e.details() or "")


class _Stream(_Call):
    """StreamFuse, and the World's Publish (``steps``: each request's ack waited for)."""

    def __init__(self, *args, steps: bool = False):
        super().__init__(*args)
        self.steps = steps
        self.requests: queue.Queue = queue.Queue(maxsize=1024)
        self.sent = 0

    def _requests(self):
        while (data := self.requests.get()) is not None:
            yield data

    def _run(self) -> None:
        call: Any = self.channel.stream_stream(f"/{self.rpc}")
        self.call = call(self._requests(), timeout=self.timeout, metadata=self.metadata)
        self._collect(self.call)

    def send(self, data: bytes) -> None:
        if self.thread is None:
            self.thread = threading.Thread(target=self._run, name=f"replay {self.rpc}",
                                           daemon=True)
            self.thread.start()
        self._put(data)
        self.sent += 1
        if self.steps:
            self._wait_for(self.sent)

    def _put(self, data) -> None:
        while not self.done.is_set():
            try:
                self.requests.put(data, timeout=0.1)
                return
            except queue.Full:
                continue

    def end(self, recorded: int) -> None:
        if self.thread is not None:
            self._put(None)

    def result(self) -> Optional[tuple[str, str]]:
        status = super().result()
        # a Publish stream's end is its producer's doing: only the server's refusal is its own
        return None if self.steps and status == ("OK", "") else status


class _Subscribe(_Call):
    def _run(self, data: bytes) -> None:
        call: Any = self.channel.unary_stream(f"/{self.rpc}")
        self.call = call(data, timeout=self.timeout, metadata=self.metadata)
        self.started.set()
        self._collect(self.call)

    def send(self, data: bytes) -> None:
        self.started = threading.Event()
        self.thread = threading.Thread(target=self._run, args=(data,),
                                       name=f"replay {self.rpc}", daemon=True)
        self.thread.start()
        self.started.wait(STEP_SECONDS)
        try:
            self.call.initial_metadata()
        except (grpc.RpcError, AttributeError):
            pass            # refused or not started: its status says so

    def end(self, recorded: int) -> None:
        self._wait_for(recorded)
        self.cancel()

    def result(self) -> Optional[tuple[str, str]]:
        status = super().result()
        # its client leaving (this replay's cancel) is the recorded end, not the server's
        return None if status is not None and status[0] in ("OK", "CANCELLED") else status


class Remote:
    """A server at ``channel`` (``metadata``: a bearer token's, when it needs one); each call at
    most ``timeout`` s."""

    def __init__(self, channel: grpc.Channel, metadata=None, timeout: float = 600.0):
        self.channel, self.metadata, self.timeout = channel, tuple(metadata or ()), timeout

    def begin(self) -> None:
        pass

    def open(self, call):
        metadata = self.metadata + (((WORLD_HEADER, call.world),) if call.world else ())
        args = (self.channel, call.rpc, metadata or None, self.timeout)
        if call.rpc == replay_world.SUBSCRIBE:
            return _Subscribe(*args)
        if call.rpc in (FUSE, replay_world.CONFIGURE):
            return _Unary(*args)
        assert call.rpc in (STREAM_FUSE, replay_world.PUBLISH), call.rpc
        return _Stream(*args, steps=call.rpc == replay_world.PUBLISH)
