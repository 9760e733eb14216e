"""A recording's World calls replayed in this process: one new World servicer, every recorded
step applied in the file's order, which is the order the recorded world applied them
(:mod:`dqpose.rpc.world_record`): each Configure, each Publish request (numbered within its call
as it was), each subscription started and ended where it was. What it answers is each call's
:class:`~dqpose.rpc.replay.Outcome`: a Configure's answer or refusal, a Publish call's acks, a
Subscribe call's answers as the world made them (a recorded subscription's answers are those it
sent before its client left: the ones it had queued beyond are not a difference)."""
from __future__ import annotations

from dqpose.rpc._proto.dqpose.v1 import world_pb2 as pb
from dqpose.rpc.world import World, status_of

NAME = World.NAME
CONFIGURE, PUBLISH, SUBSCRIBE = (f"{NAME}/{m}" for m in ("Configure", "Publish", "Subscribe"))
#: the World calls a replay feeds (Lookup reads only: its answers depend on no other call)
CALLS = (CONFIGURE, PUBLISH, SUBSCRIBE)


class _AtOnce:
    """What a subscription hands its answers to: delivered at once (no event loop here)."""

    @staticmethod
    def call_soon_threadsafe(fn, *args) -> None:
        fn(*args)


def run(rec, events, outcome) -> dict:
    """Each World call's ``outcome(answers, code, details)`` (by call id) from replaying
    ``events`` (the recording's, up to where it is cut) in order."""
    from dqpose.rpc.world import Subscription

    # each call into the world it named (recorded with it), as the server kept them apart
    server = World()
    outs: dict[int, object] = {}
    answers: dict[int, list[bytes]] = {}
    subs: dict[int, Subscription] = {}
    published: dict[int, int] = {}
    calls = {c.id: c for c in rec.calls.values() if c.rpc in CALLS and not c.continued}
    for i, e in enumerate(events):
        for c, sub in list(subs.items()):       # subscriptions that ended before this step
            end = calls[c].end_at
            if end is not None and end <= i:
                world = server.cell(calls[c].world, make=True)
                with world.lock:
                    world.subscriptions.discard(sub)
                del subs[c]
        call = calls.get(e.call)
        if call is None or e.kind != "request":
            continue
        world = server.cell(call.world, make=True)
        if call.rpc == CONFIGURE:
            try:
                config = world.configure(pb.WorldConfig.FromString(e.data))
                outs[call.id] = outcome([config.SerializeToString()])
            except Exception as ex:
                status, details = status_of(ex)
                outs[call.id] = outcome([], status.name, details)
        elif call.rpc == PUBLISH:
            r = published.get(call.id, 0)
            published[call.id] = r + 1
            ack = world.publish_bytes(e.data, r, f"\0call{call.id}")
            answers.setdefault(call.id, []).append(ack.SerializeToString())
            for c, sub in subs.items():
                while not sub.queue.empty():
                    a = sub.queue.get_nowait()
                    if a is not None:       # answers are serialized when made
                        answers[c].append(a)
        else:
            request = pb.SubscribeRequest.FromString(e.data)
            options = world.world.options
            sub = Subscription(request.bodies, request.rate_hz, request.relative_to, _AtOnce(),
                               options.max_delay, options.window)
            with world.lock:
                world.subscriptions.add(sub)
            subs[call.id] = sub
            answers[call.id] = []
    for c, got in answers.items():      # a stream's status is its client's doing: the recorded
        outs[c] = outcome(got, calls[c].code or "OK", calls[c].details)
    return outs
