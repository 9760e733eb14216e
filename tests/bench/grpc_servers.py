"""The servers the gRPC benchmarks measure, each in its own process (:class:`ServerProcess`):
``dqpose serve`` as shipped, the same Blending adapter behind grpc's threaded server (``sync``),
and the transport's ceiling (``echo``: grpc.aio answering with fixed replies, doing no work).

    .venv/bin/python -m tests.bench.grpc_servers echo|sync     # what ServerProcess starts
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
from concurrent import futures

import grpc
import numpy as np

from dqpose.rpc._proto.dqpose.v1 import blending_pb2 as pb
from dqpose.rpc._proto.dqpose.v1 import blending_pb2_grpc as pb_grpc
from dqpose.rpc.blending import Blending
from tests._proc import rss_mb

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


class _SyncBlending(pb_grpc.BlendingServicer):
    """The same adapter behind the threaded server, for comparison only."""

    def __init__(self):
        self.b = Blending()

    def Blend(self, request, context):
        try:
            return self.b.blend(request)
        except ValueError as e:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(e))

    def BlendStream(self, request_iterator, context):
        for r in request_iterator:
            yield self.b.blend(r)


def serve_sync(port: int) -> None:
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=8),
                         options=[("grpc.so_reuseport", 0)])
    pb_grpc.add_BlendingServicer_to_server(_SyncBlending(), server)
    from grpc_reflection.v1alpha import reflection
    reflection.enable_server_reflection(("dqpose.v1.Blending", reflection.SERVICE_NAME), server)
    port = server.add_insecure_port(f"127.0.0.1:{port}")
    server.start()
    print(json.dumps({"event": "serving", "address": f"127.0.0.1:{port}"}), file=sys.stderr,
          flush=True)
    server.wait_for_termination()


FUSE_EVERY = 20     # bench_fusion_stream's scene: 100 answers/s at 2,000 messages/s


def fused_reply():
    """A FusedPose of the size bench_fusion_stream's answers have: 18 measurements with times."""
    from dqpose import dq, fusion, lie
    from dqpose.rpc.fusion_convert import fused_to_msg

    rng = np.random.default_rng(0)
    t = np.arange(18) * 0.005
    Z = dq.mul(lie.se3_exp(rng.normal(size=6)), lie.se3_exp(t[:, None] * rng.normal(size=6)))
    f = fusion.fuse(Z, np.broadcast_to(np.eye(6) * 1e-6, (18, 6, 6)), times=t)
    msg = fused_to_msg(f, "body0", f.time)
    msg.measurements.extend(range(18))
    return msg


def serve_echo(port: int) -> None:
    """The transport ceiling: grpc.aio answering each BlendStream request with one fixed
    pre-serialized reply, with the server's read-ahead but none of its work."""
    import asyncio

    import uvloop

    from tests.bench.bench_grpc import request10

    reply = pb.BlendResponse(pose=request10().poses[0], iterations=3).SerializeToString()
    fused = fused_reply()

    async def stream(request_iterator, context):
        pending: asyncio.Queue = asyncio.Queue(maxsize=64)

        async def read():
            while True:
                r = await context.read()
                await pending.put(r)
                if r is grpc.aio.EOF:
                    return
        reader = asyncio.ensure_future(read())
        try:
            while await pending.get() is not grpc.aio.EOF:
                await context.write(reply)
        finally:
            reader.cancel()

    async def fuse_stream(request_iterator, context):
        # StreamFuse's transport alone (bench_fusion_stream): requests taken as bytes and not
        # read, one fused pose of a typical size after every FUSE_EVERY-th, naming it
        r = 0
        async for _ in request_iterator:
            if r % FUSE_EVERY == FUSE_EVERY - 1:
                fused.request = r
                await context.write(fused.SerializeToString())
            r += 1

    async def run():
        server = grpc.aio.server(options=[("grpc.so_reuseport", 0)])
        handler = grpc.stream_stream_rpc_method_handler(stream)
        server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(
            "dqpose.v1.Blending", {"BlendStream": handler}),))
        server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(
            "dqpose.v1.Fusion", {"StreamFuse": grpc.stream_stream_rpc_method_handler(
                fuse_stream)}),))
        bound = server.add_insecure_port(f"127.0.0.1:{port}")
        await server.start()
        print(json.dumps({"event": "serving", "address": f"127.0.0.1:{bound}"}),
              file=sys.stderr, flush=True)
        await server.wait_for_termination()

    uvloop.run(run())


class ServerProcess:
    """A server of ``kind`` in its own process: "aio" (``dqpose serve`` with ``extra`` flags),
    "sync" or "echo"; ``target`` its address, ``events`` its JSON log lines until it served,
    ``rss_mb()``, ``stop()`` (SIGTERM)."""

    def __init__(self, kind: str, quiet_log: bool, extra: tuple = ()):
        if kind == "echo":
            cmd = [sys.executable, "-m", "tests.bench.grpc_servers", "echo"]
        elif kind == "aio":
            cmd = [sys.executable, "-m", "dqpose.cli", "serve", "--port", "0", "--grace", "2",
                   *(["--no-call-log"] if quiet_log else []), *extra]
        else:
            cmd = [sys.executable, "-m", "tests.bench.grpc_servers", "sync"]
        self.log = tempfile.TemporaryFile("w+")
        self.proc = subprocess.Popen(cmd, cwd=ROOT, stderr=subprocess.PIPE, text=True)
        # the JSON events before it serves (--live says its port first), the last one its address
        self.events: list = []
        while "address" not in (self.events or [{}])[-1]:
            line = self.proc.stderr.readline()
            if not line:
                raise RuntimeError(f"{' '.join(cmd[2:])} ended before serving")
            if line.startswith("{"):
                self.events.append(json.loads(line))
        self.target = self.events[-1]["address"]
        # Drain stderr (one log line per call) into a file so the pipe never blocks the server.
        self._drain = threading.Thread(target=shutil.copyfileobj,
                                       args=(self.proc.stderr, self.log), daemon=True)
        self._drain.start()

    def rss_mb(self) -> float:
        return rss_mb(self.proc.pid)

    def cpu_seconds(self) -> float:
        """The server process's CPU time so far (user + system, all its threads)."""
        with open(f"/proc/{self.proc.pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def stop(self) -> int:
        self.proc.terminate()
        try:
            return self.proc.wait(15)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait()


if __name__ == "__main__":
    {"echo": serve_echo, "sync": serve_sync}[sys.argv[1]](0)
