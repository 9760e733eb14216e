"""A recording's World calls replayed in this process: one new World servicer a run, every
recorded step applied as the replay reaches it in the file's order, which is the order the
recorded world applied them (:mod:`dqpose.rpc.world_record`): each Configure, each Publish
request (numbered within its call as it was), each subscription started and ended where it was,
each call into the named world it was recorded in. Each call is a player
(:class:`dqpose.rpc.replay.Player`): a Configure's answer or refusal, a Publish call's acks, a
Subscribe call's answers as the world made them (a recorded subscription's answers are those it
sent before its client left: the ones it had queued beyond are not a difference)."""
from __future__ import annotations

import collections

from dqpose.rpc._proto.dqpose.v1 import world_pb2 as pb
from dqpose.rpc.world import Subscription, World, status_of

NAME = World.NAME
CONFIGURE, PUBLISH, SUBSCRIBE = (f"{NAME}/{m}" for m in ("Configure", "Publish", "Subscribe"))
#: the World calls a replay feeds (Lookup reads only: its answers depend on no other call)
CALLS = (CONFIGURE, PUBLISH, SUBSCRIBE)


class _AtOnce:
    """What a subscription hands its answers to: delivered at once (no event loop here)."""

    @staticmethod
    def call_soon_threadsafe(fn, *args) -> None:
        fn(*args)


class _Player:
    """What every World call's player has: the answers made and not yet compared, its status
    (None: the recorded one, a stream's end being its client's doing)."""

    def __init__(self, worlds: "Worlds", call):
        self.worlds, self.call = worlds, call
        self.given: collections.deque = collections.deque()
        self.status: tuple[str, str] | None = None

    def end(self, recorded: int) -> None:
        pass

    def result(self) -> tuple[str, str] | None:
        return self.status

    def cancel(self) -> None:
        pass


class _Configure(_Player):
    def send(self, data: bytes) -> None:
        world = self.worlds.server.cell(self.call.world, make=True)
        try:
            self.given.append(world.configure(pb.WorldConfig.FromString(data))
                              .SerializeToString())
            self.status = ("OK", "")
        except Exception as ex:
            status, details = status_of(ex)
            self.status = (status.name, details)


class _Publish(_Player):
    r = 0

    def send(self, data: bytes) -> None:
        world = self.worlds.server.cell(self.call.world, make=True)
        ack = world.publish_bytes(data, self.r, f"\0call{self.call.id}")
        self.r += 1
        self.given.append(ack.SerializeToString())
        self.worlds.deliver()


class _Subscribe(_Player):
    sub: Subscription | None = None

    def send(self, data: bytes) -> None:
        world = self.worlds.server.cell(self.call.world, make=True)
        request = pb.SubscribeRequest.FromString(data)
        options = world.world.options
        self.sub = Subscription(request.bodies, request.rate_hz, request.relative_to, _AtOnce(),
                                options.max_delay, options.window)
        with world.lock:
            world.subscriptions.add(self.sub)
        self.worlds.subscribed[self.call.id] = self

    def end(self, recorded: int) -> None:
        if self.sub is not None:
            world = self.worlds.server.cell(self.call.world, make=True)
            with world.lock:
                world.subscriptions.discard(self.sub)
            self.worlds.subscribed.pop(self.call.id, None)


class Worlds:
    """The World servicer a run's World calls are replayed into (new for each run)."""

    def __init__(self):
        self.server = World()
        self.subscribed: dict[int, _Subscribe] = {}

    def open(self, call) -> _Player:
        return {CONFIGURE: _Configure, PUBLISH: _Publish, SUBSCRIBE: _Subscribe}[call.rpc](
            self, call)

    def deliver(self) -> None:
        """What the last Publish request queued to each subscription, into its answers."""
        for s in self.subscribed.values():
            sub = s.sub
            assert sub is not None
            while not sub.queue.empty():
                a = sub.take()
                if a is not None:       # answers are serialized when made
                    s.given.append(a)
