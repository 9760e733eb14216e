"""World subscriptions' slots against a real server, reached from two peers (127.0.0.1 and ::1
on a server listening on both): a client that opens subscriptions and never reads them (issue
36, P4) gets its peer's share only, is ended once a write waits max_write_wait, and holds no
slot another client needs, while its calls are still open; the world's and the server's bounds
name themselves; with a token, the token is the peer."""
from __future__ import annotations

import logging
import socket
import threading
import time

import grpc
import pytest

from dqpose import limits
from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb
from dqpose.rpc.client import Client
from tests._polling import wait_until
from tests.rpc._grpc_server import ServerThread
from tests.rpc.test_world_service import SOURCES, TWIST, Collector, measurements

#: a client's channel whose streams buffer almost nothing it has not read (no window growth)
TINY_WINDOWS = [("grpc.http2.bdp_probe", 0), ("grpc.http2.lookahead_bytes", 1024)]


def _ipv6() -> bool:
    try:
        with socket.socket(socket.AF_INET6) as s:
            s.bind(("::1", 0))
        return True
    except OSError:
        return False


needs_ipv6 = pytest.mark.skipif(not _ipv6(), reason="a second peer on this machine is ::1")


def subscribe_raw(target: str, n: int, world: str = "", token: str = "", options=()):
    """``n`` SubscribeBatches calls of every body on one channel, never read: (channel, calls)."""
    channel = grpc.insecure_channel(target, options=list(options))
    metadata = [("x-dqpose-world", world)] if world else []
    if token:
        metadata.append(("authorization", f"Bearer {token}"))
    call = channel.unary_stream("/dqpose.v1.World/SubscribeBatches",
                                request_serializer=wpb.SubscribeRequest.SerializeToString)
    return channel, [call(wpb.SubscribeRequest(), metadata=metadata) for _ in range(n)]


def refused(calls, n: int = 1) -> list:
    """The calls the server has ended, once ``n`` have been (a refusal comes at once)."""
    wait_until(lambda: sum(c.done() for c in calls) >= n, timeout=10)
    return [c for c in calls if c.done()]


def counts(server) -> dict:
    return dict(server.running.calls.peers.open_count)


def subscriptions(server, name: str = "") -> int:
    """Subscriptions open in world ``name`` (0 before it is made)."""
    world = next(s for s in server.running.servicers if s.NAME == "dqpose.v1.World")
    cell = world.hubs.get(name)
    return 0 if cell is None else len(cell.subscriptions)


@needs_ipv6
def test_a_client_that_never_reads_holds_no_slot_another_client_needs(caplog):
    with ServerThread(host="[::]") as server:
        bound = limits.DEFAULT.max_peer_subscriptions
        with Client(server.target) as c:
            c.configure_world(SOURCES, twist_covariance=TWIST, window=10.0)
        channel, calls = subscribe_raw(f"[::1]:{server.port}", bound + 2, options=TINY_WINDOWS)
        try:
            over = refused(calls, 2)
            assert len(over) == 2
            for call in over:
                assert call.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
                assert call.details() == (
                    f"SubscribeBatches: peer '::1' has {bound} subscriptions open, over the "
                    f"server's limit max_peer_subscriptions = {bound} streams (dqpose serve "
                    f"--max-peer-subscriptions)")
            held = [c for c in calls if c not in over]
            assert wait_until(lambda: subscriptions(server) == bound, timeout=10)
            # answers the attacker never reads, until the server has ended all its streams
            ended = threading.Event()
            sent = [0]

            def requests():
                for k in range(1, 100_000):
                    if ended.is_set():
                        return
                    sent[0] = k
                    yield measurements("cam1", [0.01 * k], k)
                    time.sleep(0.002)

            with Client(server.target) as producer:
                feeding = threading.Thread(target=lambda: list(producer.publish(requests(), "p")))
                feeding.start()
                try:
                    assert wait_until(lambda: not subscriptions(server), timeout=60)
                finally:
                    ended.set()
                    feeding.join(30)
            # its calls still open, the attacker holds no server or world slot, only its own
            assert not any(c.done() for c in held)
            attacker = {("stream", "peer", "::1"): bound, ("subscription", "peer", "::1"): bound}
            assert wait_until(lambda: counts(server) == attacker, timeout=10), counts(server)
            # another client subscribes and is answered
            other = Collector(server.target, bodies=["box"])
            assert wait_until(lambda: subscriptions(server) == 1, timeout=10)
            with Client(server.target) as producer:
                list(producer.publish([measurements("cam1", [0.01 * (sent[0] + k)], k)
                                       for k in range(1, 4)], "q"))
            assert wait_until(lambda: other.answers, timeout=10), other.error
            other.stop()
            # what the attacker reads, once it reads: what its window held, then why it ended
            got = 0
            with pytest.raises(grpc.RpcError) as e:
                for _ in held[0]:
                    got += 1
            assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
            assert e.value.details() == (
                "SubscribeBatches: ended: the client read nothing for 1 s (a write waited), "
                "over the server's limit max_write_wait = 1 s (dqpose serve --max-write-wait)")
            assert got >= 1
        finally:
            for c in calls:
                c.cancel()
            channel.close()
        # once its calls are closed, the peer holds nothing; and its leaving was no error
        assert wait_until(lambda: not counts(server), timeout=10), counts(server)
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR], caplog.text


def test_the_world_and_server_bounds_name_themselves():
    bounds = limits.Limits(max_world_subscriptions=2, max_subscriptions=3)
    with ServerThread(limits=bounds) as server:
        channels = []
        try:
            def open_(world: str, n: int):
                channel, calls = subscribe_raw(server.target, n, world)
                channels.append(channel)
                return calls

            a = open_("a", 2)
            assert wait_until(lambda: subscriptions(server, "a") == 2,
                              timeout=10)
            third = open_("a", 1)
            assert refused(third) == third
            assert third[0].details() == (
                "SubscribeBatches: world 'a' has 2 subscriptions open, over the server's limit "
                "max_world_subscriptions = 2 streams (dqpose serve --max-world-subscriptions)")
            b = open_("b", 1)
            assert wait_until(lambda: subscriptions(server, "b"), timeout=10)
            c = open_("c", 1)
            assert refused(c) == c
            assert c[0].code() == grpc.StatusCode.RESOURCE_EXHAUSTED
            assert c[0].details() == (
                "SubscribeBatches: the server has 3 subscriptions open, over the server's limit "
                "max_subscriptions = 3 streams (dqpose serve --max-subscriptions)")
            # one closed: its slot is taken again
            a[0].cancel()
            assert wait_until(lambda: subscriptions(server, "a") == 1,
                              timeout=10)
            again = open_("c", 1)
            assert wait_until(lambda: subscriptions(server, "c"), timeout=10)
            assert not again[0].done() and not b[0].done()
        finally:
            for channel in channels:
                channel.close()


@needs_ipv6
def test_with_a_token_every_holder_of_it_is_one_peer_and_the_token_is_never_said():
    token = "s3cret-token"
    bounds = limits.Limits(max_peer_subscriptions=2)
    with ServerThread(host="[::]", token=token, limits=bounds) as server:
        ch4, first = subscribe_raw(server.target, 1, token=token)
        ch6, second = subscribe_raw(f"[::1]:{server.port}", 2, token=token)
        try:
            over = refused(first + second)
            time.sleep(0.5)     # and no other
            assert len([c for c in first + second if c.done()]) == 1
            details = over[0].details()
            assert details.startswith("SubscribeBatches: peer 'token sha256:")
            assert "has 2 subscriptions open" in details and token not in details
        finally:
            ch4.close()
            ch6.close()
