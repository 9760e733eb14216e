"""StreamFuse throughput and latency: measurements of many moving bodies streamed in messages of 10
through the shipped ``Client.stream_fuse`` into one server (a separate ``dqpose serve`` process);
one table: measurements/s and messages/s sustained, answers/s, the added latency of the answers
(p50/p99/max), CPU per message of the server and of the client, server RSS at the start and the
end; then the server's per-message cost in process, split into its parts (the served path: C
decoder then tracker; and the protobuf path it replaces), with cProfile.

    .venv/bin/python -m tests.bench.bench_fusion_stream                 # ~1 min
    .venv/bin/python -m tests.bench.bench_fusion_stream --minutes 10    # the memory run
    .venv/bin/python -m tests.bench.bench_fusion_stream --plot docs/bench_fusion_stream.png
    valgrind --tool=callgrind --callgrind-out-file=/dev/null \
        .venv/bin/python -m tests.bench.bench_fusion_stream --in-process 1000   # and 0: Ir/msg

Scene: ``--bodies`` bodies on constant-twist screws, each measured in turn (round robin) by one
of two sources with latencies, 10 measurements a message with full covariances; the server keeps
a ``--window`` per body and answers each body at ``--output-rate`` (ticks on the measurements'
time). The added latency of an answer: from the client handing gRPC the message whose
measurement made the answer due (the answer's ``request``) to the answer's arrival, so it holds
the server's queue, the estimate and both transports. With ``--probe`` every message also
carries an 11th measurement with no body, which the server answers at once with an error entry:
then the table also has the round trip of every message (to its first answer), at the cost of
one error entry a message more for the server and the client. The scene's messages are made
ahead, 256 at a time, so the client's time is the shipped client's. Rows: the transport alone
(the same client and messages against a server that answers as often and fuses nothing: the
floor the added latency is measured against), paced at the target rate (20,000 measurements/s),
and unpaced (as fast as the client sends), which shows the ceiling.
"""
from __future__ import annotations

import argparse
import cProfile
import gc
import io
import os
import pstats
import sys
import threading
import time

import numpy as np

from dqpose import dq, fusion, lie
from dqpose.rpc.client import Batch, Client
from tests.bench.bench_grpc import FUSE_EVERY, ServerProcess

PER_MESSAGE = 10
COV = np.diag(np.r_[np.full(3, np.deg2rad(0.3)), np.full(3, 1e-3)] ** 2)
SOURCES = [fusion.Source("cam", latency=0.03), fusion.Source("arm", latency=0.004)]


class Scene:
    """Message ``i`` holds measurements ``10 i .. 10 i + 9`` of the whole stream: measurement
    ``j`` is of body ``j % bodies`` stamped ``j / rate`` (``rate`` measurements/s in all), by
    the camera or the arm in turn; with ``probe``, plus the probe."""

    def __init__(self, bodies: int, rate: float, seed: int = 0, probe: bool = False):
        rng = np.random.default_rng(seed)
        self.bodies, self.rate, self.probe = bodies, rate, probe
        self.X0 = lie.se3_exp(rng.normal(size=(bodies, 6)))
        self.V = rng.normal(size=(bodies, 6)) * 0.2
        self.names = [f"body{b}" for b in range(bodies)]
        self.cov = np.broadcast_to(COV, (PER_MESSAGE + probe, 6, 6))

    def batches(self, i: int, count: int) -> list[Batch]:
        """Messages ``i .. i + count - 1``, computed together."""
        j = np.arange(i * PER_MESSAGE, (i + count) * PER_MESSAGE)
        b = j % self.bodies
        src = np.where((j // self.bodies) % 2 == 0, 0, 1)
        stamps = j / self.rate
        taken = stamps - np.where(src == 0, 0.03, 0.004)
        Z = dq.mul(self.X0[b], lie.se3_exp(taken[:, None] * self.V[b])).reshape(
            count, PER_MESSAGE, 8)
        stamps = stamps.reshape(count, PER_MESSAGE)
        names = [SOURCES[s].name for s in src.tolist()]
        bodies = [self.names[k] for k in b.tolist()]
        out = []
        for m in range(count):
            rows = slice(m * PER_MESSAGE, (m + 1) * PER_MESSAGE)
            if self.probe:
                out.append(Batch(np.concatenate([Z[m], Z[m, :1]]), self.cov,
                                 names=names[rows] + ["cam"], bodies=bodies[rows] + [""],
                                 times=np.concatenate([stamps[m], stamps[m, :1]])))
            else:
                out.append(Batch(Z[m], self.cov, names=names[rows], bodies=bodies[rows],
                                 times=stamps[m]))
        return out

    def batch(self, i: int) -> Batch:
        return self.batches(i, 1)[0]


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time of process ``pid`` (all its threads)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run(target: str, scene: Scene, seconds: float, msg_rate: float | None, args,
        rss=None, server_pid: int | None = None) -> dict:
    """Stream for ``seconds``; ``msg_rate`` None: unpaced. Latencies after the first second
    (warm-up) only."""
    n_max = int(seconds * (msg_rate or 20000)) + 1
    sent = np.full(n_max, np.nan)
    first_answer = np.full(n_max, np.nan)
    fused = []                  # (request, arrival) of every fused pose
    stop = [False]
    t_start = [0.0]

    def batches():
        t0 = time.perf_counter()
        t_start[0] = t0
        ahead: list = []
        for i in range(n_max):
            if not ahead:
                ahead = scene.batches(i, 256)[::-1]
            b = ahead.pop()
            if msg_rate:
                due = t0 + i / msg_rate
                while (now := time.perf_counter()) < due:
                    time.sleep(min(due - now, 0.0005))
            if time.perf_counter() - t0 > seconds or stop[0]:
                return
            sent[i] = time.perf_counter()
            yield b

    samples = []

    def sample_rss():
        while not stop[0]:
            samples.append((time.perf_counter(), rss()))
            time.sleep(1.0)

    sampler = threading.Thread(target=sample_rss, daemon=True)
    sampler.start()
    # as `dqpose serve` does: a full collection over this process's imports would stall the
    # client ~25 ms, which the latencies would charge to the server
    gc.freeze()
    cpu0 = (_cpu_seconds(server_pid) if server_pid else 0.0, _cpu_seconds(os.getpid()))
    with Client(target) as c:
        for a in c.stream_fuse(batches(), sources=SOURCES, output_rate=args.output_rate,
                               window=args.window):
            now = time.perf_counter()
            if np.isnan(first_answer[a.request]):
                first_answer[a.request] = now
            if a.error is None:
                fused.append((a.request, now))
    cpu1 = (_cpu_seconds(server_pid) if server_pid else 0.0, _cpu_seconds(os.getpid()))
    stop[0] = True
    sampler.join()
    done = ~np.isnan(sent)
    n = int(done.sum())
    elapsed = np.nanmax(sent) - t_start[0]
    req, arrival = np.array(fused, dtype=float).reshape(-1, 2).T
    req = req.astype(np.int64)
    warm = sent[req] > t_start[0] + 1.0
    lat = (arrival - sent[req])[warm]
    msg = done & (sent > t_start[0] + 1.0)
    msg_lat = (first_answer - sent)[msg]
    return dict(messages=n / elapsed, measurements=n * PER_MESSAGE / elapsed,
                answers=len(fused) / elapsed,
                p50=np.percentile(lat, 50) * 1e3, p99=np.percentile(lat, 99) * 1e3,
                max=lat.max() * 1e3, latencies=len(lat),
                msg_p99=np.nanpercentile(msg_lat, 99) * 1e3 if scene.probe else None,
                server_cpu=(cpu1[0] - cpu0[0]) / n * 1e6 if server_pid else float("nan"),
                client_cpu=(cpu1[1] - cpu0[1]) / n * 1e6, rss=samples, n=n,
                lat=lat * 1e3)


def wire_messages(scene: Scene, messages: int) -> list[bytes]:
    """Messages ``0 .. messages - 1`` of the stream as the server receives them (request bytes,
    the options in none of them)."""
    from dqpose.rpc.wire import measurements_wire

    return [measurements_wire(*b) for i in range(0, messages, 256)
            for b in scene.batches(i, min(256, messages - i))]


def in_process(scene: Scene, args, messages: int, warm: int = 500) -> None:
    """``warm`` messages, then ``messages`` more, through the server's per-message path in
    process (``Fusion.stream_step_wire``, answers serialised), and nothing printed: under
    callgrind the instructions per message are ``(Ir(N) - Ir(0)) / N``, which the load of a
    shared machine does not move."""
    from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as pb
    from dqpose.rpc.fusion import Fusion
    from dqpose.rpc.fusion_convert import options_msg

    data = wire_messages(scene, warm + max(messages, 1000))   # the same set-up for every N
    f = Fusion()
    state = f.stream_options(pb.FuseStreamRequest(
        output_rate=args.output_rate, options=options_msg(sources=SOURCES, window=args.window)))
    for r in range(warm + messages):
        for a in f.stream_step_wire(state, data[r], r + 1, r * (PER_MESSAGE + scene.probe))[0]:
            a.SerializeToString()


def _best_us(fn, n, repeat=3):
    """Microseconds a unit of ``fn()``'s ``n``, its best of ``repeat`` runs (a shared machine)."""
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best / n * 1e6


def per_message_cost(scene: Scene, args, messages: int = 6000) -> str:
    """The server's per-message path in process (no transport): request bytes to answers by
    ``Fusion.stream_step_wire`` (what StreamFuse serves: the C decoder, then the tracker), and
    for comparison the protobuf path (bytes parsed, then ``Fusion.stream_step``); cProfile of
    the parts."""
    from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as pb
    from dqpose.rpc.fusion import Fusion
    from dqpose.rpc.fusion_convert import options_msg

    data = wire_messages(scene, messages)
    from dqpose.rpc.fusion_convert import measurements_to_arrays
    from dqpose.rpc.wire import fuse_stream_from_wire

    f = Fusion()

    def stream(rate):
        return f.stream_options(pb.FuseStreamRequest(
            output_rate=rate, options=options_msg(sources=SOURCES, window=args.window)))

    state = stream(args.output_rate)

    def go(lo, hi, state=state, wire=True):
        # r + 1: request 0 is the one with the options, which always takes the protobuf path
        for r in range(lo, hi):
            if wire:
                answers = f.stream_step_wire(state, data[r], r + 1,
                                             r * (PER_MESSAGE + scene.probe))[0]
            else:
                answers = f.stream_step(state, pb.FuseStreamRequest.FromString(data[r]), r + 1,
                                        r * (PER_MESSAGE + scene.probe))
            for a in answers:
                a.SerializeToString()

    # The stream runs over consecutive chunks (a tracker cannot take the same times twice): the
    # best chunk, as the machine is shared.
    chunk = messages // 6

    def chunks(state, pick, wire=True):
        go(0, chunk, state, wire)
        return pick([_best_us(lambda k=k: go(k * chunk, (k + 1) * chunk, state, wire), chunk, 1)
                     for k in range(1, 5)])

    per = chunks(state, np.mean)      # the ticks fall in some chunks: all of them
    # the same messages with no tick due (output_rate 1e-9 Hz: one tick, at 0): the ingest path
    ingest = chunks(stream(1e-9), min)
    ingest_pb = chunks(stream(1e-9), min, wire=False)
    decode = _best_us(lambda: [fuse_stream_from_wire(d) for d in data[:chunk]], chunk)
    parsed = [pb.FuseStreamRequest.FromString(d) for d in data[:chunk]]
    parse = _best_us(lambda: [pb.FuseStreamRequest.FromString(d) for d in data[:chunk]], chunk)
    convert = _best_us(lambda: [measurements_to_arrays(m.measurements, "m", []) for m in parsed],
                 chunk)
    tracker = state.tracker
    bodies = tracker.bodies[:50]
    fit = _best_us(lambda: [tracker.estimate(b, tracker.newest(b) - 0.01) for b in bodies],
             len(bodies))
    size = np.mean([len(tracker.window_of(b).ids) for b in bodies])
    ticks = args.output_rate * args.bodies / (args.rate / PER_MESSAGE)
    out = io.StringIO()
    out.write(
        f"server per-message path in process (parse + stream_step + answers serialised), "
        f"{PER_MESSAGE} measurements{' + probe' if scene.probe else ''} a message:\n"
        f"  all: {per:.0f} us/message at output_rate {args.output_rate:g} Hz "
        f"({ticks:.3f} estimates a message on average)\n"
        f"  ingest only (no tick due): {ingest:.0f} us/message, of which the C decoder "
        f"(decode and every check) {decode:.1f} us; the rest is Python: "
        f"{'the probe error entry, ' if scene.probe else ''}Tracker.ingest with checked codes "
        f"(window floor, store), the service's bookkeeping\n"
        f"  the same through the protobuf path: {ingest_pb:.0f} us/message, of which protobuf "
        f"parse {parse:.1f} us and messages to arrays {convert:.0f} us; the rest "
        f"Tracker.ingest (batched checks, window arrays) and the bookkeeping\n"
        f"  one estimate (Tracker.estimate, {size:.0f} measurements in the window): "
        f"{fit / 1e3:.2f} ms\n")
    _profile(lambda: go(5 * chunk, messages), out)
    return out.getvalue()


def _profile(run, out) -> None:
    """cProfile of ``run()``: the per-message path's parts, written to ``out``."""
    pr = cProfile.Profile()
    pr.enable()
    run()
    pr.disable()
    st = pstats.Stats(pr, stream=out)
    st.sort_stats("cumulative").print_stats(
        r"stream_step|update|ingest|_admit|refusals|measurements_to_arrays|_covariances|_poses|"
        r"_due|estimate|fused_to_msg|unknown_sources|append|fuse_stream_from_wire|FromString|"
        r"SerializeToString")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rate", type=float, default=20000.0, help="measurements/s (paced row)")
    ap.add_argument("--bodies", type=int, default=100)
    ap.add_argument("--output-rate", type=float, default=1.0, help="answers per body, Hz")
    ap.add_argument("--window", type=float, default=0.1, help="seconds per body")
    ap.add_argument("--seconds", type=float, default=20.0, help="length of each row")
    ap.add_argument("--minutes", type=float, help="one paced run this long (memory), no "
                                                  "unpaced row")
    ap.add_argument("--no-profile", action="store_true")
    ap.add_argument("--plot", metavar="PATH", help="RSS and latency over the paced run (PNG)")
    ap.add_argument("--in-process", type=int, metavar="N", help="only run N messages (after "
                    "500 to warm up) through the server's per-message path in process, print "
                    "nothing: for callgrind, whose count does not depend on the machine's load")
    ap.add_argument("--probe", action="store_true", help="an 11th measurement a message that "
                    "the server refuses at once: the round trip of every message too (no transport "
                    "row then)")
    args = ap.parse_args(argv)

    scene = Scene(args.bodies, args.rate, probe=args.probe)
    if args.in_process is not None:
        in_process(scene, args, args.in_process)
        return 0
    rows = []
    if not args.minutes and not args.probe:
        # the peer: gRPC and the shipped client alone, a server that answers as often with a
        # fused pose of the same size and fuses nothing; the latency fusion adds is above it
        echo = ServerProcess("echo", quiet_log=True)
        try:
            rows.append(("transport only (no fusion)", run(
                echo.target, scene, args.seconds, args.rate / PER_MESSAGE, args, echo.rss_mb,
                echo.proc.pid)))
        finally:
            echo.stop()
    server = ServerProcess("aio", quiet_log=True)
    try:
        if args.minutes:
            rows.append(("paced", run(server.target, scene, args.minutes * 60,
                                      args.rate / PER_MESSAGE, args, server.rss_mb,
                                      server.proc.pid)))
        else:
            rows.append(("paced", run(server.target, scene, args.seconds,
                                      args.rate / PER_MESSAGE, args, server.rss_mb,
                                      server.proc.pid)))
            rows.append(("unpaced", run(server.target, scene, args.seconds, None, args,
                                        server.rss_mb, server.proc.pid)))
    finally:
        server.stop()

    print(f"StreamFuse, one server (dqpose serve --no-call-log), Python Client.stream_fuse; "
          f"{args.bodies} bodies, {PER_MESSAGE} measurements (full covariances)"
          f"{' + 1 probe' if args.probe else ''} a message, window {args.window:g} s, "
          f"output_rate {args.output_rate:g} Hz per body; latency of the answers (after the "
          f"first second): from sending the message that made each due to its arrival; the "
          f"transport row's server answers every {FUSE_EVERY}th message with a fused pose of the "
          f"same size and fuses nothing")
    head = ("row", "meas/s", "msgs/s", "answers/s", "p50 ms", "p99 ms", "max ms",
            *(("message p99 ms",) if args.probe else ()), "server CPU us/msg",
            "client CPU us/msg", "RSS start MB", "RSS end MB", "seconds")
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for name, r in rows:
        rss = [m for _, m in r["rss"]]
        start = rss[min(2, len(rss) - 1)] if rss else float("nan")   # after the warm-up
        probe = f"{r['msg_p99']:.2f} | " if args.probe else ""
        print(f"| {name} | {r['measurements']:.0f} | {r['messages']:.0f} | {r['answers']:.1f} | "
              f"{r['p50']:.2f} | {r['p99']:.2f} | {r['max']:.1f} | {probe}"
              f"{r['server_cpu']:.0f} | {r['client_cpu']:.0f} | {start:.1f} | "
              f"{rss[-1] if rss else float('nan'):.1f} | "
              f"{(r['rss'][-1][0] - r['rss'][0][0]) if r['rss'] else 0:.0f} |")
    if not args.no_profile:
        print()
        print(per_message_cost(scene, args))
    if args.plot:
        plot(args.plot, rows[0][1])
    return 0


def plot(path: str, r: dict) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t0 = r["rss"][0][0]
    fig, ax = plt.subplots(figsize=(7, 3))
    ax.plot([t - t0 for t, _ in r["rss"]], [m for _, m in r["rss"]])
    ax.set_xlabel("s")
    ax.set_ylabel("server RSS, MB")
    ax.set_title("StreamFuse paced run: server memory")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    sys.exit(main())
