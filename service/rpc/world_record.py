"""The World service's calls recorded (:mod:`dqpose.record`) in the order the world applied them.

A World's answers depend on the one order in which it applied every call's requests (Publish
requests, a subscription's start and end, Configure), not on each call's own order; Publish
requests are applied in the worker pool, where two of them may take the world's lock in another
order than they arrived. So while a call is recorded, recording it and applying it happen
together under :data:`ORDER` (taken before the world's lock): the file holds the requests in the
order the world saw them, and a replay that applies them in the file's order makes the same
answers (:func:`dqpose.rpc.replay.replay`). A call not recorded takes no extra lock.

Every body of a recorded world is recorded, subscribed or not: each world the server makes gets
the recorder's own subscription to all its bodies at ``recorder.world_rate`` Hz of measurement
time (:func:`follow`), a Subscribe call like a client's (marked ``internal`` in the call log),
fitted and recorded where the world makes every subscriber's answers, so that its cost is the
world's own, and replayed like any other.
"""
from __future__ import annotations

import contextlib
import threading

#: held while a recorded World call records and applies one step (before the world's lock)
ORDER = threading.Lock()


def ordered(rec):
    """:data:`ORDER` held (when ``rec`` records) around a Subscribe's start or end."""
    return ORDER if rec.alive else contextlib.nullcontext()


def publish(world, rec, data: bytes, r: int, anonymous: str):
    """``world.publish_bytes(data, r, anonymous)`` (``world`` a world's cell), recorded with its
    ack as one step."""
    if not rec.alive:
        return world.publish_bytes(data, r, anonymous)
    with ORDER:
        rec.measurements(data)
        ack = world.publish_bytes(data, r, anonymous)
        rec.fused(ack)
    return ack


def configure(world, rec, request):
    """``world.configure(request)``, recorded with its answer or refusal as one step."""
    from dqpose.rpc.world import status_of

    if not rec.alive:
        return world.configure(request)
    with ORDER:
        rec.measurements(request)
        try:
            answer = world.configure(request)
        except Exception as e:
            status, details = status_of(e)
            rec.end(status.name, details)
            raise
        rec.fused(answer)
        rec.end("OK")
    return answer


class _Recording:
    """Stands for the event loop of the recorder's own subscription: the answers the world hands
    it (under its lock, in the order it made them) are recorded at once."""

    def __init__(self, rec):
        self.rec = rec

    def call_soon_threadsafe(self, deliver, answers: list) -> None:
        for answer in answers:
            self.rec.fused(answer)


def follow(cell, recorder) -> None:
    """World ``cell`` (just made) followed by the recorder's own subscription to every body,
    when ``recorder`` records a world (its ``world_rate``); the recorder ends it when it
    closes."""
    if recorder.world_rate is None:
        return
    from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb
    from dqpose.rpc._proto.dqpose.v1 import world_pb2 as pb
    from dqpose.rpc.world import Subscription, World

    rec = recorder.call(f"{World.NAME}/Subscribe", pb.SubscribeRequest, fpb.FusedPose,
                        cell.name, internal=True)
    if not rec.alive:       # dropped (the recording behind): its answers could not replay
        return
    options = cell.world.options
    sub = Subscription((), recorder.world_rate, "", _Recording(rec), options.max_delay,
                       options.window)
    with ORDER, cell.lock:
        cell.subscriptions.add(sub)
        rec.measurements(pb.SubscribeRequest(rate_hz=recorder.world_rate))
