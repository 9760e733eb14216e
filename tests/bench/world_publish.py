"""The Publish -> Subscribe table of bench_world (``--publish``, ``--soak``): the world under load.

:func:`publish_table` (its rows :func:`publish_rows`): the shared world under load, producers
(processes) publishing measurements of many bodies into one server (a ``dqpose serve`` process)
while subscribers (processes) read the fused poses at 30 Hz per body: measurements/s sustained,
the added latency from a measurement's arrival to the subscriber's answer that it made due
(p50/p99), answers/s and answers a message, the server's CPU over the row (cores: its CPU
seconds a second, all threads; its Python runs under one interpreter lock, only its C parts
beside it) and the client processes' (all of them together), its RSS at the start and the end;
:func:`soak` one row for minutes, its RSS. Subscribers use SubscribeBatches, as the shipped
client does (``--subscribe Subscribe``: one answer a message), and so does the relay.

Scene: body ``b{i}`` is measured by producer ``i % producers`` only (its own source), a static
pose with a full covariance; each producer sends messages of 10 measurements (10 bodies each),
stamped with the host's clock when made (``time.time()``, which every process here shares), so
a measurement's time is its send time. Each body is fed by one source, so its tick at t falls
due with its first measurement at or after t: the answer's latency is its arrival time minus
that measurement's time (client serialisation, both transports, the server's queue, the fit).
The world fuses over a window of 0.2 s (``--window``).

Rows: "transport" is the same producers and subscribers against a relay server (``bench_world
--serve-relay``, :func:`serve_relay`) that parses each request, paces ticks with the same
:class:`dqpose.world_ticks.Schedule` and sends an answer of the size the world's answers had in the
target row, fusing nothing: the floor the added latency is measured against. "target" is 4
producers and 4 subscribers at 20,000 measurements/s into 100 bodies; the sweep rows are one
subscriber and unpaced producers (as fast as the acks come back, 8 requests in flight each).
"""
from __future__ import annotations

import asyncio
import bisect
import json
import multiprocessing
import sys
import threading
import time

import numpy as np

from tests.bench._table import markdown
from tests.bench.bench_grpc import ServerProcess

PUBLISH_HEAD = ["row", "producers", "subscribers", "bodies", "offered meas/s", "sustained meas/s",
                "answers/s", "answers a message", "p50 ms", "p99 ms", "added p99 ms",
                "server cores", "client cores", "answer bytes", "RSS MB start", "RSS MB end",
                "subscriber streams"]
PER_MESSAGE = 10
IN_FLIGHT = 8
SUBSCRIBE_RATE = 30.0


def scene_poses(bodies: int):
    """Static poses of ``bodies`` bodies (one seed for every process) and the covariance their
    measurements carry; the in-process rows of bench_world use the same scene."""
    from dqpose import lie
    rng = np.random.default_rng(0)
    poses = lie.se3_exp(rng.normal(size=(bodies, 6)) * 0.3)
    cov = np.diag([1e-4] * 3 + [1e-6] * 3)
    return poses, cov


def _start_time(ready, go) -> float:
    """Says this process is ready, then waits for the start time every process shares (set
    once all are ready: a loaded machine may take seconds to start them)."""
    ready.put(1)
    while go.value == 0.0:
        time.sleep(0.005)
    return go.value


def _cpu_over(start: float, seconds: float) -> threading.Thread:
    """A thread that reads this process's CPU time (all its threads) at ``start`` and
    ``start + seconds`` (host clock), the server's interval: ``.cpu`` the seconds between."""
    def read():
        time.sleep(max(0.0, start - time.time()))
        c0 = time.process_time()
        time.sleep(max(0.0, start + seconds - time.time()))
        reader.cpu = time.process_time() - c0    # type: ignore[attr-defined]

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    return reader


def _cpu(reader: threading.Thread, seconds: float) -> float:
    reader.join()
    return reader.cpu / seconds      # type: ignore[attr-defined]


def produce(target: str, k: int, producers: int, bodies: int, rate: float | None,
            seconds: float, ready, go, out) -> None:
    """Producer ``k``: its bodies' measurements in messages of PER_MESSAGE from ``start`` (host
    clock) for ``seconds``, ``rate`` measurements/s (None: as fast as the acks allow); puts
    ``(k, {body: times}, measurements acked, seconds)``."""
    from dqpose.rpc.client import Batch, Client
    mine = list(range(k, bodies, producers))
    poses, cov = scene_poses(bodies)
    sent: dict[int, list] = {b: [] for b in mine}
    slots = threading.Semaphore(IN_FLIGHT)
    per = min(PER_MESSAGE, len(mine))
    covs = np.repeat(cov[None], per, 0)
    names = [f"p{k}"] * per
    start = _start_time(ready, go)

    def batches():
        i = 0
        while time.time() < start:
            time.sleep(0.001)
        end = start + seconds
        while True:
            if rate is not None:
                due = start + i * per / rate
                time.sleep(max(0.0, due - time.time()))
            slots.acquire()
            t = time.time()
            if t >= end:
                return
            chosen = [mine[(i * per + j) % len(mine)] for j in range(per)]
            for b in chosen:
                sent[b].append(t)
            i += 1
            yield Batch(poses[chosen], covs, None, names, [f"b{b}" for b in chosen],
                        np.full(per, t))

    acked = 0
    cpu = _cpu_over(start, seconds)
    with Client(target) as c:
        for ack in c.publish(batches(), producer=f"p{k}"):
            slots.release()
            acked = ack.acked_through
    out.put(("producer", k, {b: np.array(v) for b, v in sent.items()}, acked * per,
             time.time() - start, _cpu(cpu, seconds)))


def subscribe(target: str, k: int, seconds: float, ready, go, out,
              rpc: str = "SubscribeBatches") -> None:
    """Subscriber ``k`` through ``rpc`` (SubscribeBatches, the shipped client's, or Subscribe):
    every answer's ``(body, time, arrival)``, and each message's ``(bytes, answers)``."""
    import grpc

    from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb
    from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb
    batched = rpc == "SubscribeBatches"
    rows, sizes = [], []
    ended = ""
    start = _start_time(ready, go)
    cpu = _cpu_over(start, seconds)
    with grpc.insecure_channel(target) as ch:
        call = ch.unary_stream(f"/dqpose.v1.World/{rpc}",
                               request_serializer=wpb.SubscribeRequest.SerializeToString)(
            wpb.SubscribeRequest(rate_hz=SUBSCRIBE_RATE), timeout=seconds + (start - time.time())
            + 5.0)
        try:
            for data in call:
                now = time.time()
                batch = (wpb.FusedPoseBatch.FromString(data).poses if batched else
                         [fpb.FusedPose.FromString(data)])
                rows += [(int(a.body[1:]) if a.body else -1, a.time, now) for a in batch]
                sizes.append((len(data), len(batch)))
        except grpc.RpcError as e:
            if e.code() != grpc.StatusCode.DEADLINE_EXCEEDED:
                ended = e.code().name       # e.g. RESOURCE_EXHAUSTED: it fell too far behind
    out.put(("subscriber", k, np.array(rows).reshape(-1, 3), np.array(sizes).reshape(-1, 2),
             ended, _cpu(cpu, seconds)))


def run(target: str, producers: int, subscribers: int, bodies: int, rate: float | None,
        seconds: float, rss=None, cpu=None, rpc: str = "SubscribeBatches") -> dict:
    ctx = multiprocessing.get_context("spawn")
    out = ctx.Queue()
    ready, go = ctx.Queue(), ctx.Value("d", 0.0)
    procs = [ctx.Process(target=subscribe, args=(target, k, seconds, ready, go, out, rpc))
             for k in range(subscribers)]
    procs += [ctx.Process(target=produce, args=(target, k, producers, bodies,
                                                None if rate is None else rate / producers,
                                                seconds, ready, go, out))
              for k in range(producers)]
    for p in procs:
        p.start()
    for _ in procs:
        ready.get(timeout=300)
    start = go.value = time.time() + 1.0      # the subscriptions open before the first data
    rss0 = rss() if rss else float("nan")
    samples: list[tuple[float, float]] = []       # (seconds since start, RSS MB), every 5 s
    done = threading.Event()

    def sample():
        while rss and not done.wait(5.0):
            samples.append((time.time() - start, rss()))

    cores: list[float] = []     # the server's CPU time over the run / its seconds

    def server_cpu():
        time.sleep(max(0.0, start - time.time()))
        c0 = cpu()
        time.sleep(seconds)
        cores.append((cpu() - c0) / seconds)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    timer = threading.Thread(target=server_cpu, daemon=True)
    if cpu:
        timer.start()
    results = [out.get(timeout=seconds + 120) for _ in procs]
    done.set()
    rss1 = rss() if rss else float("nan")
    if cpu:
        timer.join()
    for p in procs:
        p.join(30)
    sent: dict[int, np.ndarray] = {}
    measured, span, client_cores = 0, 0.0, 0.0
    answers, sizes, ended = [], [], set()
    for r in results:
        client_cores += r[-1]       # over the server's interval, as its cores
        if r[0] == "producer":
            sent.update(r[2])
            measured += r[3]
            span = max(span, r[4])
        else:
            answers.append(r[2])
            sizes.append(r[3])
            if r[4]:
                ended.add(r[4])
    lat = []
    for rows in answers:
        for body, t, arrival in rows:
            times = sent.get(int(body))
            if times is None or not len(times):
                continue
            i = bisect.bisect_left(times, t - 1e-9)
            if i < len(times):
                lat.append(arrival - times[i])
    lat_ms = np.array(lat) * 1e3
    n_answers = sum(len(a) for a in answers)
    messages = np.concatenate(sizes) if sizes else np.zeros((0, 2))
    return dict(rate=measured / span if span else 0.0, answers=n_answers / span if span else 0.0,
                p50=float(np.percentile(lat_ms, 50)) if len(lat_ms) else float("nan"),
                p99=float(np.percentile(lat_ms, 99)) if len(lat_ms) else float("nan"),
                size=messages[:, 0].sum() / messages[:, 1].sum() if messages[:, 1].sum()
                else 0.0, per_message=messages[:, 1].mean() if len(messages) else 0.0,
                rss0=rss0, rss1=rss1, ended=",".join(sorted(ended)), samples=samples,
                cores=cores[0] if cores else float("nan"),
                client_cores=client_cores)


def serve_relay(answer_bytes: int) -> None:
    """The transport alone: World's Publish and Subscribe with the same pacing and answers of
    ``answer_bytes``, fusing nothing."""
    import grpc

    from dqpose.hub import Interest
    from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb
    from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb
    from dqpose.rpc.wire import messages_wire
    from dqpose.rpc.world import Subscriber, _ready
    from dqpose.world_ticks import Schedule, horizon
    subs: list = []
    newest: dict[str, dict[str, float]] = {}
    template = fpb.FusedPose()
    template.residuals.extend([0.0] * max(0, (answer_bytes - 40) // 8))

    async def publish(request_iterator, context):
        async for data in request_iterator:
            req = wpb.PublishRequest.FromString(data)
            for m in req.measurements:          # the world's newest of each body's sources
                mine = newest.setdefault(m.body, {})
                mine[m.source] = max(mine.get(m.source, m.time), m.time)
            for sub, schedule in subs:
                for body in dict.fromkeys(m.body for m in req.measurements):
                    h = horizon(newest[body], 0.1)
                    for k in schedule.due(body, h, h - 0.2):
                        template.body, template.time = body, schedule.time(body, k)
                        sub.deliver([template.SerializeToString()])
            yield wpb.PublishAck(acked_through=req.sequence).SerializeToString()

    def subscriber():
        # the world's queue of a subscriber (its bounds and batching), fed by the relay
        return (Subscriber(Interest(None, SUBSCRIBE_RATE), asyncio.get_running_loop()),
                Schedule(SUBSCRIBE_RATE))

    async def one_a_message(request, context):
        entry = subscriber()
        subs.append(entry)
        try:
            while (answer := await entry[0].next()) is not None:
                yield answer
        finally:
            subs.remove(entry)

    async def batches(request, context):
        entry = subscriber()
        subs.append(entry)
        try:
            carry = None
            while (first := carry if carry is not None else await entry[0].next()) is not None:
                # the world's batching (one message of what is ready)
                answers, carry = _ready(first, entry[0])
                yield messages_wire(answers)
        finally:
            subs.remove(entry)

    async def main():
        server = grpc.aio.server()
        server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(
            "dqpose.v1.World", {
                "Publish": grpc.stream_stream_rpc_method_handler(publish),
                "Subscribe": grpc.unary_stream_rpc_method_handler(one_a_message),
                "SubscribeBatches": grpc.unary_stream_rpc_method_handler(batches)}),))
        port = server.add_insecure_port("127.0.0.1:0")
        await server.start()
        print(json.dumps({"event": "serving", "address": f"127.0.0.1:{port}"}),
              file=sys.stderr, flush=True)
        await server.wait_for_termination()

    asyncio.run(main())


class RelayProcess(ServerProcess):
    def __init__(self, answer_bytes: int):
        import shutil
        import subprocess
        import tempfile

        from tests.bench.bench_grpc import ROOT
        self.log = tempfile.TemporaryFile("w+")
        self.proc = subprocess.Popen([sys.executable, "-m", "tests.bench.bench_world",
                                      "--serve-relay", str(answer_bytes)], cwd=ROOT,
                                     stderr=subprocess.PIPE, text=True)
        self.target = json.loads(self.proc.stderr.readline())["address"]
        self._drain = threading.Thread(target=shutil.copyfileobj,
                                       args=(self.proc.stderr, self.log), daemon=True)
        self._drain.start()


def publish_rows(args) -> list:
    """The Publish -> Subscribe rows: the target's producers alone, its transport floor, the
    target, the row within 2 cores and its floor, the sweep."""
    from dqpose.rpc.client import Client
    rows = []

    def on_world(name, producers, subscribers, bodies, rate):
        server = ServerProcess("aio", quiet_log=True)
        try:
            with Client(server.target) as c:
                c.configure_world(window=args.window)
            r = run(server.target, producers, subscribers, bodies, rate, args.seconds,
                    server.rss_mb, server.cpu_seconds, args.subscribe)
        finally:
            server.stop()
        rows.append((name, producers, subscribers, bodies, rate, r))
        return r

    # The target row, then a row this machine can carry (fits are made per body and tick, so
    # fewer bodies), each beside the transport alone at the same load; first what the target's
    # producers alone take of the machine (against the relay, nobody subscribed).
    for name, bodies, rate in (("target", 100, args.rate),
                               ("within 2 cores", args.fit_bodies, args.fit_rate)):
        world = on_world(name, 4, 4, bodies, rate)
        relay = RelayProcess(int(world["size"]) or 1000)
        try:
            floor = run(relay.target, 4, 4, bodies, rate, args.seconds, relay.rss_mb,
                        relay.cpu_seconds, args.subscribe)
            rows.insert(len(rows) - 1, ("transport (relay)", 4, 4, bodies, rate, floor))
            if name == "target":
                alone = run(relay.target, 4, 0, bodies, rate, args.seconds, relay.rss_mb,
                            relay.cpu_seconds, args.subscribe)
                rows.insert(0, ("producers alone (relay)", 4, 0, bodies, rate, alone))
        finally:
            relay.stop()
    if args.sweep == "full":
        for producers in (1, 2, 4, 8):
            for bodies in (1, 10, 100, 1000):
                if bodies >= producers:
                    on_world("sweep", producers, 1, bodies, None)
    return rows


def soak(args) -> int:
    """The soak: RSS growth of one server from minute 2 to the end (target <= 5 %)."""
    from dqpose.rpc.client import Client
    server = ServerProcess("aio", quiet_log=True)
    try:
        with Client(server.target) as c:
            c.configure_world(window=args.window)
        r = run(server.target, 4, 4, args.fit_bodies, args.fit_rate, args.soak, server.rss_mb,
                rpc=args.subscribe)
    finally:
        server.stop()
    after2 = [mb for t, mb in r["samples"] if t >= 120.0]
    base = after2[0] if after2 else float("nan")
    print(f"World soak: 4 producers, 4 subscribers, {args.fit_bodies} bodies, "
          f"{args.fit_rate:g} measurements/s offered, {args.soak:g} s")
    print(markdown(["sustained meas/s", "answers/s", "p50 ms", "p99 ms", "RSS MB at 2 min",
                    "RSS MB end", "growth %", "RSS MB max after 2 min", "subscriber streams"], [[
        f"{r['rate']:.0f}", f"{r['answers']:.0f}", f"{r['p50']:.2f}", f"{r['p99']:.2f}",
        f"{base:.1f}", f"{r['rss1']:.1f}", f"{100 * (r['rss1'] / base - 1):.2f}",
        f"{max(after2, default=float('nan')):.1f}", r["ended"] or "ran to the end"]]))
    return 0


def publish_table(args) -> int:
    """The table of :func:`publish_rows`, each world row's added p99 over the transport row just
    above it."""
    rows = publish_rows(args)
    print(f"World Publish -> {args.subscribe}, one server (dqpose serve), producers and "
          f"subscribers in processes of their own, window {args.window:g} s, subscribers at "
          f"{SUBSCRIBE_RATE:g} Hz per body, {args.seconds:g} s per row; added p99 = p99 - the p99 "
          f"of the transport row just above it")
    lines, floor = [], float("nan")
    for name, p, s_, b, rate, r in rows:
        relay = name.startswith("transport")
        if relay:
            floor = r["p99"]
        heard = [f"{r['answers']:.0f}", f"{r['per_message']:.1f}", f"{r['p50']:.2f}",
                 f"{r['p99']:.2f}",
                 "" if relay or floor != floor else f"{r['p99'] - floor:.2f}"]
        lines.append([name, str(p), str(s_), str(b), "unpaced" if rate is None else f"{rate:.0f}",
                      f"{r['rate']:.0f}", *(heard if s_ else [""] * len(heard)),
                      f"{r['cores']:.2f}", f"{r['client_cores']:.2f}",
                      f"{r['size']:.0f}" if s_ else "", f"{r['rss0']:.1f}", f"{r['rss1']:.1f}",
                      (r["ended"] or "ran to the end") if s_ else "none"])
        if not relay:
            floor = float("nan")        # the sweep's rows have no transport row of their own
    print(markdown(PUBLISH_HEAD, lines))
    return 0
