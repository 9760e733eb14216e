"""x-dqpose-replica on every answer (initial metadata and trailers, refusals included) and
x-dqpose-world read by ``routing.world_of``, on a real server."""
from __future__ import annotations

import asyncio
import threading

import grpc
import numpy as np
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

from dqpose.rpc import routing
from dqpose.rpc._proto.dqpose.v1 import blending_pb2 as pb
from dqpose.rpc.client import Client
from dqpose.rpc.geometry import dqs_to_poses
from dqpose.rpc.server import ConfigError, ServerConfig
from dqpose.rpc.wire import measurements_wire
from tests.rpc._grpc_server import ServerThread

IDENTITY = np.array([1.0, 0, 0, 0, 0, 0, 0, 0])


def _replica(metadata) -> list[str]:
    return [v for k, v in metadata or () if k == routing.REPLICA_HEADER]


@pytest.fixture(scope="module")
def server():
    with ServerThread(replica_name="replica-a") as s:
        yield s


def test_unary_answer_carries_replica(server):
    with grpc.insecure_channel(server.target) as ch:
        blend = ch.unary_unary("/dqpose.v1.Blending/Blend")
        request = pb.BlendRequest(poses=dqs_to_poses(np.stack([IDENTITY, IDENTITY])))
        _, call = blend.with_call(request.SerializeToString(), timeout=10)
        assert _replica(call.initial_metadata()) == ["replica-a"]
        assert _replica(call.trailing_metadata()) == ["replica-a"]


def test_refused_call_carries_replica(server):
    with grpc.insecure_channel(server.target) as ch:
        blend = ch.unary_unary("/dqpose.v1.Blending/Blend")
        with pytest.raises(grpc.RpcError) as e:
            blend.with_call(pb.BlendRequest().SerializeToString(), timeout=10)
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert _replica(e.value.trailing_metadata()) == ["replica-a"]


def test_stream_and_health_carry_replica(server):
    with grpc.insecure_channel(server.target) as ch:
        stream = ch.stream_stream("/dqpose.v1.Fusion/StreamFuse")
        call = stream(iter([measurements_wire(np.stack([IDENTITY]), bodies=["b"], times=[0.0])]),
                      timeout=10)
        answers = list(call)
        assert answers and _replica(call.initial_metadata()) == ["replica-a"]
        assert _replica(call.trailing_metadata()) == ["replica-a"]
        _, hc = health_pb2_grpc.HealthStub(ch).Check.with_call(
            health_pb2.HealthCheckRequest(), timeout=10)
        assert _replica(hc.initial_metadata()) == ["replica-a"]


def test_shutting_down_refusal_carries_replica():
    s = ServerThread(replica_name="replica-b")
    try:
        s.running.gate.closed = True       # what SIGTERM does first
        with grpc.insecure_channel(s.target) as ch:
            with pytest.raises(grpc.RpcError) as e:
                ch.unary_unary("/dqpose.v1.Blending/Blend")(b"", timeout=10)
        assert e.value.code() == grpc.StatusCode.UNAVAILABLE
        assert _replica(e.value.trailing_metadata()) == ["replica-b"]
        # no headers: a retry policy may still retry the call elsewhere
        assert _replica(e.value.initial_metadata()) == []
    finally:
        s.stop()


def test_default_replica_name_is_the_host_name():
    import socket
    assert ServerConfig().replica_name == socket.gethostname()


@pytest.mark.parametrize("name, problem", [("", "must not be empty"),
                                           ("a b", "printable ASCII"),
                                           ("x" * 254, "254 characters, over the 253"),
                                           (7, "must be a string")])
def test_bad_replica_name_is_refused(name, problem):
    with pytest.raises(ConfigError) as e:
        ServerConfig(replica_name=name)
    assert e.value.setting == "replica_name" and problem in e.value.problem


class _WorldEcho:
    """A real grpc.aio server whose one method answers ``routing.world_of(context)``."""

    def __enter__(self):
        self.loop = asyncio.new_event_loop()
        threading.Thread(target=self.loop.run_forever, daemon=True).start()

        async def echo(request, context):
            try:
                return routing.world_of(context).encode()
            except ValueError as e:
                await context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(e))

        async def start():
            server = grpc.aio.server()
            server.add_generic_rpc_handlers([grpc.method_handlers_generic_handler(
                "t.T", {"Echo": grpc.unary_unary_rpc_method_handler(echo)})])
            port = server.add_insecure_port("127.0.0.1:0")
            await server.start()
            return server, port

        self.server, port = asyncio.run_coroutine_threadsafe(start(), self.loop).result(10)
        self.channel = grpc.insecure_channel(f"127.0.0.1:{port}")
        return self.channel.unary_unary("/t.T/Echo")

    def __exit__(self, *exc):
        self.channel.close()
        asyncio.run_coroutine_threadsafe(self.server.stop(None), self.loop).result(10)
        self.loop.call_soon_threadsafe(self.loop.stop)


def test_world_of_reads_the_header():
    with _WorldEcho() as echo:
        assert echo(b"", metadata=[(routing.WORLD_HEADER, "cell-7")], timeout=10) == b"cell-7"
        assert echo(b"", timeout=10) == b""
        with pytest.raises(grpc.RpcError) as e:
            echo(b"", metadata=[(routing.WORLD_HEADER, "w" * 129)], timeout=10)
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert e.value.details().startswith("x-dqpose-world: 129 characters, over the 128")


def test_client_world_option_sets_the_header():
    with _WorldEcho() as echo, Client("127.0.0.1:1", world="cell-9") as c:
        assert echo(b"", metadata=c.metadata, timeout=10) == b"cell-9"
    with pytest.raises(ValueError, match="^world: only printable ASCII"):
        Client("127.0.0.1:1", world="cell 9")
