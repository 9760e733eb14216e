"""Ports, concurrent clients, metrics, SIGTERM draining and cancelled streams."""
from __future__ import annotations

import json
import logging
import queue
import re
import signal
import subprocess
import sys
import threading
import urllib.request

import grpc
import numpy as np
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

from dqpose import dq
from dqpose.rpc._proto.dqpose.v1 import blending_pb2 as pb
from dqpose.rpc._proto.dqpose.v1 import blending_pb2_grpc as pb_grpc
from dqpose.rpc.server import ServerConfig, start
from tests._polling import wait_until
from tests.rpc._grpc_server import ServerThread
from tests.rpc.server._blending import (
    ROOT,
    _blend_ok,
    _code,
    _poses,
    blend_req,
    msg_to_dq,
    random_poses,
    same_pose,
    socket_free_port,
)

# --------------------------------------------------------------------------- lifecycle

def test_second_server_on_the_same_port_fails(server):
    import asyncio

    from dqpose.rpc.server import AddressInUse

    with pytest.raises(AddressInUse, match=f"^cannot listen on 127.0.0.1:{server.port}: address "
                                           f"already in use$") as e:
        asyncio.run(start(ServerConfig(port=server.port)))
    assert e.value.setting == "port"
    res = subprocess.run([sys.executable, "-m", "dqpose.cli", "serve", "--port", str(server.port)],
                         capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert res.returncode == 2
    # one line, ours (not gRPC core's bind log), naming the flag to change
    assert res.stderr == (f"dqpose serve: error: cannot listen on 127.0.0.1:{server.port}: "
                          f"address already in use; choose another --port\n")


def test_metrics_port_in_use_names_the_metrics_flag(server):
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        res = subprocess.run([sys.executable, "-m", "dqpose.cli", "serve", "--port", "0",
                              "--metrics-port", str(port)],
                             capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert res.returncode == 2
    assert res.stderr == (f"dqpose serve: error: cannot serve metrics on 127.0.0.1:{port}: "
                          f"address already in use; choose another --metrics-port\n")


def test_concurrent_clients_get_their_own_answers(server):
    errors = []

    def worker(seed):
        rng = np.random.default_rng(seed)
        with grpc.insecure_channel(server.target) as ch:
            s = pb_grpc.BlendingStub(ch)
            for _ in range(40):
                q, t = random_poses(rng, 5)
                try:
                    same_pose(msg_to_dq(s.Blend(blend_req(q, t), timeout=10).pose),
                              dq.dib(dq.from_pose(q, t)))
                except Exception as e:  # collected: assertion errors in threads are lost
                    errors.append(e)

    threads = [threading.Thread(target=worker, args=(i,)) for i in range(8)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert not errors, errors[:3]


def test_metrics_count_calls():
    with socket_free_port() as port, ServerThread(metrics_port=port) as s:
        with grpc.insecure_channel(s.target) as ch:
            _blend_ok(ch)
            _code(lambda: pb_grpc.BlendingStub(ch).Blend(pb.BlendRequest(), timeout=5))

        def scrape() -> str:
            return urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics",
                                          timeout=5).read().decode()
        # a call is counted when its handler has ended, which can be just after its client has
        # the answer: read until both calls are in (or time out and check what was there)
        wait_until(lambda: 'dqpose_grpc_call_seconds_count{rpc="Blend"} 2.0' in scrape(),
                   timeout=10, poll=0.01)
        text = scrape()
    assert re.search(r'dqpose_grpc_calls_total\{code="OK",rpc="Blend"\} 1\.0', text)
    assert re.search(r'dqpose_grpc_calls_total\{code="INVALID_ARGUMENT",rpc="Blend"\} 1\.0', text)
    assert 'dqpose_grpc_call_seconds_count{rpc="Blend"} 2.0' in text




def test_sigterm_drains_in_flight_calls_and_exits_zero():
    proc = subprocess.Popen([sys.executable, "-m", "dqpose.cli", "serve", "--port", "0",
                             "--grace", "20"], cwd=ROOT, stderr=subprocess.PIPE, text=True)
    try:
        first = json.loads(proc.stderr.readline())
        assert first["event"] == "serving"
        target = first["address"]
        with grpc.insecure_channel(target) as ch:
            stub = pb_grpc.BlendingStub(ch)
            requests: queue.Queue = queue.Queue()
            stream = stub.BlendStream(iter(requests.get, None), timeout=60)
            requests.put(blend_req(*_poses(2)))
            next(stream)
            watch = health_pb2_grpc.HealthStub(ch).Watch(health_pb2.HealthCheckRequest(),
                                                         timeout=60)
            assert next(watch).status == health_pb2.HealthCheckResponse.SERVING

            proc.send_signal(signal.SIGTERM)
            assert next(watch).status == health_pb2.HealthCheckResponse.NOT_SERVING
            watch.cancel()
            # the stream that was open before SIGTERM keeps working until the client ends it
            for _ in range(5):
                requests.put(blend_req(*_poses(3)))
                assert next(stream).pose.orientation.w == pytest.approx(1.0)
            requests.put(None)
            assert list(stream) == []
            # new calls are refused once the server drains
            assert _code(lambda: _blend_ok(ch))[0] == grpc.StatusCode.UNAVAILABLE
        assert proc.wait(timeout=30) == 0
        lines = [json.loads(x) for x in proc.stderr.read().splitlines() if x.startswith("{")]
        calls = [x for x in lines if "rpc" in x]
        assert any(x["rpc"] == "BlendStream" and x["code"] == "OK" and x["messages"] == 6
                   for x in calls), calls
        assert all(isinstance(x["ms"], float) for x in calls)
        assert lines[-1] == {"event": "stopped"}
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _call_lines(caplog) -> list[dict]:
    return [json.loads(line) for r in caplog.records if r.name == "dqpose.calls"
            for line in r.getMessage().splitlines()]


def test_calls_cut_when_the_grace_period_ends_are_logged_and_counted(caplog):
    # Streams still open when the grace period runs out are cancelled by gRPC; their handlers
    # record them as they unwind, which must happen before the last flush and before the
    # metrics close: every call that started gets exactly one line and one sample.
    from dqpose.fusion import Source
    from dqpose.rpc import fusion_convert
    from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb

    caplog.set_level(logging.INFO, logger="dqpose.calls")
    first = fpb.FuseStreamRequest(options=fusion_convert.options_msg(sources=[Source("cam")]))
    first.measurements.extend(fusion_convert.measurement_msgs(
        dq.from_pose([1.0, 0, 0, 0], [0.1, 0.2, 0.3])[None], np.eye(6)[None] * 1e-4,
        names=["cam"], bodies=["box"]))
    with socket_free_port() as port:
        s = ServerThread(metrics_port=port)
        with grpc.insecure_channel(s.target) as ch:
            blends: queue.Queue = queue.Queue()
            blend = pb_grpc.BlendingStub(ch).BlendStream(iter(blends.get, None), timeout=60)
            fuses: queue.Queue = queue.Queue()
            fuse = ch.stream_stream(
                "/dqpose.v1.Fusion/StreamFuse",
                request_serializer=fpb.FuseStreamRequest.SerializeToString,
                response_deserializer=fpb.FusedPose.FromString)(iter(fuses.get, None), timeout=60)
            for _ in range(3):
                blends.put(blend_req(*_poses(2)))
                next(blend)
            fuses.put(first)
            assert next(fuse).HasField("pose")
            s.stop(grace=0.2)               # both streams are still open
            blends.put(None)
            fuses.put(None)
        metrics = s.running.metrics
    calls = sorted((c["rpc"], c["code"], c["messages"]) for c in _call_lines(caplog))
    assert calls == [("BlendStream", "CANCELLED", 3), ("StreamFuse", "CANCELLED", 1)], calls
    from prometheus_client import generate_latest
    text = generate_latest(metrics._registry).decode()
    for rpc in ("BlendStream", "StreamFuse"):
        assert re.search(rf'dqpose_grpc_calls_total\{{code="CANCELLED",rpc="{rpc}"\}} 1\.0',
                         text), text


def test_blend_stream_cancelled_mid_way_leaves_the_server_serving(stub):
    # The server reads ahead of its replies; a client that leaves with requests still unread
    # must end the reading task too, and the next stream must see only its own replies.
    rng = np.random.default_rng(21)
    reqs = [blend_req(*random_poses(rng, 4)) for _ in range(300)]
    call = stub.BlendStream(iter(reqs), timeout=10)
    next(call)
    call.cancel()
    with pytest.raises(grpc.RpcError) as e:
        for _ in call:
            pass
    assert e.value.code() == grpc.StatusCode.CANCELLED
    fresh = [blend_req(*random_poses(rng, 3), method=pb.METHOD_DLB) for _ in range(20)]
    got = list(stub.BlendStream(iter(fresh), timeout=10))
    assert len(got) == 20
    for req, r in zip(fresh, got):
        same_pose(msg_to_dq(r.pose), msg_to_dq(stub.Blend(req, timeout=10).pose), atol=1e-12)


def test_a_read_the_servers_stop_ends_is_a_cut_not_a_failure():
    # What grpc's stream reader raises once the grace period has cut the calls (it failed
    # StreamFuse as INTERNAL with an error logged): the installed grpc's own class, so that a
    # rename there fails here.
    from grpc._cython import cygrpc

    from dqpose.rpc.calls import Calls
    calls = Calls()
    assert calls.cut_off(cygrpc._ServerStoppedError("Server already stopped."))
    assert not calls.cut_off(ValueError("a bug"))
    calls.cut = True
    assert calls.cut_off(ValueError("anything, once the calls were cut"))
