"""dqpose.rpc.peers against a real server: every streaming RPC takes a slot of its peer
(max_peer_streams, RESOURCE_EXHAUSTED naming it, the slot taken again once a stream is closed);
the peer of gRPC's address forms; BlendStream's read-ahead bounded in bytes."""
from __future__ import annotations

import asyncio
import queue
import threading

import grpc
import pytest

from dqpose import limits
from dqpose.rpc import blending
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb
from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb
from dqpose.rpc.peers import ReadAhead, host_of
from tests._polling import wait_until
from tests.rpc._grpc_server import ServerThread


@pytest.mark.parametrize("peer, host", [
    ("ipv4:10.0.0.7:51234", "10.0.0.7"),
    ("ipv6:%5B::1%5D:5555", "::1"),
    ("ipv6:[fe80::1]:80", "fe80::1"),
    ("unix:/run/dqpose.sock", "unix:/run/dqpose.sock"),
])
def test_the_peer_is_the_clients_host(peer, host):
    assert host_of(peer) == host


class Held:
    """A client-streaming call kept open (its requests wait on a queue) until :meth:`close`."""

    def __init__(self, channel, method: str, first: bytes | None = None):
        self.requests: queue.Queue = queue.Queue()
        if first is not None:
            self.requests.put(first)
        self.call = channel.stream_stream(method)(iter(self.requests.get, None))
        self.error: grpc.RpcError | None = None
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        try:
            for _ in self.call:
                pass
        except grpc.RpcError as e:
            self.error = e

    def close(self):
        self.requests.put(None)
        self.thread.join(10)


def test_every_stream_takes_a_slot_of_its_peer():
    bound = 3
    with ServerThread(limits=limits.Limits(max_peer_streams=bound)) as server:
        peers = server.running.calls.peers
        channel = grpc.insecure_channel(server.target)
        first = fpb.FuseStreamRequest(output_rate=0.0).SerializeToString()
        held = [Held(channel, "/dqpose.v1.Blending/BlendStream"),
                Held(channel, "/dqpose.v1.Fusion/StreamFuse", first),
                Held(channel, "/dqpose.v1.World/Publish", wpb.PublishRequest().SerializeToString())]
        try:
            assert wait_until(lambda: peers.open_count[("stream", "peer", "127.0.0.1")] == bound,
                              timeout=10)
            over = channel.unary_stream(
                "/dqpose.v1.World/Subscribe",
                request_serializer=wpb.SubscribeRequest.SerializeToString)(wpb.SubscribeRequest())
            with pytest.raises(grpc.RpcError) as e:
                next(over)
            assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
            assert e.value.details() == (
                f"Subscribe: peer '127.0.0.1' has {bound} streams open, over the server's limit "
                f"max_peer_streams = {bound} streams (dqpose serve --max-peer-streams)")
            plan = channel.unary_stream("/dqpose.v1.Trajectories/Plan")(b"")
            with pytest.raises(grpc.RpcError) as e:
                next(plan)
            assert "max_peer_streams" in e.value.details()
            assert all(h.error is None for h in held)
            held[0].close()         # one closed: its slot is taken again
            assert wait_until(lambda: peers.open_count[("stream", "peer", "127.0.0.1")]
                              == bound - 1, timeout=10)
            again = Held(channel, "/dqpose.v1.Blending/BlendStream")
            assert wait_until(lambda: peers.open_count[("stream", "peer", "127.0.0.1")] == bound,
                              timeout=10)
            again.close()
            assert again.error is None
        finally:
            for h in held:
                h.close()
            channel.close()
        assert wait_until(lambda: not peers.open_count, timeout=10), dict(peers.open_count)


def test_read_ahead_takes_what_was_read_up_to_the_end_of_the_stream():
    """take() waits for one request, then hands over every one read behind it (World.Publish
    applies them in one pool job), and stops at the end of the stream or a read's failure."""
    async def run():
        ahead = ReadAhead(8, 1 << 20)
        for item in (b"a", b"b", b"c", grpc.aio.EOF, b"late"):
            await ahead.put(item)
        assert await ahead.take() == [b"a", b"b", b"c", grpc.aio.EOF]
        assert await ahead.take() == [b"late"]
        failed = ValueError("read failed")
        await ahead.put(b"d")
        await ahead.put(failed)
        assert await ahead.take() == [b"d", failed]
        waiting = asyncio.ensure_future(ahead.take())
        await asyncio.sleep(0)
        assert not waiting.done()
        await ahead.put(b"e")
        assert await asyncio.wait_for(waiting, 5) == [b"e"]
    asyncio.run(run())


def test_blend_streams_read_ahead_is_bounded_in_bytes():
    """A reader stops taking requests once what waits for a reply reaches the byte bound (one
    request past it), and goes on as the writer takes them."""
    async def run():
        ahead = ReadAhead(blending.STREAM_READ_AHEAD, blending.STREAM_READ_AHEAD_BYTES)
        size = blending.STREAM_READ_AHEAD_BYTES // 4
        put = 0

        async def reader():
            nonlocal put
            for _ in range(10):
                await ahead.put(b"x" * size)
                put += 1

        task = asyncio.ensure_future(reader())
        for _ in range(10):
            await asyncio.sleep(0)
        assert put == 4             # 4 x a quarter: at the bound, the fifth waits
        assert len(await ahead.get()) == size
        for _ in range(10):
            await asyncio.sleep(0)
        assert put == 5
        for _ in range(5):
            await ahead.get()
        await asyncio.wait_for(task, 5)
        assert put == 10
    asyncio.run(run())


def test_health_watches_are_streams_of_their_peer_too():
    """Health is open to clients without a token: its Watch streams are bounded all the same."""
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    with ServerThread(limits=limits.Limits(max_peer_streams=2)) as server, \
            grpc.insecure_channel(server.target) as channel:
        watch = health_pb2_grpc.HealthStub(channel).Watch
        held = [watch(health_pb2.HealthCheckRequest()) for _ in range(2)]
        for w in held:
            assert next(w).status == health_pb2.HealthCheckResponse.SERVING
        with pytest.raises(grpc.RpcError) as e:
            next(watch(health_pb2.HealthCheckRequest()))
        assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        assert "max_peer_streams = 2 streams" in e.value.details()
        for w in held:
            w.cancel()


def test_watches_without_the_token_take_no_slot_of_the_token_holders():
    """With a token every authenticated call is one peer (the token's): a Watch, open to anyone,
    is its host's, so watchers without the token cannot use up the token holders' streams."""
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    token = "peers-test-token"
    with ServerThread(token=token, limits=limits.Limits(max_peer_streams=2)) as server, \
            grpc.insecure_channel(server.target) as channel:
        watch = health_pb2_grpc.HealthStub(channel).Watch
        held = [watch(health_pb2.HealthCheckRequest()) for _ in range(2)]
        for w in held:
            assert next(w).status == health_pb2.HealthCheckResponse.SERVING
        with pytest.raises(grpc.RpcError) as e:     # the watchers' own bound holds
            next(watch(health_pb2.HealthCheckRequest()))
        assert "peer '127.0.0.1' has 2 streams open" in e.value.details()
        subscribe = channel.unary_stream(
            "/dqpose.v1.World/Subscribe",
            request_serializer=wpb.SubscribeRequest.SerializeToString)
        call = subscribe(wpb.SubscribeRequest(), metadata=[("authorization", f"Bearer {token}")])
        counts = server.running.calls.peers.open_count
        try:        # the token holder's subscription open beside the two watches
            assert wait_until(lambda: call.done() or counts[("stream", "peer", "127.0.0.1")]
                              + sum(n for (kind, scope, name), n in counts.items()
                                    if (kind, scope) == ("stream", "peer")
                                    and name.startswith("token ")) == 3, timeout=10)
            assert not call.done(), call.details()
        finally:
            call.cancel()
            for w in held:
                w.cancel()


def test_a_call_refused_for_its_peers_streams_makes_no_world():
    """A Publish refused for max_peer_streams, and a Subscribe refused for a bad body name, leave
    no world behind (the 256 named worlds of a replica are not taken by refused calls)."""
    with ServerThread(limits=limits.Limits(max_peer_streams=1)) as server, \
            grpc.insecure_channel(server.target) as channel:
        worlds = next(s for s in server.running.servicers if s.NAME == "dqpose.v1.World").hubs
        held = Held(channel, "/dqpose.v1.Blending/BlendStream")
        try:
            assert wait_until(lambda: server.running.calls.peers.open_count[
                ("stream", "peer", "127.0.0.1")] == 1, timeout=10)
            publish = channel.stream_stream("/dqpose.v1.World/Publish")(
                iter([wpb.PublishRequest().SerializeToString()]),
                metadata=[("x-dqpose-world", "refused-publish")])
            with pytest.raises(grpc.RpcError) as e:
                list(publish)
            assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        finally:
            held.close()
        subscribe = channel.unary_stream(
            "/dqpose.v1.World/Subscribe",
            request_serializer=wpb.SubscribeRequest.SerializeToString)(
                wpb.SubscribeRequest(bodies=["a/b"]),
                metadata=[("x-dqpose-world", "refused-subscribe")])
        with pytest.raises(grpc.RpcError) as e:
            next(subscribe)
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert "refused-publish" not in worlds and "refused-subscribe" not in worlds
