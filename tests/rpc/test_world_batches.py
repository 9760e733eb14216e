"""World.SubscribeBatches against a real server on 127.0.0.1, beside a plain Subscribe of the
same bodies: the same answers in the same order, the answers one Publish request makes due in
as few messages as the byte bound allows, and a subscriber that falls behind ended the same
way."""
from __future__ import annotations

import grpc
import pytest

from dqpose.limits import Limits, answer_cost
from dqpose.rpc import world as servicer
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb
from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb
from tests._polling import wait_until
from tests.rpc._grpc_server import ServerThread, read_in_thread
from tests.rpc.test_world_service import (  # noqa: F401 (the fixture client)
    SOURCES,
    TWIST,
    client,
    measurements,
)

#: the answers a Publish request here affords: 1,024 fits of the box's two measurements, so
#: that the jump below skips some
FITS = 1024


@pytest.fixture
def server():
    with ServerThread(limits=Limits(max_fused_per_request=FITS * answer_cost(2))) as s:
        yield s


class Raw:
    """One Subscribe or SubscribeBatches call in a thread: every message as it came, and the
    error that ended it."""

    def __init__(self, target: str, rpc: str, **request):
        self.channel = grpc.insecure_channel(target)
        self.call = self.channel.unary_stream(
            f"/dqpose.v1.World/{rpc}", request_serializer=wpb.SubscribeRequest.SerializeToString)(
            wpb.SubscribeRequest(**request))
        self.messages: list[bytes] = []
        self.error: grpc.RpcError | None = None
        self.thread = read_in_thread(self.call, self.messages, grpc.RpcError, self._ended)

    def _ended(self, e: grpc.RpcError) -> None:
        self.error = e

    def stop(self) -> None:
        self.call.cancel()
        self.thread.join(10)
        self.channel.close()


def batches(raw: Raw) -> list[list[fpb.FusedPose]]:
    return [list(wpb.FusedPoseBatch.FromString(m).poses) for m in raw.messages]


def subscribed(server, n: int) -> bool:
    world = next(s for s in server.running.servicers if s.NAME == "dqpose.v1.World")
    return len(world.hub("").subscriptions) == n


def streams(server, client) -> tuple[Raw, Raw]:
    """A Subscribe and a SubscribeBatches of the box at 30 Hz, open, in a world whose window
    spans a 60 s jump (as the subscriptions see it when they open)."""
    client.configure_world(SOURCES, twist_covariance=TWIST, window=60.0, buffer=60.0,
                           max_extrapolation=None)
    pair = (Raw(server.target, "Subscribe", bodies=["box"], rate_hz=30.0),
            Raw(server.target, "SubscribeBatches", bodies=["box"], rate_hz=30.0))
    assert wait_until(lambda: subscribed(server, 2), timeout=10)
    return pair


def jump(client) -> int:
    """One request whose source's time jumps 60 s (1,800 ticks due at once, FITS fitted, the
    rest skipped), then three ordinary ones: the answers a subscription at 30 Hz gets, the error
    included."""
    list(client.publish([measurements("cam1", [0.0], 1), measurements("cam1", [60.0], 2)]
                        + [measurements("cam1", [60.0 + k / 30], 3 + k) for k in (1, 2, 3)],
                        producer="p"))
    return FITS + 1 + 3


def packed(sizes: list[int]) -> int:
    """Messages that answers of ``sizes`` bytes fill, in order, each up to MAX_BATCH_BYTES."""
    messages, room = 0, 0
    for n in sizes:
        if n > room:
            messages, room = messages + 1, servicer.MAX_BATCH_BYTES
        room -= n
    return messages


@pytest.mark.parametrize("cap", [None, 2000])
def test_batches_carry_subscribes_answers_in_order_in_few_messages(server, client, cap,
                                                                   monkeypatch):
    if cap is not None:
        monkeypatch.setattr(servicer, "MAX_BATCH_BYTES", cap)
    plain, batched = streams(server, client)
    n = jump(client)
    assert wait_until(lambda: len(plain.messages) == n and
                      sum(map(len, batches(batched))) == n, timeout=60)
    plain.stop()
    batched.stop()
    got = batches(batched)
    assert [a for b in got for a in b] == [fpb.FusedPose.FromString(m) for m in plain.messages]
    assert got[0][0].HasField("error")      # the skipped ticks named first, as Subscribe does
    # every message within the byte bound, unless it is one answer larger than it
    cap = servicer.MAX_BATCH_BYTES
    assert all(len(b) == 1 or sum(a.ByteSize() for a in b) <= cap for b in got)
    # the answers one request made due are queued together: a message is only ever cut by the
    # bound, so there are at most as many as each request's answers need, packed in order
    per_request: dict[int, list[int]] = {}
    for m in plain.messages:
        a = fpb.FusedPose.FromString(m)
        per_request.setdefault(a.request, []).append(len(m))
    most = sum(map(packed, per_request.values()))
    assert len(got) <= most < n
    if cap == 2000:
        assert len(got) > len(per_request)      # the bound did cut the jump's answers


@pytest.mark.parametrize("bound, value, text", [
    ("MAX_QUEUED", 16, "this subscriber fell 16 answers behind the world (MAX_QUEUED)"),
    ("MAX_QUEUED_BYTES", 20_000, "this subscriber fell 20000 bytes of answers behind the world "
                                 "(MAX_QUEUED_BYTES)"),
])
def test_a_subscriber_that_falls_behind_is_ended_the_same_way(server, client, monkeypatch,
                                                               bound, value, text):
    monkeypatch.setattr(servicer, bound, value)
    plain, batched = streams(server, client)
    jump(client)
    plain.thread.join(30)
    batched.thread.join(30)
    for raw, rpc in ((plain, "Subscribe"), (batched, "SubscribeBatches")):
        assert raw.error is not None and raw.error.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        assert raw.error.details() == (f"{rpc}: {text}; subscribe to fewer bodies or a lower "
                                       f"rate_hz")
        assert raw.messages == []       # the jump's 1,025 answers would have been too many
        raw.stop()
    # both slots free: the subscriptions left the world, the server counts none
    assert wait_until(lambda: subscribed(server, 0), timeout=10)
    assert wait_until(lambda: not server.running.calls.peers.open_count, timeout=10)
