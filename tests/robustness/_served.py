"""The robustness tests' server: ``dqpose serve`` in a process of its own (a request that held it
would be killed with it, not hang the tests), its health asked with a deadline, its memory read
from /proc, and the probe's requests as messages."""
from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import threading
from contextlib import contextmanager

import grpc
import numpy as np
from grpc_health.v1 import health_pb2, health_pb2_grpc

from dqpose.rpc import geometry
from tests._proc import rss_mb

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
# Long enough for a loaded 2-core machine to answer a health check; far shorter than any of
# the probe's requests held the server before the fixes (6 s to forever).
HEALTH_DEADLINE = 10.0
IDENTITY = np.array([1.0, 0, 0, 0, 0, 0, 0, 0])


class Served:
    """``dqpose serve --port 0 FLAGS`` in its own process: ``.target``, ``.pid``, ``.channel``."""

    def __init__(self, *flags: str):
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "dqpose.cli", "serve", "--port", "0", "--no-call-log",
             *flags],
            cwd=ROOT, stderr=subprocess.PIPE, text=True)
        line = self.proc.stderr.readline()
        try:
            first = json.loads(line)
        except ValueError:
            self.proc.kill()
            raise AssertionError(line + self.proc.stderr.read()) from None
        self.target = first["address"]
        self.pid = self.proc.pid
        # read on, so that the server never blocks on a full pipe; what it logs is kept
        self.log: list[str] = []
        threading.Thread(target=lambda: self.log.extend(self.proc.stderr), daemon=True).start()
        self.channel = grpc.insecure_channel(self.target, options=[
            ("grpc.max_receive_message_length", 64 << 20),
            ("grpc.max_send_message_length", 64 << 20)])

    def health(self, timeout: float = HEALTH_DEADLINE) -> str:
        """The server's health status name; fails the test when it does not answer in time."""
        stub = health_pb2_grpc.HealthStub(self.channel)
        try:
            status = stub.Check(health_pb2.HealthCheckRequest(), timeout=timeout).status
        except grpc.RpcError as e:
            raise AssertionError(f"health not answered: {e.code().name}") from None
        return health_pb2.HealthCheckResponse.ServingStatus.Name(status)

    def rss_mb(self) -> float:
        mb = rss_mb(self.pid)
        assert not math.isnan(mb), "no VmRSS"
        return mb

    def stop(self) -> int | None:
        """SIGTERM, then the exit code (None: it ignored SIGTERM and was killed)."""
        self.channel.close()
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                return self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
                return None
        return self.proc.returncode


@contextmanager
def served(*flags: str):
    s = Served(*flags)
    try:
        yield s
    finally:
        s.stop()


def code_of(call) -> tuple[grpc.StatusCode, str]:
    """``(status code, details)`` of a call (OK and "" when it returns)."""
    try:
        call()
    except grpc.RpcError as e:
        return e.code(), e.details()
    return grpc.StatusCode.OK, ""


def pose(dq=IDENTITY):
    return geometry.dq_to_pose(np.asarray(dq, dtype=np.float64))
