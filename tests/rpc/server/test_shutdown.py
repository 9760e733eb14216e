"""Shutdown of a `dqpose serve` process: calls after SIGTERM, health during the drain delay, open
watches."""
from __future__ import annotations

import json
import signal
import subprocess
import sys

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

from tests.rpc.server._blending import (
    ROOT,
    _blend_ok,
    _code,
)

# --------------------------------------------------------------------------- shutdown

def _serve(*flags) -> tuple[subprocess.Popen, str]:
    """``dqpose serve --port 0 FLAGS`` in its own process; (process, address) once it serves."""
    proc = subprocess.Popen([sys.executable, "-m", "dqpose.cli", "serve", "--port", "0", *flags],
                            cwd=ROOT, stderr=subprocess.PIPE, text=True)
    line = proc.stderr.readline()
    try:
        first = json.loads(line)
    except ValueError:
        proc.kill()
        raise AssertionError(line + proc.stderr.read()) from None
    assert first["event"] == "serving", first
    return proc, first["address"]


def _log_after(proc) -> list[dict]:
    """The JSON lines the server logs until it exits (it must exit with 0)."""
    assert proc.wait(timeout=60) == 0
    return [json.loads(x) for x in proc.stderr.read().splitlines() if x.startswith("{")]


@pytest.mark.parametrize("run", range(3))
def test_calls_arriving_after_sigterm_are_unavailable_never_cancelled(run):
    # UNAVAILABLE is what retry policies retry (on another server where there is one);
    # CANCELLED is not retried. A call may still be served if it reaches the server before the
    # signal does; from the first refusal on, every call is refused, the same way.
    proc, target = _serve()
    try:
        with grpc.insecure_channel(target) as ch:
            assert _code(lambda: _blend_ok(ch))[0] == grpc.StatusCode.OK
            proc.send_signal(signal.SIGTERM)
            codes = []
            while not codes or codes[-1] == grpc.StatusCode.OK:
                codes.append(_code(lambda: _blend_ok(ch))[0])
                assert len(codes) < 1000, "still served long after SIGTERM"
            assert codes[-1] == grpc.StatusCode.UNAVAILABLE, codes[-1]
            for _ in range(5):
                code, details = _code(lambda: _blend_ok(ch))
                assert code == grpc.StatusCode.UNAVAILABLE, code
                assert details == "server is shutting down", details
        lines = _log_after(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    blends = [x["code"] for x in lines if x.get("rpc") == "Blend"]
    # every call answered is logged once, with the code its client got
    assert blends == ["OK"] + [c.name for c in codes] + ["UNAVAILABLE"] * 5, blends


def test_health_says_not_serving_for_the_drain_delay_before_the_listener_closes():
    proc, target = _serve("--drain", "5")
    try:
        with grpc.insecure_channel(target) as ch:
            health = health_pb2_grpc.HealthStub(ch)

            def check():
                return health.Check(health_pb2.HealthCheckRequest(), timeout=5).status

            assert check() == health_pb2.HealthCheckResponse.SERVING
            proc.send_signal(signal.SIGTERM)
            status = check()
            while status == health_pb2.HealthCheckResponse.SERVING:
                status = check()
            # a load balancer polling health sees NOT_SERVING, not a closed port
            assert status == health_pb2.HealthCheckResponse.NOT_SERVING
            assert _code(lambda: _blend_ok(ch))[0] == grpc.StatusCode.UNAVAILABLE
            assert proc.poll() is None
        lines = _log_after(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert {"event": "shutting_down", "drain_s": 5.0, "grace_s": 10.0} in lines


def test_an_open_health_watch_ends_at_shutdown_and_does_not_hold_the_process():
    # A grace period of ten minutes: the process ends long before it only if the watch ends.
    proc, target = _serve("--grace", "600", "--drain", "0.2")
    try:
        with grpc.insecure_channel(target) as ch:
            watch = health_pb2_grpc.HealthStub(ch).Watch(health_pb2.HealthCheckRequest(),
                                                         timeout=60)
            assert next(watch).status == health_pb2.HealthCheckResponse.SERVING
            proc.send_signal(signal.SIGTERM)
            assert next(watch).status == health_pb2.HealthCheckResponse.NOT_SERVING
            assert list(watch) == []        # ended by the server, with OK
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
