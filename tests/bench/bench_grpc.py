"""gRPC benchmark: Blend of 10 poses (1 and 8 clients), BlendStream throughput, where the time
goes (C core vs adapter vs gRPC transport), and memory over many calls.

    .venv/bin/python -m tests.bench.bench_grpc            # full run (~2-3 min)
    .venv/bin/python -m tests.bench.bench_grpc --quick    # smaller counts
    .venv/bin/python -m tests.bench.bench_grpc --server sync   # threaded grpc.server instead
    .venv/bin/python -m tests.bench.bench_grpc --plot docs/bench_grpc.png

The server runs as a separate process (`dqpose serve`, per-call log lines on unless --quiet-log),
like in production. `ghz` (go install github.com/bojand/ghz/cmd/ghz@latest) is used when found
for the load-generator rows: a Go client costs far less per call than a Python one, so its
numbers are the server's; the Python-client rows are what a Python caller sees.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import timeit

import grpc
import numpy as np

from dqpose import dq
from dqpose.rpc._proto.dqpose.v1 import blending_pb2 as pb
from dqpose.rpc._proto.dqpose.v1 import blending_pb2_grpc as pb_grpc
from dqpose.rpc._proto.dqpose.v1 import geometry_pb2 as geo
from dqpose.rpc.blending import Blending
from dqpose.rpc.geometry import pose_msgs, poses_to_dqs
from dqpose.rpc.wire import decode_blend_request
from tests.bench.grpc_servers import (  # noqa: F401 (FUSE_EVERY: other benchmarks import it here)
    FUSE_EVERY,
    ROOT,
    ServerProcess,
)

PROTO = os.path.join(ROOT, "proto")


def request10(seed: int = 0) -> pb.BlendRequest:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(10, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    t = rng.uniform(-1, 1, (10, 3))
    return pb.BlendRequest(poses=[
        geo.Pose(position=geo.Vector3(x=b[0], y=b[1], z=b[2]),
                 orientation=geo.Quaternion(w=a[0], x=a[1], y=a[2], z=a[3]))
        for a, b in zip(q.tolist(), t.tolist())])


STREAM_LEN = 1000   # requests per ghz BlendStream call


def request_measured(seed: int = 0) -> pb.BlendRequest:
    """Ten noisy measurements of one pose (5 degrees, 2 cm): what a fusion client sends. DIB
    takes ~3 steps here, against 14-27 for the uniformly random poses of request10."""
    rng = np.random.default_rng(seed)
    q0 = rng.normal(size=4)
    true = dq.from_pose(q0 / np.linalg.norm(q0), rng.uniform(-1, 1, 3))
    turn = np.zeros((10, 6))
    turn[:, :3] = rng.normal(size=(10, 3)) * np.radians(5) / 2   # log is half the rotation vector
    q, t = dq.to_pose(dq.mul(true, dq.exp(turn)))
    return pb.BlendRequest(poses=pose_msgs(q, t + rng.normal(size=(10, 3)) * 0.02))


def us_per_call(fn, n: int) -> float:
    fn()
    return min(timeit.repeat(fn, number=n, repeat=3)) / n * 1e6


# --------------------------------------------------------------------------- clients

def python_unary(target: str, n: int) -> np.ndarray:
    req = request10()
    with grpc.insecure_channel(target) as ch:
        call = pb_grpc.BlendingStub(ch).Blend
        for _ in range(min(500, n)):
            call(req, timeout=5)
        lat = np.empty(n)
        for i in range(n):
            t0 = time.perf_counter()
            call(req, timeout=5)
            lat[i] = time.perf_counter() - t0
    return lat


def _python_worker(target: str, seconds: float, q) -> None:
    req = request10()
    lat = []
    with grpc.insecure_channel(target) as ch:
        call = pb_grpc.BlendingStub(ch).Blend
        call(req, timeout=5)
        end = time.perf_counter() + seconds
        while (t0 := time.perf_counter()) < end:
            call(req, timeout=5)
            lat.append(time.perf_counter() - t0)
    q.put(lat)


def python_clients(target: str, clients: int, seconds: float) -> tuple[float, np.ndarray]:
    """``clients`` processes (one channel each) for ``seconds``: calls/s and latencies."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    procs = [ctx.Process(target=_python_worker, args=(target, seconds, q)) for _ in range(clients)]
    for p in procs:
        p.start()
    lat = [q.get() for _ in procs]
    for p in procs:
        p.join()
    allat = np.concatenate([np.array(x) for x in lat])
    return len(allat) / seconds, allat


def python_stream(target: str, n: int) -> float:
    """Blends per second through one BlendStream with requests sent ahead."""
    reqs = [request10(i % 16) for i in range(n)]
    with grpc.insecure_channel(target) as ch:
        stub = pb_grpc.BlendingStub(ch)
        for _ in stub.BlendStream(iter(reqs[:200])):
            pass
        t0 = time.perf_counter()
        count = sum(1 for _ in stub.BlendStream(iter(reqs)))
        dt = time.perf_counter() - t0
    assert count == n
    return n / dt


def python_batch(target: str, n: int, batch: int = 500) -> float:
    """Blends per second through BlendBatch calls of ``batch`` requests each."""
    reqs = [request10(i % 16) for i in range(batch)]
    msg = pb.BlendBatchRequest(requests=reqs)
    with grpc.insecure_channel(target) as ch:
        stub = pb_grpc.BlendingStub(ch)
        stub.BlendBatch(msg)
        calls = max(1, n // batch)
        t0 = time.perf_counter()
        for _ in range(calls):
            assert len(stub.BlendBatch(msg).responses) == batch
        dt = time.perf_counter() - t0
    return calls * batch / dt


def dqs10(seed: int = 0) -> np.ndarray:
    """The poses of :func:`request10` as a user holds them: a ``(10, 8)`` array."""
    r = request10(seed)
    return poses_to_dqs(r.poses, "poses")


def client_unary(target: str, n: int) -> np.ndarray:
    """Latencies of ``Client.blend`` (the shipped client: arrays in, array out)."""
    from dqpose.rpc.client import Client

    dqs = dqs10()
    with Client(target) as c:
        for _ in range(min(500, n)):
            c.blend(dqs)
        lat = np.empty(n)
        for i in range(n):
            t0 = time.perf_counter()
            c.blend(dqs)
            lat[i] = time.perf_counter() - t0
    return lat


def client_stream(target: str, n: int) -> float:
    """Blends per second through ``Client.blend_stream`` of ``n`` ``(dqs, None)`` pairs."""
    from dqpose.rpc.client import Client

    sets = [(dqs10(i % 16), None) for i in range(n)]
    with Client(target) as c:
        for _ in c.blend_stream(sets[:200]):
            pass
        t0 = time.perf_counter()
        count = sum(1 for _ in c.blend_stream(sets))
        dt = time.perf_counter() - t0
    assert count == n
    return n / dt


def client_batch(target: str, m: int = 20_000, repeat: int = 3) -> float:
    """Blends per second through ``Client.blend_batch`` of an ``(m, 10, 8)`` array (split by
    the client under the server's 4 MiB and 10,000-request limits)."""
    from dqpose.rpc.client import Client

    sets = np.stack([dqs10(i % 16) for i in range(m)])
    with Client(target, timeout=60) as c:
        c.blend_batch(sets[:500])
        best = float("inf")
        for _ in range(repeat):
            t0 = time.perf_counter()
            out = c.blend_batch(sets)
            best = min(best, time.perf_counter() - t0)
    assert out.shape == (m, 8)
    return m / best


def find_tool(name: str) -> str | None:
    found = shutil.which(name)
    if found:
        return found
    go = shutil.which("go")
    if go:
        gopath = subprocess.run([go, "env", "GOPATH"], capture_output=True,
                                text=True).stdout.strip()
        exe = os.path.join(gopath, "bin", name)
        if os.path.exists(exe):
            return exe
    return None


def ghz(exe: str, target: str, clients: int, n: int, data_path: str,
        procs: int | None = None) -> dict:
    """ghz's summary; ``procs`` caps the Go runtime's threads (GOMAXPROCS): on 2 cores a
    single-client load generator otherwise spins on both and takes CPU from the server."""
    env = dict(os.environ, GOMAXPROCS=str(procs)) if procs else None
    out = subprocess.run(
        [exe, "--insecure", "--proto", os.path.join(PROTO, "dqpose/v1/blending.proto"),
         "--import-paths", PROTO, "--call", "dqpose.v1.Blending/Blend", "-D", data_path,
         "-c", str(clients), "--connections", str(clients), "-n", str(n), "--format", "json",
         target], capture_output=True, text=True, check=True, env=env).stdout
    d = json.loads(out)
    pct = {x["percentage"]: x["latency"] / 1e9 for x in d["latencyDistribution"] or []}
    return {"rps": d["rps"], "p50": pct.get(50, float("nan")), "p99": pct.get(99, float("nan")),
            "errors": {k: v for k, v in d["statusCodeDistribution"].items() if k != "OK"}}


def ghz_stream(exe: str, target: str, data_path: str, per_stream: int, streams: int = 20,
               procs: int | None = None) -> float:
    """Blends per second over ``streams`` BlendStream calls of ``per_stream`` requests each,
    one after another (a Go client: what the server sustains); ``procs`` as in :func:`ghz`."""
    env = dict(os.environ, GOMAXPROCS=str(procs)) if procs else None
    out = subprocess.run(
        [exe, "--insecure", "--proto", os.path.join(PROTO, "dqpose/v1/blending.proto"),
         "--import-paths", PROTO, "--call", "dqpose.v1.Blending/BlendStream", "-D", data_path,
         "-c", "1", "-n", str(streams), "--format", "json", target],
        capture_output=True, text=True, check=True, env=env).stdout
    d = json.loads(out)
    bad = {k: v for k, v in d["statusCodeDistribution"].items() if k != "OK"}
    if bad:
        raise RuntimeError(f"ghz BlendStream: {bad}")
    return d["rps"] * per_stream


def json_body(req: pb.BlendRequest) -> str:
    from google.protobuf import json_format
    return json_format.MessageToJson(req)


# --------------------------------------------------------------------------- main

class _Table:
    """The benchmark's one table, and for --plot each row's rate (blends or messages a second)."""

    def __init__(self) -> None:
        self.rows: list[tuple[str, str, str, str, str]] = []
        self.rates: dict[str, float] = {}

    def row(self, what, p50="", p99="", rate="", note="") -> None:
        self.rows.append((what, p50, p99, rate, note))
        if rate and not what[0].isdigit():          # not the memory row
            self.rates[what.strip()] = float(rate.split()[0].rstrip("/s"))

    def print(self) -> None:
        head = ("what", "p50", "p99", "throughput", "note")
        widths = [max(len(r[i]) for r in self.rows + [head]) for i in range(5)]
        fmt = "| " + " | ".join(f"{{:{w}}}" for w in widths) + " |"
        print(fmt.format(*head))
        print("|" + "|".join("-" * (w + 2) for w in widths) + "|")
        for r in self.rows:
            print(fmt.format(*r))


def _us(x: float) -> str:
    return f"{x * 1e6:.0f} us"


def in_process_rows(t: _Table, req: pb.BlendRequest) -> float:
    """Where the time of one Blend goes without transport; returns what the server runs per
    Blend (us)."""
    dqs = poses_to_dqs(req.poses, "poses")
    core = us_per_call(lambda: dq.dib(dqs, None, 1e-12, 100, return_info=True), 2000)
    conv = us_per_call(lambda: poses_to_dqs(req.poses, "poses"), 2000)
    adapter = us_per_call(lambda: Blending().blend(req), 2000)
    data = req.SerializeToString()
    parse = us_per_call(lambda: pb.BlendRequest.FromString(data), 2000)
    wire = us_per_call(lambda: decode_blend_request(data), 2000)
    b = Blending()
    adapter_bytes = us_per_call(lambda: b.blend_bytes(data), 2000)
    served = us_per_call(lambda: b.blend_wire(data), 2000)
    t.row("C core: dq.dib of 10 poses", f"{core:.1f} us", note="in process")
    t.row("message objects -> array (10 poses)", f"{conv:.1f} us",
          note="in process (fallback path)")
    t.row("wire bytes -> arrays (10 poses, C)", f"{wire:.1f} us", note="in process (served path)")
    t.row("adapter: Blending.blend(request)", f"{adapter:.1f} us",
          note="from message objects, no transport")
    t.row("adapter: Blending.blend_bytes(data)", f"{adapter_bytes:.1f} us",
          note="full path (names errors), no transport")
    t.row("adapter: Blending.blend_wire(data)", f"{served:.1f} us",
          note="what the server runs per Blend: bytes to bytes in C")
    t.row("protobuf parse of the request", f"{parse:.1f} us", note="in process")
    return served


def _ghz_bodies(req: pb.BlendRequest) -> dict[str, str]:
    """ghz's request files: one Blend (``unary``), a stream of them (``stream``), a stream of
    measurements of one pose (``measured``)."""
    bodies = {"unary": json_body(req),
              "stream": "[" + ",".join(json_body(request10(i % 16))
                                       for i in range(STREAM_LEN)) + "]",
              "measured": "[" + ",".join(json_body(request_measured(i))
                                         for i in range(STREAM_LEN)) + "]"}
    paths = {}
    for name, body in bodies.items():
        with tempfile.NamedTemporaryFile("w", suffix=".json", delete=False) as f:
            f.write(body)
        paths[name] = f.name
    return paths


def unary_rows(t: _Table, target: str, n1: int, secs: float, exe, files, served: float) -> int:
    """Blend from each kind of client; returns ghz's error count."""
    lat = python_unary(target, n1)
    p50, p99 = np.percentile(lat, [50, 99])
    t.row("Blend 10 poses, 1 Python client", _us(p50), _us(p99), f"{1 / lat.mean():.0f}/s",
          f"gRPC layer ~{p50 * 1e6 - served:.0f} us of the p50")
    lat = client_unary(target, n1)
    p50, p99 = np.percentile(lat, [50, 99])
    t.row("Blend 10 poses, Client.blend", _us(p50), _us(p99), f"{1 / lat.mean():.0f}/s",
          "the shipped client: (10, 8) array in, (8,) out")
    errors = 0
    if exe:
        g1 = ghz(exe, target, 1, n1, files["unary"])
        t.row("Blend 10 poses, 1 client (ghz)", _us(g1["p50"]), _us(g1["p99"]),
              f"{g1['rps']:.0f}/s", f"errors {g1['errors'] or 0}")
        g1p = ghz(exe, target, 1, n1, files["unary"], procs=1)
        t.row("Blend 10 poses, 1 client (ghz, GOMAXPROCS=1)", _us(g1p["p50"]), _us(g1p["p99"]),
              f"{g1p['rps']:.0f}/s", f"errors {g1p['errors'] or 0}; client on one thread")
        g8 = ghz(exe, target, 8, int(n1 * 3), files["unary"])
        t.row("Blend 10 poses, 8 clients (ghz)", _us(g8["p50"]), _us(g8["p99"]),
              f"{g8['rps']:.0f}/s", f"errors {g8['errors'] or 0}")
        errors += sum(sum(g["errors"].values()) for g in (g1, g1p, g8))
    else:
        t.row("ghz", note="not installed: go install github.com/bojand/ghz/cmd/ghz@latest")
    rate8, lat8 = python_clients(target, 8, secs)
    p50, p99 = np.percentile(lat8, [50, 99])
    t.row("Blend 10 poses, 8 Python client processes", _us(p50), _us(p99), f"{rate8:.0f}/s",
          "clients share the 2 cores with the server")
    return errors


def stream_rows(t: _Table, target: str, n_stream: int, exe, files) -> None:
    """BlendStream from each kind of client."""
    sr = python_stream(target, n_stream)
    t.row("BlendStream 10 poses, 1 stream (Python)", rate=f"{sr:.0f} blends/s",
          note=f"{n_stream} requests sent ahead")
    cs = client_stream(target, n_stream)
    t.row("BlendStream 10 poses, Client.blend_stream", rate=f"{cs:.0f} blends/s",
          note=f"{n_stream} (dqs, None) pairs of (10, 8) arrays")
    if exe:
        gs = ghz_stream(exe, target, files["stream"], STREAM_LEN)
        t.row("BlendStream 10 poses, 1 stream (ghz)", rate=f"{gs:.0f} blends/s",
              note=f"20 streams of {STREAM_LEN} requests")
        gs1 = ghz_stream(exe, target, files["stream"], STREAM_LEN, procs=1)
        t.row("BlendStream 10 poses, 1 stream (ghz, GOMAXPROCS=1)", rate=f"{gs1:.0f} blends/s",
              note="client on one thread")
        gm1 = ghz_stream(exe, target, files["measured"], STREAM_LEN, procs=1)
        t.row("BlendStream 10 measurements of one pose (ghz, GOMAXPROCS=1)",
              rate=f"{gm1:.0f} blends/s", note="5 deg / 2 cm noise: DIB ~3 steps")


def ceiling_rows(t: _Table, n_stream: int, exe, files) -> None:
    """The same clients against a grpc.aio stream that does no work: the transport's ceiling."""
    echo = ServerProcess("echo", True)
    try:
        er = python_stream(echo.target, n_stream)
        t.row("  ceiling: grpc.aio fixed-reply stream (Python)", rate=f"{er:.0f} msgs/s",
              note="same client, server does no work")
        if exe:
            eg = ghz_stream(exe, echo.target, files["stream"], STREAM_LEN)
            t.row("  ceiling: grpc.aio fixed-reply stream (ghz)", rate=f"{eg:.0f} msgs/s",
                  note="same client, server does no work")
            eg1 = ghz_stream(exe, echo.target, files["stream"], STREAM_LEN, procs=1)
            t.row("  ceiling: grpc.aio fixed-reply stream (ghz, GOMAXPROCS=1)",
                  rate=f"{eg1:.0f} msgs/s", note="same client, server does no work")
    finally:
        echo.stop()


def memory_row(t: _Table, srv: ServerProcess, n_mem: int, exe, files) -> int:
    """The server's RSS over many calls; returns ghz's error count."""
    errors = 0
    rss0 = srv.rss_mb()
    t0 = time.perf_counter()
    if exe:
        gm = ghz(exe, srv.target, 8, n_mem, files["unary"])
        errors += sum(gm["errors"].values())
        how = f"ghz, 8 clients, errors {gm['errors'] or 0}"
    else:
        python_unary(srv.target, n_mem)
        how = "Python client"
    dt = time.perf_counter() - t0
    rss1 = srv.rss_mb()
    t.row(f"{n_mem} Blend calls: server RSS", rate=f"{n_mem / dt:.0f}/s",
          note=f"{rss0:.1f} -> {rss1:.1f} MB ({rss1 - rss0:+.1f} MB), {how}")
    return errors


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller counts (~40 s)")
    ap.add_argument("--server", choices=["aio", "sync"], default="aio")
    ap.add_argument("--quiet-log", action="store_true", help="serve with --no-call-log")
    ap.add_argument("--plot", metavar="PATH", help="also save the throughputs as a bar chart (PNG)")
    args = ap.parse_args(argv)

    n1 = 3000 if args.quick else 10000
    secs = 5.0 if args.quick else 10.0
    n_stream = 20000 if args.quick else 50000
    n_mem = 20000 if args.quick else 100000

    t = _Table()
    req = request10()
    served = in_process_rows(t, req)
    exe = find_tool("ghz")
    files = _ghz_bodies(req) if exe else {}
    srv = ServerProcess(args.server, args.quiet_log)
    errors = 0
    try:
        errors += unary_rows(t, srv.target, n1, secs, exe, files, served)
        stream_rows(t, srv.target, n_stream, exe, files)
        ceiling_rows(t, n_stream, exe, files)
        if args.server == "aio":
            br = python_batch(srv.target, n_stream)
            t.row("BlendBatch 10 poses x 500 per call, 1 client", rate=f"{br:.0f} blends/s",
                  note="many blends per message")
            cb = client_batch(srv.target)
            t.row("BlendBatch 10 poses, Client.blend_batch", rate=f"{cb:.0f} blends/s",
                  note="(20000, 10, 8) array in, (20000, 8) out; split in 4 MiB calls")
        errors += memory_row(t, srv, n_mem, exe, files)
    finally:
        rc = srv.stop()
        for path in files.values():
            os.unlink(path)
    t.row("server exit code after SIGTERM", note=str(rc))

    load = os.getloadavg()
    print(f"\ngRPC benchmark ({args.server} server, per-call log "
          f"{'off' if args.quiet_log else 'on'}; loopback; {os.cpu_count()} CPUs, load average "
          f"{load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f})\n")
    t.print()
    if args.plot:
        plot(args.plot, t.rates, f"{os.cpu_count()} CPUs, loopback, call log "
                                 f"{'off' if args.quiet_log else 'on'}")
    return 1 if errors else 0


def plot(path: str, rates: dict[str, float], conditions: str) -> None:
    """Throughput per way of calling, log scale: where a reader sees at a glance which RPC to
    use and how close each is to what grpc.aio allows."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    names = list(rates)[::-1]
    values = [rates[k] for k in names]
    colors = ["0.7" if k.startswith("ceiling") else "C0" for k in names]
    fig, ax = plt.subplots(figsize=(9, 0.32 * len(names) + 1.4))
    ax.barh(range(len(names)), values, color=colors)
    for i, v in enumerate(values):
        ax.text(v, i, f" {v / 1000:.1f}k", va="center", fontsize=8)
    ax.set_yticks(range(len(names)), names, fontsize=8)
    ax.set_xscale("log")
    ax.set_xlabel("blends (or calls, messages) per second")
    ax.set_xlim(right=max(values) * 4)            # room for the value labels
    fig.suptitle(f"dqpose gRPC throughput, 10 poses per blend ({conditions})\n"
                 f"grey: a grpc.aio stream that does no work, the transport's ceiling", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"plot saved to {path}")


if __name__ == "__main__":
    sys.exit(main())
