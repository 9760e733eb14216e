"""The shared world (``dqpose.world``): one table (``--publish``: the other one).

    .venv/bin/python -m tests.bench.bench_world            # ~1 min
    .venv/bin/python -m tests.bench.bench_world --trials 500 --lookups 2000
    .venv/bin/python -m tests.bench.bench_world --publish          # Publish -> Subscribe, ~4 min
    .venv/bin/python -m tests.bench.bench_world --publish --soak 600   # RSS over 10 min
    .venv/bin/python -m tests.bench.bench_world --cost           # the costliest Publish, ~1 min

Sections (each a function returning rows of the one table, so that more can be added):

* :func:`ingest_rows` — the world in process under the Publish table's target scene (100
  bodies, 20,000 stamps/s, 30 Hz ticks): measurements/s and fits/s one thread sustains.
* :func:`answer_rows` — a Subscribe answer for one tick of that scene: the body's fit and its
  message, each timed.
* :func:`publish_request_rows` — one Publish request of 10 measurements into that world, as
  the server's worker runs it: from its bytes (decoded in C) against the protobuf path.
* :func:`lookup_rows` — ``World.relative`` (Lookup's server time, in process): the latency of a
  lookup between two moving bodies, each seen at 30 Hz by two cameras with latencies over a 1 s
  window (60 measurements a body's fit, the constant-twist fit over time), p50/p99 over
  ``--lookups`` calls: bodies that share no uncertain extrinsic (two fits composed), and bodies
  seen by the same camera with an ``extrinsic_covariance`` (the joint fit with its error), and
  ``World.pose`` alone. Target: ≤ 200 µs.
* :func:`rpc_lookup_rows` — the Lookup RPC of one body through a ``dqpose serve`` process and
  the shipped client: the server's own time (its call log) and the client's round trip.
* :func:`publish_cost_rows` (``--cost``: these rows alone) — the costliest legal Publish
  request through a ``dqpose serve`` process: the server's CPU for it and what its budget
  (``limits.Budget``) answered and skipped.
* :func:`nees_rows` — the mean NEES of ``World.relative`` against the truth over ``--trials``
  draws, on the scene of tests/test_world.py: one camera whose mount is uncertain (1° / 5 mm)
  sees both bodies twice (0.1° / 0.5 mm each); beside it the composition of the two bodies'
  marginals, which ignores the error they share. 6 is consistent; the 95 % band of the mean of
  500 χ²₆ draws is about 6 ± 0.3.

With ``--publish``, the other table: the shared world under load, producers and subscribers
in processes of their own against a ``dqpose serve`` process and a relay
(:mod:`tests.bench.world_publish`).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import threading
import time

import numpy as np

from dqpose import dq, lie
from dqpose.fusion import Measurement, Source
from dqpose.world import World, WorldOptions
from tests.bench._table import markdown
from tests.bench.bench_grpc import ServerProcess
from tests.bench.world_publish import SUBSCRIBE_RATE, publish_table, scene_poses, serve_relay, soak

HEAD = ["section", "case", "value", "unit", "detail"]
COV = np.diag(np.r_[np.full(3, np.deg2rad(0.3)), np.full(3, 1e-3)] ** 2)
MOUNT = np.diag(np.r_[np.full(3, np.deg2rad(1.0)), np.full(3, 5e-3)] ** 2)


def _moving_world(shared: bool, seed: int = 0):
    """Bodies "a" and "b" on screws, each seen at 30 Hz by two cameras over 2 s (window 1 s):
    with ``shared`` camera "top" (extrinsic uncertain) sees both, else each body has its own
    pair of exact cameras. Returns the world and a function that publishes the next 30 Hz
    tick."""
    rng = np.random.default_rng(seed)
    names = ["top", "side"] if shared else ["a1", "a2", "b1", "b2"]
    sources = [Source(n, lie.se3_exp(rng.normal(size=6) * 0.5), latency=0.02 + 0.01 * k,
                      extrinsic_covariance=MOUNT if n == "top" else None)
               for k, n in enumerate(names)]
    world = World(sources=sources, options=WorldOptions(window=1.0, buffer=10.0))
    seen = {"a": names[:2], "b": names[:2]} if shared else {"a": names[:2], "b": names[2:]}
    X0 = {b: lie.se3_exp(rng.normal(size=6) * 0.3) for b in "ab"}
    V = {b: rng.normal(size=6) * 0.2 for b in "ab"}
    by = {s.name: s for s in sources}
    tick = [0]

    def more():
        t = tick[0] / 30.0
        tick[0] += 1
        batch = []
        for b in "ab":
            for n in seen[b]:
                s = by[n]
                X = dq.mul(X0[b], lie.se3_exp((t - s.latency) * V[b]))
                z = dq.mul(dq.mul(dq.conj(s.extrinsic), X),
                           lie.se3_exp(rng.multivariate_normal(np.zeros(6), COV)))
                batch.append(Measurement(n, b, t, z, COV))
        world.publish(batch)

    for _ in range(60):
        more()
    return world, more


def _target_scene(on_tick):
    """The Publish table's target scene in process: 100 bodies, messages of 10 measurements at
    20,000 stamps/s, window 0.2 s. Returns the world and ``step(n, ticks)``, which ingests the
    next ``n`` messages (``World.ingest``, as the server calls it) and, with ``ticks``, calls
    ``on_tick(body, t)`` for each body's 30 Hz tick as it falls due, as a subscriber asks;
    ``step`` returns how many it called."""
    bodies, per, rate = 100, 10, 20_000.0
    poses, cov = scene_poses(bodies)
    covs = np.broadcast_to(cov, (per, 6, 6))
    world = World(options=WorldOptions(window=0.2))
    due: dict[str, float] = {}
    i = 0

    def step(n: int, ticks: bool) -> int:
        nonlocal i
        made = 0
        for _ in range(n):
            t = 1000.0 + i * per / rate
            chosen = [(i * per + j) % bodies for j in range(per)]
            names = [f"b{b}" for b in chosen]
            world.ingest(names, [f"p{b % 4}" for b in chosen], np.full(per, t), poses[chosen],
                         covs)
            for name in names if ticks else ():
                tick = due.get(name, 0.0)
                if t >= tick:
                    if tick:
                        on_tick(name, tick)
                        made += 1
                    due[name] = (math.floor(t * SUBSCRIBE_RATE) + 1) / SUBSCRIBE_RATE
            i += 1
        return made

    step(int(10.0 * rate / per), False)            # 10 s of history
    return world, step


def ingest_rows(messages: int = 2000) -> list[list[str]]:
    """The world in process under the Publish table's target scene (:func:`_target_scene`),
    each body's pose fitted at its 30 Hz ticks (``World.pose``): measurements/s and fits/s one
    thread sustains, after the history has filled."""
    def fit(body: str, t: float) -> None:
        world.pose(body, t)
    world, step = _target_scene(fit)
    t0, c0 = time.perf_counter(), time.thread_time()
    made = step(messages, True)
    spent, cpu = time.perf_counter() - t0, time.thread_time() - c0
    return [["World in process", "100 bodies, 20,000 stamps/s, ticks at 30 Hz",
             f"{messages * 10 / spent:.0f}", "measurements/s",
             f"{made / spent:.0f} fits/s ({1e6 * spent / made:.0f} µs of the thread a fit, "
             f"admission included); by the thread's CPU time {messages * 10 / cpu:.0f} "
             f"measurements/s, {1e6 * cpu / made:.0f} µs a fit; window 0.2 s, 10 s of "
             f"history"]]


def answer_rows(messages: int = 2000) -> list[list[str]]:
    """A Subscribe answer as the server makes it for a tick of the target scene
    (:func:`_target_scene`): the body's fit (``World.pose``, NIS and the sources' verdicts
    included) and its ``FusedPose`` bytes (``body_pose_bytes``, the C writer), each timed, p50;
    beside it the same message made by protobuf (``fused_to_msg``, serialized), alternated."""
    from dqpose.rpc.fusion_convert import fused_to_msg
    from dqpose.rpc.world_convert import body_pose_bytes
    fits, msgs, protobuf, sizes = [], [], [], []

    def answer(body: str, t: float) -> None:
        t0 = time.perf_counter()
        p = world.pose(body, t)
        t1 = time.perf_counter()
        body_pose_bytes(p, 1, [7])
        t2 = time.perf_counter()
        msg = fused_to_msg(p.fused, p.body, p.time)
        msg.request, msg.measurements[:] = 1, [7]
        msg.SerializeToString()
        fits.append(t1 - t0)
        msgs.append(t2 - t1)
        protobuf.append(time.perf_counter() - t2)
        sizes.append(len(p.fused.nis))
    world, step = _target_scene(answer)
    step(messages, True)
    detail = (f"{len(fits)} ticks, {np.median(sizes):.0f} measurements a fit (median); "
              f"window 0.2 s, 10 s of history")
    return [["Subscribe answer (in process)", "a tick's fit (World.pose)",
             f"{1e6 * np.median(fits):.1f}", "µs p50", detail],
            ["Subscribe answer (in process)", "its FusedPose bytes (the C writer)",
             f"{1e6 * np.median(msgs):.1f}", "µs p50", detail],
            ["Subscribe answer (in process)", "the same by protobuf (fused_to_msg, serialized)",
             f"{1e6 * np.median(protobuf):.1f}", "µs p50", detail]]


def publish_request_rows(requests: int = 3000, rounds: int = 3,
                         history: float = 10.0) -> list[list[str]]:
    """One Publish request of 10 measurements into the target scene's world (100 bodies, 10 s
    of history, nobody subscribed), in process as the server's worker runs it: from its bytes
    (``World.publish_bytes``, measurements decoded and checked in C) against the protobuf path
    (the request parsed, ``measurements_to_arrays``), each ``rounds`` times alternated, the
    best µs a request of each."""
    from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb
    from dqpose.rpc.fusion_convert import measurement_msgs
    from dqpose.rpc.world import World
    from dqpose.rpc.world_publish import publish
    bodies, per, rate = 100, 10, 20_000.0
    poses, cov = scene_poses(bodies)
    covs = np.repeat(cov[None], per, 0)

    def wire(first: int, n: int) -> list[bytes]:
        out = []
        for i in range(first, first + n):
            chosen = [(i * per + j) % bodies for j in range(per)]
            out.append(wpb.PublishRequest(measurements=measurement_msgs(
                poses[chosen], covs, names=[f"p{b % 4}" for b in chosen],
                bodies=[f"b{b}" for b in chosen], times=np.full(per, 1000.0 + i * per / rate)),
                producer="p", sequence=i + 1).SerializeToString())
        return out

    n = int(history * rate / per)
    filled, timed = wire(0, n), wire(n, requests)
    best = {"bytes": math.inf, "message": math.inf}
    for _ in range(rounds):
        for path in best:
            server = World()
            hub = server.hub("bench", make=True)
            for r, data in enumerate(filled):
                server.publish_bytes(hub, data, r, "")
            t0 = time.perf_counter()
            for r, data in enumerate(timed):
                if path == "bytes":
                    server.publish_bytes(hub, data, r, "")
                else:
                    publish(hub, wpb.PublishRequest.FromString(data), r, "", server.max_poses)
            best[path] = min(best[path], (time.perf_counter() - t0) / requests * 1e6)
    detail = (f"10 measurements, 100 bodies, {history:g} s of history, nobody subscribed; best of "
              f"{rounds} alternated runs of {requests} requests")
    return [["Publish (in process)", "a request from its bytes (measurements decoded in C)",
             f"{best['bytes']:.1f}", "µs a request", detail],
            ["Publish (in process)", "the same request parsed (protobuf path)",
             f"{best['message']:.1f}", "µs a request", detail]]


def _timed(call, n: int, before=None) -> tuple[np.ndarray, np.ndarray]:
    """``call``'s duration and the thread's CPU time in it (µs) ``n`` times, ``before`` run
    untimed ahead of each (on a machine shared with other jobs the CPU time is the steadier
    of the two: it leaves out the time the thread waited for a core)."""
    call()
    out, cpu = np.empty(n), np.empty(n)
    for i in range(n):
        if before is not None:
            before()
        c0 = time.thread_time()
        t0 = time.perf_counter()
        call()
        out[i] = time.perf_counter() - t0
        cpu[i] = time.thread_time() - c0
    return out * 1e6, cpu * 1e6


#: the idle time before each call of the body's "1 ms idle" Lookup row
IDLE = 0.001


def lookup_rows(lookups: int = 1000) -> list[list[str]]:
    """Per case: a call after a new 30 Hz tick of measurements (the fits run) and a call
    repeated without new data (the answer the world keeps). Cases: a Lookup of one body's pose
    (``World.relative("", body)``, what the Lookup RPC runs: the pose and its covariance), the
    same body's full fit (``World.pose``: what a Subscribe answer carries, leave-one-out NIS and
    the sources' verdicts included), and a Lookup between two bodies; the first case also after
    new data and :data:`IDLE` s asleep, as in a server."""
    rows = []
    for shared in (False, True):
        world, more = _moving_world(shared)
        n = len(world.pose("a").fused.inliers)
        seen = ", seen by the uncertain camera" if shared else ""
        cases = [("Lookup of a body (T_world_a)" + seen, lambda: world.relative("", "a")),
                 ("World.pose of a body, NIS included" + seen, lambda: world.pose("a")),
                 ("Lookup between bodies, " + ("one camera with extrinsic_covariance sees "
                                               "both" if shared else
                                               "no shared uncertain extrinsic"),
                  lambda: world.relative("a", "b"))]
        before = {"after new data": more, "repeated": None,
                  # what a server's Lookup meets, its thread asleep between calls (on this
                  # guest a vCPU that idled runs the same fit slower: docs/benchmarks/world.md)
                  "after new data and 1 ms idle": lambda: (more(), time.sleep(IDLE))}
        for k, (label, call) in enumerate(cases):
            for when in before if k == 0 and not shared else list(before)[:2]:
                us, cpu = _timed(call, lookups, before[when])
                rows.append(["Lookup (in process)", f"{label}; {when}",
                             f"{np.percentile(us, 50):.1f}", "µs p50",
                             f"p99 {np.percentile(us, 99):.1f} µs; CPU p50 "
                             f"{np.percentile(cpu, 50):.1f} µs; {n} measurements a body, "
                             f"{lookups} calls"])
    return rows


#: the load beside the "while others publish" Lookup row: measurements/s of LOAD_BODIES static
#: bodies from one producer (10 a request) and a subscriber of them all at SUBSCRIBE_RATE
LOAD_BODIES, LOAD_RATE = 20, 2000.0


def _load(target: str, stop: threading.Event) -> list[threading.Thread]:
    """A producer and a subscriber of the load bodies (source "load"), each a thread with its
    own client, until ``stop``: the Publish requests whose Subscribe answers the server fits
    (about 3 a request) while a Lookup runs."""
    from dqpose.rpc.client import Batch, Client
    from dqpose.rpc.client_types import RpcError

    bodies = [f"load{i}" for i in range(LOAD_BODIES)]
    poses, cov = scene_poses(LOAD_BODIES)
    covs = np.broadcast_to(cov, (10, 6, 6))

    def batches():
        n, t0 = 0, time.perf_counter()
        while not stop.is_set():
            chosen = [(n * 10 + j) % LOAD_BODIES for j in range(10)]
            yield Batch(poses[chosen], covs, None, ["load"] * 10, [bodies[b] for b in chosen],
                        np.full(10, 2000.0 + n * 10 / LOAD_RATE))
            n += 1
            time.sleep(max(0.0, t0 + n * 10 / LOAD_RATE - time.perf_counter()))

    def produce():
        with Client(target) as c:
            for _ in c.publish(batches(), producer="load"):
                pass

    def subscribe():
        with Client(target) as c:
            answers = c.subscribe(bodies, rate_hz=SUBSCRIBE_RATE)
            try:
                for _ in answers:
                    if stop.is_set():
                        answers.close()
                        return
            except RpcError:
                # once the producer stops no answer comes, and the server's stop ends the
                # stream UNAVAILABLE: the end of the load, not a failure
                if not stop.is_set():
                    raise

    threads = [threading.Thread(target=f, daemon=True) for f in (subscribe, produce)]
    for th in threads:
        th.start()
        time.sleep(0.5)             # the subscription open before the first measurement
    return threads


def rpc_lookup_rows(lookups: int = 1000, load: bool = False,
                    polled: bool = True) -> list[list[str]]:
    """The Lookup RPC of one body through a ``dqpose serve`` process and the shipped client,
    after new data each time (a 30 Hz tick of both cameras published, acked, then the Lookup):
    the server's own time (its call log: from the handler's start to its answer, the worker
    pool's hop included), the client's round trip, and the Publish request's (its ack).
    Scene: :func:`lookup_rows`' body "a". ``polled``: at time 0, so the pair is watched and
    each Publish request makes its answer (:mod:`dqpose.answers`); else at the tick's
    time (the newest), fitted by each Lookup. With ``load``, while :func:`_load` publishes
    into the same world and subscribes."""
    import queue

    from dqpose.rpc.client import Batch, Client

    rng = np.random.default_rng(0)
    names = ["a1", "a2"]
    sources = [Source(n, lie.se3_exp(rng.normal(size=6) * 0.5), latency=0.02 + 0.01 * k)
               for k, n in enumerate(names)]
    X0, V = lie.se3_exp(rng.normal(size=6) * 0.3), rng.normal(size=6) * 0.2
    pending: queue.Queue = queue.Queue()

    def batches():
        while (b := pending.get()) is not None:
            yield b

    def tick(k: int) -> Batch:
        t = 1000.0 + k / 30.0
        Z = [dq.mul(dq.mul(dq.conj(s.extrinsic), dq.mul(X0, lie.se3_exp((k / 30.0 - s.latency)
                                                                         * V))),
                    lie.se3_exp(rng.multivariate_normal(np.zeros(6), COV))) for s in sources]
        return Batch(np.array(Z), np.array([COV, COV]), None, names, ["a", "a"],
                     np.array([t, t]))

    server = ServerProcess("aio", quiet_log=False)
    rtt, acked = [], []
    stop = threading.Event()
    threads: list[threading.Thread] = []
    try:
        with Client(server.target) as c:
            c.configure_world(sources + [Source("load", lie.se3_exp(np.zeros(6)))], window=1.0,
                              buffer=10.0)
            if load:
                threads = _load(server.target, stop)
            acks = c.publish(batches(), producer="bench")
            for k in range(60 + lookups):
                t0 = time.perf_counter()
                pending.put(tick(k))
                next(acks)
                if k >= 60:
                    acked.append(time.perf_counter() - t0)
                    t0 = time.perf_counter()
                    c.lookup("", "a", 0.0 if polled else 1000.0 + k / 30.0)
                    rtt.append(time.perf_counter() - t0)
            pending.put(None)
            for _ in acks:
                pass
    finally:
        stop.set()
        for th in threads[1:]:      # the producer; the subscriber waits for an answer that
            th.join(10.0)           # no longer comes, until the server's stop ends its stream
        server.stop()
        for th in threads[:1]:
            th.join(10.0)
    server.log.seek(0)
    calls = [json.loads(line) for line in server.log if line.startswith("{")]
    ms = np.array([r["ms"] for r in calls if r.get("rpc", "").endswith("Lookup")][-lookups:])
    us, rt, ack = ms * 1e3, np.array(rtt) * 1e6, np.array(acked) * 1e6
    how = ("at time 0, polled (answered from the answer its data made)" if polled else
           "at its newest time (fitted)")
    beside = (f"; while {LOAD_RATE:,.0f} measurements/s of {LOAD_BODIES} other bodies are "
              f"published and their {SUBSCRIBE_RATE:g} Hz answers fitted" if load else "")
    return [["Lookup (gRPC)", f"Lookup of a body through dqpose serve {how}; after new data"
             + beside, f"{np.percentile(us, 50):.1f}", "µs p50",
             f"the server's time (its call log) p99 {np.percentile(us, 99):.1f} µs; the "
             f"shipped client's round trip p50 {np.percentile(rt, 50):.1f} µs, p99 "
             f"{np.percentile(rt, 99):.1f} µs; the tick's Publish round trip p50 "
             f"{np.percentile(ack, 50):.1f} µs; 61 measurements a body, {len(us)} calls"]]


def publish_cost_rows() -> list[list[str]]:
    """The costliest legal Publish requests, each with one subscriber at the server's
    ``max_output_rate`` (1 kHz: a tick due every ms of a body's measurements, each fusing the
    body's window, 1 s; at rate 0 a request is answered once a body, one fit): 1,000
    measurements of one body 1 ms apart, in a plain, a robust and an ``acceleration_psd``
    world; and ``max_poses`` (10,000) measurements of the world's 1,000 bodies, 10 each. Per
    request the ``dqpose serve`` process's CPU (user + system, all its threads) from its send
    until its ack and its answers are in, the ack's wall time, and the answers fitted and
    ticks skipped (``limits.Budget``)."""
    from dqpose.limits import DEFAULT
    from dqpose.rpc.client import Batch, Client, RpcError

    def subscribe(sub: Client, answers: list) -> None:
        try:
            answers.extend(sub.subscribe(rate_hz=DEFAULT.max_output_rate))
        except RpcError:
            pass        # closed at the end

    server = ServerProcess("aio", quiet_log=True)
    cases = [("plain", {}, 1000, 1), ("robust", {"robust": True}, 1000, 1),
             ("acceleration_psd", {"acceleration_psd": np.eye(6) * 1e-2}, 1000, 1),
             ("plain", {}, 10_000, 1000)]
    rows = []
    try:
        for k, (label, options, n, bodies) in enumerate(cases):
            with Client(server.target, world=f"cost-{k}") as c, \
                    Client(server.target, world=f"cost-{k}") as sub:
                c.configure_world(window=1.0, buffer=10.0, **options)
                answers: list = []
                threading.Thread(target=subscribe, args=(sub, answers), daemon=True).start()
                time.sleep(1.0)     # the subscription open before the request
                poses = lie.se3_exp(1e-3 * np.random.default_rng(0).normal(size=(n, 6)))
                each = n // bodies
                batch = Batch(poses, np.repeat(COV[None], n, 0), None, ["cam"] * n,
                              [f"b{i // each}" for i in range(n)],
                              np.tile(np.arange(each) * 1e-3, bodies))
                cpu, t0 = server.cpu_seconds(), time.perf_counter()
                list(c.publish([batch], producer="bench"))
                ack = time.perf_counter() - t0
                got = -1
                while got != len(answers):      # every answer in: none more for 1 s
                    got = len(answers)
                    time.sleep(1.0)
                cpu = server.cpu_seconds() - cpu
            errors = [a.error for a in answers if a.error is not None]
            skipped = sum(int(e.split(": ")[2].split()[0]) for e in errors
                          if "max_fused_per_request" in e)
            what = "one body" if bodies == 1 else f"{bodies} bodies"
            rows.append(["costliest Publish", f"{n} measurements of {what}, a subscriber at "
                         f"{DEFAULT.max_output_rate:g} Hz, {label} world", f"{cpu:.2f}", "s CPU",
                         f"ack after {ack:.2f} s; {got - len(errors)} answers fitted, "
                         f"{skipped} ticks skipped; the server process, all threads"])
    finally:
        server.stop()
    return rows


def _nees(trials: int, seed: int = 0) -> tuple[float, float]:
    from tests.test_world import relative_nees
    return relative_nees(trials, seed)


def nees_rows(trials: int = 500) -> list[list[str]]:
    joint, composed = _nees(trials)
    scene = "one camera (mount 1° / 5 mm) sees both bodies"
    return [["NEES of relative", "World.relative (joint fit)", f"{joint:.2f}", "mean NEES",
             f"{scene}; {trials} trials; 6 expected"],
            ["NEES of relative", "composition of the marginals", f"{composed:.2f}", "mean NEES",
             f"{scene}; {trials} trials; ignores the shared error"]]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=500)
    ap.add_argument("--lookups", type=int, default=1000)
    ap.add_argument("--publish", action="store_true",
                    help="the Publish -> Subscribe table instead of Lookup and NEES")
    ap.add_argument("--seconds", type=float, default=10.0,
                    help="--publish: per row (default %(default)s)")
    ap.add_argument("--rate", type=float, default=20_000.0,
                    help="--publish: the target row's measurements/s in total (default "
                         "%(default)s)")
    ap.add_argument("--window", type=float, default=0.2, help="--publish: the world's window, s")
    ap.add_argument("--fit-bodies", type=int, default=20,
                    help="--publish: bodies of the row sized to this machine (default "
                         "%(default)s)")
    ap.add_argument("--fit-rate", type=float, default=4_000.0,
                    help="--publish: its measurements/s in total (default %(default)s)")
    ap.add_argument("--sweep", choices=("full", "none"), default="full")
    ap.add_argument("--subscribe", choices=("SubscribeBatches", "Subscribe"),
                    default="SubscribeBatches",
                    help="--publish: the subscribers' RPC (default %(default)s, the shipped "
                         "client's; Subscribe: one answer a message), the relay's alike")
    ap.add_argument("--soak", type=float, metavar="SECONDS",
                    help="--publish: instead of the table, one world row (--fit-bodies, "
                         "--fit-rate) for SECONDS, its RSS from minute 2 to the end")
    ap.add_argument("--cost", action="store_true",
                    help="only the costliest Publish's rows (publish_cost_rows)")
    ap.add_argument("--serve-relay", type=int, metavar="BYTES", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.serve_relay is not None:
        serve_relay(args.serve_relay)
        return 0
    if args.cost:
        print(markdown(HEAD, publish_cost_rows()))
        return 0
    if not args.publish:
        print(markdown(HEAD, ingest_rows() + answer_rows() + publish_request_rows()
                       + lookup_rows(args.lookups)
                       + [row for load in (False, True) for polled in (False, True)
                          for row in rpc_lookup_rows(args.lookups, load, polled)]
                       + publish_cost_rows() + nees_rows(args.trials)))
        return 0
    if args.soak:
        return soak(args)
    return publish_table(args)


if __name__ == "__main__":
    sys.exit(main())
