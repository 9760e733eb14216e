"""A recording's World calls replayed in this process: one new World servicer a run, every
recorded step applied as the replay reaches it in the file's order, which is the order the
recorded world applied them (its hub's order, :mod:`dqpose.hub`): each Configure, each Publish
request (numbered within its call as it was), each subscription started and ended where it was,
each call into the named world it was recorded in, its subscriptions' answers handed to their
players in the step that makes them. Each call is a player
(:class:`dqpose.rpc.replay.Player`): a Configure's answer or refusal, a Publish call's acks, a
Subscribe call's answers as the world made them (a recorded subscription's answers are those it
sent before its client left: the ones it had queued beyond are not a difference)."""
from __future__ import annotations

import collections

from dqpose import hub
from dqpose.rpc._proto.dqpose.v1 import world_pb2 as pb
from dqpose.rpc.world import World, interest, status_of

NAME = World.NAME
CONFIGURE, PUBLISH, SUBSCRIBE = (f"{NAME}/{m}" for m in ("Configure", "Publish", "Subscribe"))
#: the World calls a replay feeds (Lookup reads only: its answers depend on no other call)
CALLS = (CONFIGURE, PUBLISH, SUBSCRIBE)


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

    @property
    def hub(self) -> hub.Hub:
        return self.worlds.server.hub(self.call.world, make=True)


class _Configure(_Player):
    def send(self, data: bytes) -> None:
        try:
            self.given.append(self.worlds.server.configure(
                self.hub, pb.WorldConfig.FromString(data)).SerializeToString())
            self.status = ("OK", "")
        except Exception as ex:
            status, details = status_of(ex)
            self.status = (status.name, details)


class _Publish(_Player):
    r = 0

    def send(self, data: bytes) -> None:
        ack = self.worlds.server.publish_bytes(self.hub, data, self.r, f"\0call{self.call.id}")
        self.r += 1
        self.given.append(ack.SerializeToString())


class _Subscribe(_Player):
    sub: hub.Subscription | None = None

    def send(self, data: bytes) -> None:
        # its answers straight into what it gave, in the step that makes them
        self.sub = hub.Subscription(interest(pb.SubscribeRequest.FromString(data)),
                                    self.given.extend, internal=self.call.internal)
        self.hub.subscribe(self.sub)

    def end(self, recorded: int) -> None:
        if self.sub is not None:
            self.hub.unsubscribe(self.sub)


class Worlds:
    """The World servicer a run's World calls are replayed into (new for each run)."""

    def __init__(self):
        self.server = World()

    def open(self, call) -> _Player:
        return {CONFIGURE: _Configure, PUBLISH: _Publish, SUBSCRIBE: _Subscribe}[call.rpc](
            self, call)
