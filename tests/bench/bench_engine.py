"""The world's fusion engine beside GTSAM 4.3, in one run (issue 38's benchmark and targets).

    .venv/bin/python -m tests.bench.bench_engine                 # quick (the default), ~2 min
    .venv/bin/python -m tests.bench.bench_engine --rounds 11 --seconds 1 --ticks 300
    .venv/bin/python -m tests.bench.bench_engine --serve         # and through dqpose serve

Each side is timed by its thread's CPU time (``time.thread_time``: on a machine shared with
other jobs it leaves out the time the thread waited for a core) and its wall time; the sides
alternate, round by round (the first side alternating too), so a change of load meets both. A
row gives each side's CPU a call (the median over the rounds of each round's mean), the median
of the rounds' ratios with their range, the target, and each side's CPU share of its wall time
(the load it ran under; 100 % is a core of its own).

Rows:

* tick answer — the in-process scene of docs/benchmarks/world.md (:class:`TickScene`: 100
  bodies, each seen by 4 cameras at 50 Hz, 20,000 measurements/s, window 0.2 s, 10 s of
  history, a subscriber of every body at 30 Hz): dqpose's Subscribe answer of a tick (the fit,
  NIS and verdicts included, and its ``FusedPose`` serialized), against one body of the same
  measurements on GTSAM (:mod:`tests.bench.engine_gtsam`): an ``IncrementalFixedLagSmoother``
  (lag = the window) and ``ISAM2``, each tick's update, estimate and marginal covariance. ISAM2
  keeps every key and its tick grows with its history (its relinearisation check visits every
  variable): a new one each round, warmed up on the second before, so its figure is that of
  1 s to 1 s + ``--ticks`` of history.
* Lookup of two bodies (:class:`LookupScene`: each seen at 30 Hz by two cameras of its own,
  window 1 s, 62 measurements a body): ``World.relative`` and its ``RelativePose`` after new
  data, against ISAM2's update, both estimates and ``jointMarginalCovariance``, the ISAM2 of an
  ``IncrementalFixedLagSmoother`` whose lag is the window (a plain ISAM2's Lookup grows with its
  history: 122 → 196 µs over 600 ticks, through the mount 195 → 1,550 µs, CPU at load ~15).
* the same through a shared uncertain mount: one camera with an ``extrinsic_covariance`` sees
  both bodies (the joint fit), against ISAM2 with the mount a ``Pose3`` variable under its prior.
* ingest: a Publish request's bytes (10 measurements) into the world, as the server takes it.
* in process: the tick scene's whole load on one thread (ingest, the ticks falling due, their
  answers), in cores (its CPU seconds a second of measurement time).
* with ``--serve``: a ``dqpose serve`` process under 4 producer processes publishing 8,000
  measurements/s of 100 bodies and 4 subscriber processes at 30 Hz, its CPU (``/proc`` utime +
  stime) beside the relay's (tests/bench/world_publish.py: the same transport, fusing nothing),
  and the answers' p99 latency above the relay's.

The dqpose side goes through :class:`Engine` alone: the calls the server makes today, which the
engine's rewrite replaces.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from dqpose import dq, lie
from dqpose.fusion import Source
from dqpose.rpc.client_types import Batch
from dqpose.rpc.wire import publish_from_wire, publish_head, publish_request_wire, wire_rows
from dqpose.rpc.world_convert import body_pose_bytes, relative_pose_bytes
from dqpose.world import World, WorldOptions
from dqpose.world_ticks import Schedule
from tests.bench._table import markdown

#: every measurement's noise: 0.3° and 1 mm (1 σ), rotation first
COV = np.diag(np.r_[np.full(3, np.deg2rad(0.3)), np.full(3, 1e-3)] ** 2)
#: the shared camera's mount: 1° and 5 mm
MOUNT = np.diag(np.r_[np.full(3, np.deg2rad(1.0)), np.full(3, 5e-3)] ** 2)
T0 = 1000.0             # the scenes' first measurement time, s
TICK_RATE = 30.0        # ticks and GTSAM's keys, Hz
WINDOW, HISTORY, LOOKUP_WINDOW = 0.2, 10.0, 1.0
WARM = 30               # GTSAM's ticks before it is timed (a second)
CAMERAS, CAMERA_RATE, PER = 4, 50.0, 10      # a body's cameras, each's rate; a request's size
ESTIMATORS = (
    "The estimators differ: dqpose fits each body's pose and a constant twist over the window "
    "(leave-one-out NIS and the sources' verdicts included), GTSAM has no twist state and no "
    "NIS: its keys at 30 Hz are joined by a random walk (0.5° and 5 mm a tick) and each "
    "measurement is a prior on its nearest key. GTSAM's tick is one body's smoother; dqpose's "
    "world holds every body of the scene, as a server does.")


class Engine:
    """The dqpose side, through the calls a world's hub (:class:`dqpose.hub.Hub`) makes in a
    step (a Publish request applied, a subscriber's ticks, a Subscribe answer, a Lookup
    answer), each timed apart: the few lines the engine's rewrite changes."""

    def __init__(self, window: float, sources=()):
        self.world = World(sources=sources, options=WorldOptions(window=window, buffer=HISTORY))
        self.schedule = Schedule(TICK_RATE)

    def ingest(self, data: bytes):
        """A Publish request's bytes into the world as the server applies them: the message
        read for its producer (publish_head, C), the measurements decoded and checked in C, taken
        in."""
        producer = publish_head(data)[0]
        m, errors, codes = wire_rows(data, publish_from_wire(data), "requests[0].measurements")
        published = self.world.ingest(m.bodies, m.sources, m.times, m.poses, m.covariances,
                                      codes, producer)
        assert not errors and not published.errors, (errors, published.errors)
        return m

    def due(self, m) -> list[tuple[str, float]]:
        """The ticks that the rows ``m`` made due for a subscriber of every body at
        :data:`TICK_RATE` (the sources' latencies are 0)."""
        out = []
        bodies = list(dict.fromkeys(m.bodies))
        # the hub's order of looks (Hub._answer_subscriptions): the body's newest, its horizon,
        # then its window, each only while a tick may be due
        for body, top in zip(bodies, self.world.newest_of(bodies)):
            if self.schedule.waiting(body, top) or self.schedule.waiting(
                    body, self.world.horizon(body)):
                continue
            w = self.world.tick_window(body)
            out += [(body, self.schedule.time(body, k))
                    for k in self.schedule.due(body, w.horizon, w.floor)]
        return out

    def tick(self, body: str, t: float) -> bytes:
        """The Subscribe answer of ``body`` at tick ``t``, as the hub makes it: one C call
        (``World.tick_wire``), else the fit and its message."""
        data = self.world.tick_wire(body, t, 0)
        if data is not None:
            return data
        p, ids = self.world.tick(body, t)
        return body_pose_bytes(p, 0, ids.tolist())

    def lookup(self, target: str, source: str) -> bytes:
        """The Lookup answer of ``T_target_source`` at time 0 (the newest both are known at)."""
        return relative_pose_bytes(self.world.relative(target, source, 0.0))

    def estimate(self, body: str, t: float) -> tuple[np.ndarray, np.ndarray]:
        p = self.world.tick(body, t)[0]
        return p.pose, p.covariance


def request(poses, bodies, sources, t: float, sequence: int) -> bytes:
    n = len(bodies)
    return publish_request_wire(Batch(poses, np.broadcast_to(COV, (n, 6, 6)), None,
                                      list(sources), list(bodies), np.full(n, t)),
                                "bench", sequence)


class TickScene:
    """``bodies`` static bodies, each seen by :data:`CAMERAS` cameras at :data:`CAMERA_RATE`,
    staggered; request ``i`` holds :data:`PER` measurements at time ``T0 + i / rate``, body
    ``n % bodies`` and camera ``n // bodies % CAMERAS`` of measurement ``n``. Every measurement
    is ``truth · Exp(ε)``, ``ε ~ N(0, COV)``, drawn by blocks of requests from one seed."""

    BLOCK = 200                 # requests drawn at once

    def __init__(self, bodies: int = 100, seed: int = 0):
        self.bodies, self.seed = bodies, seed
        self.truth = lie.se3_exp(np.random.default_rng(seed).normal(size=(bodies, 6)) * 0.3)
        self.rate = bodies * CAMERAS * CAMERA_RATE / PER        # requests a second
        self._blocks: dict[int, np.ndarray] = {}

    def measured(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Request ``i``'s bodies and cameras (indices), poses and time."""
        b, j = divmod(i, self.BLOCK)
        block = self._blocks.get(b)
        if block is None:
            if len(self._blocks) >= 4:          # the two sides' places in the scene, each's
                self._blocks.clear()            # block and the next
            rng = np.random.default_rng((self.seed, b))
            n = np.arange(b * self.BLOCK * PER, (b + 1) * self.BLOCK * PER)
            eps = rng.normal(size=(len(n), 6)) * np.sqrt(np.diag(COV))
            block = self._blocks[b] = dq.mul(self.truth[n % self.bodies], lie.se3_exp(eps))
        n = np.arange(i * PER, (i + 1) * PER)
        return (n % self.bodies, n // self.bodies % CAMERAS, block[j * PER:(j + 1) * PER],
                T0 + i / self.rate)

    def wire(self, i: int) -> bytes:
        bodies, cams, poses, t = self.measured(i)
        return request(poses, [f"b{b}" for b in bodies], [f"c{c}" for c in cams], t, i + 1)

    def first(self, t: float) -> int:
        """The first request at or after ``t``."""
        return int(np.ceil((t - T0) * self.rate - 1e-9))

    def of_body(self, body: int, t0: float, t1: float) -> list:
        """``body``'s measurements with times in ``(t0, t1]``: ``(time, pose, COV)``."""
        out = []
        for i in range(max(0, self.first(t0)), self.first(t1) + 1):
            bodies, _, poses, t = self.measured(i)
            if t0 < t <= t1:
                out += [(t, poses[k], COV) for k in np.flatnonzero(bodies == body)]
        return out


class LookupScene:
    """Bodies ``a`` and ``b`` on slow screws, each seen at 30 Hz (at the ticks' times) by two
    cameras: with ``shared``, camera ``top`` (its mount uncertain, :data:`MOUNT`) and ``side``
    see both; else ``a1``, ``a2`` see ``a`` and ``b1``, ``b2`` see ``b`` (all exact)."""

    def __init__(self, shared: bool, seed: int = 0):
        rng = np.random.default_rng(seed)
        names = ["top", "side"] if shared else ["a1", "a2", "b1", "b2"]
        self.sources = [Source(n, lie.se3_exp(rng.normal(size=6) * 0.5),
                               extrinsic_covariance=MOUNT if n == "top" else None)
                        for n in names]
        self.seen = {"a": names[:2], "b": names[:2] if shared else names[2:]}
        self.start = {b: lie.se3_exp(rng.normal(size=6) * 0.3) for b in "ab"}
        self.twist = {b: rng.normal(size=6) * 0.05 for b in "ab"}
        self.mount = (self.sources[0].extrinsic, MOUNT) if shared else None
        self.rng = rng

    def truth(self, body: str, t: float) -> np.ndarray:
        return dq.mul(self.start[body], lie.se3_exp((t - T0) * self.twist[body]))

    def tick(self, k: int) -> tuple[bytes, dict]:
        """Tick ``k``'s (at ``k / 30`` s) Publish request, and the same measurements in GTSAM's
        forms per body (:class:`tests.bench.engine_gtsam.Chain`)."""
        t = k / TICK_RATE
        poses, bodies, names, forms = [], [], [], {"a": [], "b": []}
        for b in "ab":
            for s in (s for s in self.sources if s.name in self.seen[b]):
                eps = self.rng.multivariate_normal(np.zeros(6), COV)
                z = dq.mul(dq.mul(dq.conj(s.extrinsic), self.truth(b, t)), lie.se3_exp(eps))
                poses.append(z)
                bodies.append(b)
                names.append(s.name)
                forms[b].append((t, z, COV, "m") if s.extrinsic_covariance is not None else
                                (t, dq.mul(s.extrinsic, z), COV))
        return request(np.array(poses), bodies, names, t, k), forms


class Side:
    """One side of a row, round by round: CPU and wall seconds and the calls they were spent
    on."""

    def __init__(self) -> None:
        self.cpu: list[float] = []
        self.wall: list[float] = []
        self.calls: list[float] = []

    def add(self, cpu: float, wall: float, calls: float) -> None:
        self.cpu.append(cpu)
        self.wall.append(wall)
        self.calls.append(calls)

    def per_call(self) -> np.ndarray:
        """Each round's CPU a call."""
        return np.array(self.cpu) / np.array(self.calls)

    def share(self) -> str:
        return f"{100 * sum(self.cpu) / sum(self.wall):.0f} %"


def _us(x: float) -> str:
    return f"{x * 1e6:,.1f} µs"


def ratio_row(case: str, ours: Side, peer: Side, peer_name: str, limit: float | None,
              detail: str) -> list[str]:
    """A row whose target is ``ours`` ≤ ``limit`` × ``peer`` (None: no target), round by
    round."""
    r = ours.per_call() / peer.per_call()
    med = float(np.median(r))
    return [case, _us(float(np.median(ours.per_call()))),
            f"{peer_name} {_us(float(np.median(peer.per_call())))}",
            f"{med:.2f}× [{r.min():.2f}–{r.max():.2f}]",
            "—" if limit is None else f"≤ {limit:g}×",
            "—" if limit is None else "yes" if med <= limit else "no",
            f"{ours.share()} / {peer.share()}", detail]


def value_row(case: str, values: np.ndarray, text, limit: float, limit_text: str, share: str,
              detail: str, beside: str = "—") -> list[str]:
    """A row whose target is an absolute bound on ``values`` (one a round), shown by
    ``text``."""
    med = float(np.median(values))
    return [case, f"{text(med)} [{text(values.min())}–{text(values.max())}]", beside, "—",
            limit_text, "yes" if med <= limit else "no", share, detail]


def gtsam_ticks(scene: TickScene, k0: int, n: int, sides: dict, order: list) -> dict:
    """Ticks ``k0 .. k0 + n - 1`` of body 0 on each GTSAM smoother of ``sides``
    (name -> (``engine_gtsam.Tick``, :class:`Side` or None)), in ``order``: each smoother's
    last answer ``(pose, covariance)``."""
    measured = [scene.of_body(0, (k - 1) / TICK_RATE, k / TICK_RATE) for k in range(k0, k0 + n)]
    last = {}
    for name in order:
        smoother, side = sides[name]
        cpu = wall = 0.0
        for j, m in enumerate(measured):
            c, w, pose, cov = smoother.tick(k0 + j, m)
            cpu, wall = cpu + c, wall + w
            last[name] = (pose, cov)
        if side is not None:
            side.add(cpu, wall, n)
    return last


def engine_round(eng: Engine, scene: TickScene, i0: int, n: int, sides: dict | None = None,
                 answer: bool = True) -> None:
    """Requests ``i0 .. i0 + n - 1`` of ``scene`` into ``eng``, each followed by the answers of
    the ticks it made due (``answer``); with ``sides`` (``tick``, ``ingest``, ``total``: a
    :class:`Side` each) the round's CPU and wall time of each."""
    wires = [scene.wire(i) for i in range(i0, i0 + n)]
    tick, ingest = [0.0, 0.0, 0], [0.0, 0.0]
    c_start, w_start = time.thread_time(), time.perf_counter()
    for data in wires:
        c0, w0 = time.thread_time(), time.perf_counter()
        m = eng.ingest(data)
        ingest[0] += time.thread_time() - c0
        ingest[1] += time.perf_counter() - w0
        for body, t in eng.due(m):
            if answer:
                c0, w0 = time.thread_time(), time.perf_counter()
                eng.tick(body, t)
                tick[0] += time.thread_time() - c0
                tick[1] += time.perf_counter() - w0
                tick[2] += 1
    total = (time.thread_time() - c_start, time.perf_counter() - w_start)
    if sides is not None:
        sides["tick"].add(*tick)
        sides["ingest"].add(*ingest, n * PER)
        sides["total"].add(*total, n / scene.rate)


def _filled(scene: TickScene, history: float) -> tuple[Engine, int]:
    """A world holding ``history`` seconds of ``scene`` (the subscriber's ticks kept up, not
    answered), and the next request's number."""
    eng = Engine(WINDOW)
    n = int(round(history * scene.rate))
    for i0 in range(0, n, 2000):
        engine_round(eng, scene, i0, min(2000, n - i0), answer=False)
    return eng, n


def tick_agreement(bodies: int = 4, seconds: float = 1.0, seed: int = 0) -> dict:
    """One :class:`TickScene` (``seconds`` of it) answered by both sides at the last 30 Hz key
    time the world has data after: body 0's ``(pose, covariance)`` from dqpose
    (``World.pose``) and from each GTSAM smoother (its newest key), and the truth."""
    from tests.bench.engine_gtsam import Tick
    scene = TickScene(bodies, seed)
    eng, _ = _filled(scene, seconds)
    k0 = int(np.ceil(T0 * TICK_RATE))
    k1 = int(np.floor((T0 + seconds - 0.05) * TICK_RATE))
    gts = {"IFLS": (Tick(WINDOW), None), "ISAM2": (Tick(None), None)}
    out: dict = gtsam_ticks(scene, k0, k1 - k0 + 1, gts, list(gts))
    out["dqpose"] = eng.estimate("b0", k1 / TICK_RATE)
    out["truth"] = scene.truth[0]
    return out


def tick_rows(rounds: int = 5, seconds: float = 0.3, ticks: int = 100, bodies: int = 100,
              history: float = HISTORY, seed: int = 0) -> list[list[str]]:
    """The tick answer, ingest and in-process rows (:class:`TickScene`): per round ``seconds`` of
    the scene through dqpose, ``ticks`` of body 0 through each GTSAM smoother."""
    from tests.bench.engine_gtsam import Tick
    scene = TickScene(bodies, seed)
    eng, i = _filled(scene, history)
    k = int(np.ceil(T0 * TICK_RATE)) + WARM
    gts = {"IFLS": (Tick(WINDOW), Side()), "ISAM2": (Tick(None), Side())}
    gtsam_ticks(scene, k - WARM, WARM, {"IFLS": (gts["IFLS"][0], None)}, ["IFLS"])
    sides = {"tick": Side(), "ingest": Side(), "total": Side()}
    n = int(round(seconds * scene.rate))
    for r in range(rounds):
        for what in ("dqpose", "gtsam") if r % 2 == 0 else ("gtsam", "dqpose"):
            if what == "dqpose":
                engine_round(eng, scene, i, n, sides)
                i += n
                continue
            # ISAM2 keeps every key and checks every one for relinearisation, so its tick grows
            # with its history: a new one each round, warmed up on the second before
            isam = Tick(None)
            gtsam_ticks(scene, k - WARM, WARM, {"ISAM2": (isam, None)}, ["ISAM2"])
            gts["ISAM2"] = (isam, gts["ISAM2"][1])
            gtsam_ticks(scene, k, ticks, gts, list(gts)[::1 if r % 2 == 0 else -1])
            k += ticks
    tick, ifls, isam = sides["tick"], gts["IFLS"][1], gts["ISAM2"][1]
    scene_text = (f"{bodies} bodies × {CAMERAS} cameras × {CAMERA_RATE:g} Hz, window "
                  f"{WINDOW:g} s, {history:g} s of history; {int(sum(tick.calls))} dqpose ticks, "
                  f"{ticks * rounds} GTSAM ticks of body 0 each")
    gtsam_cores = float(np.median(ifls.per_call())) * bodies * TICK_RATE
    return [
        ratio_row("tick answer (fit + FusedPose) ÷ ISAM2 update + estimate + marginal", tick,
                  isam, "ISAM2", 0.5, scene_text),
        ratio_row("tick answer ÷ IncrementalFixedLagSmoother (lag = window)", tick, ifls, "IFLS",
                  None, scene_text),
        value_row("ingest a measurement (Publish request bytes, 10 measurements)",
                  sides["ingest"].per_call(), _us, 3e-6, "≤ 3 µs", sides["ingest"].share(),
                  "its producer read, decoded and checked in C, World.ingest"),
        value_row("in process: ingest + ticks + answers, one thread",
                  np.array(sides["total"].cpu) / np.array(sides["total"].calls),
                  lambda x: f"{x:.2f} cores", 0.25, "≤ 0.25 core", sides["total"].share(),
                  f"{bodies * CAMERAS * CAMERA_RATE:,.0f} measurements/s, a subscriber of "
                  f"every body at {TICK_RATE:g} Hz",
                  beside=f"IFLS's ticks alone {gtsam_cores:.2f} cores (its tick × "
                         f"{bodies * TICK_RATE:,.0f}/s)"),
    ]


def lookup_rows(rounds: int = 5, ticks: int = 60, seed: int = 0) -> list[list[str]]:
    """The Lookup rows (:class:`LookupScene`), without and with the shared uncertain mount: per
    round ``ticks`` 30 Hz ticks, each published (untimed) and then looked up by both sides."""
    from tests.bench.engine_gtsam import Pair
    rows = []
    for shared in (False, True):
        scene = LookupScene(shared, seed)
        eng, pair = Engine(LOOKUP_WINDOW, scene.sources), Pair(LOOKUP_WINDOW, scene.mount)
        ours, peer = Side(), Side()
        k = int(np.ceil(T0 * TICK_RATE))
        for r in range(-1, rounds):
            n = 2 * int(LOOKUP_WINDOW * TICK_RATE) if r < 0 else ticks    # warm-up: 2 s
            made = [scene.tick(k + j) for j in range(n)]
            for what in ("dqpose", "gtsam") if r % 2 == 0 else ("gtsam", "dqpose"):
                cpu = wall = 0.0
                for j, (data, forms) in enumerate(made):
                    if what == "dqpose":
                        eng.ingest(data)
                        c0, w0 = time.thread_time(), time.perf_counter()
                        eng.lookup("a", "b")
                        c, w = time.thread_time() - c0, time.perf_counter() - w0
                    else:
                        c, w, _, _ = pair.tick(k + j, forms)
                    cpu, wall = cpu + c, wall + w
                if r >= 0:
                    (ours if what == "dqpose" else peer).add(cpu, wall, n)
            k += n
        inliers = len(eng.world.pose("a").fused.inliers)
        detail = (f"{inliers} measurements a body (window {LOOKUP_WINDOW:g} s), "
                  f"{ticks * rounds} Lookups a side")
        rows.append(ratio_row(
            "Lookup a→b through a shared uncertain mount (joint fit) ÷ ISAM2 with the mount"
            if shared else "Lookup a→b ÷ ISAM2 update + estimates + jointMarginalCovariance",
            ours, peer, "ISAM2 (IFLS)", 1.0 if shared else 0.5, detail))
    return rows


#: the --serve rows' load: producer processes, measurements/s, bodies, subscriber processes
SERVE_PRODUCERS, SERVE_RATE, SERVE_BODIES, SERVE_SUBSCRIBERS = 4, 8000.0, 100, 4


def serve_rows(rounds: int = 3, seconds: float = 10.0,
               load: tuple = (SERVE_PRODUCERS, SERVE_SUBSCRIBERS, SERVE_BODIES, SERVE_RATE)
               ) -> list[list[str]]:
    """A ``dqpose serve`` process and the relay under the same Publish/Subscribe ``load``
    (producers, subscribers, bodies, measurements/s: tests/bench/world_publish.py's ``run``),
    alternated round by round: the server's cores above the relay's, and the answers' p99 above
    the relay's."""
    from dqpose.rpc.client import Client
    from tests.bench.bench_grpc import ServerProcess
    from tests.bench.world_publish import RelayProcess, run

    producers, subscribers, bodies, rate = load
    each = (*load, seconds)
    got: dict[str, list[dict]] = {"world": [], "relay": []}
    size = 0
    for r in range(rounds):
        for what in ("world", "relay") if r % 2 == 0 else ("relay", "world"):
            if what == "world":
                server = ServerProcess("aio", quiet_log=True)
                try:
                    with Client(server.target) as c:
                        c.configure_world(window=WINDOW)
                    res = run(server.target, *each, server.rss_mb, server.cpu_seconds)
                finally:
                    server.stop()
                size = int(res["size"]) or size
            else:
                relay = RelayProcess(size or 1000)     # answers of the world's answers' size
                try:
                    res = run(relay.target, *each, relay.rss_mb, relay.cpu_seconds)
                finally:
                    relay.stop()
            got[what].append(res)
    cores = np.array([w["cores"] - r["cores"] for w, r in zip(got["world"], got["relay"])])
    p99 = np.array([w["p99"] - r["p99"] for w, r in zip(got["world"], got["relay"])])
    world = {k: float(np.median([x[k] for x in got["world"]])) for k in ("cores", "p99", "rate")}
    relay = {k: float(np.median([x[k] for x in got["relay"]])) for k in ("cores", "p99", "rate")}
    ended = ",".join(sorted({x["ended"] for x in got["world"] + got["relay"] if x["ended"]}))
    detail = (f"{producers} producer processes, {rate:,.0f} measurements/s offered "
              f"of {bodies} bodies (world sustained {world['rate']:,.0f}, relay "
              f"{relay['rate']:,.0f}), {subscribers} subscribers at {TICK_RATE:g} Hz, "
              f"{seconds:g} s a run, {rounds} runs a side; subscriber streams: "
              f"{ended or 'all ran to the end'}")
    return [
        value_row("dqpose serve: the server's cores above the relay's", cores,
                  lambda x: f"{x:+.2f} cores", 0.15, "≤ 0.15 core", "—", detail,
                  beside=f"world {world['cores']:.2f} cores, relay {relay['cores']:.2f}"),
        value_row("dqpose serve: the answers' p99 above the relay's", p99,
                  lambda x: f"{x:+.2f} ms", 3.0, "≤ 3 ms", "—", detail,
                  beside=f"world p99 {world['p99']:.2f} ms, relay {relay['p99']:.2f} ms"),
    ]


HEAD = ["case", "dqpose (CPU a call)", "beside", "ratio: median [range] over rounds", "target",
        "holds", "CPU share of wall: dqpose / beside", "detail"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=5, help="alternated rounds (default %(default)s)")
    ap.add_argument("--seconds", type=float, default=0.3,
                    help="seconds of the tick scene a round of dqpose runs (default %(default)s)")
    ap.add_argument("--ticks", type=int, default=100,
                    help="GTSAM's ticks of body 0 a round (default %(default)s)")
    ap.add_argument("--lookups", type=int, default=60,
                    help="Lookups a round and side (default %(default)s)")
    ap.add_argument("--bodies", type=int, default=100)
    ap.add_argument("--history", type=float, default=HISTORY,
                    help="seconds of the tick scene taken in before the rounds (default "
                         "%(default)s)")
    ap.add_argument("--serve", action="store_true",
                    help="also the dqpose serve rows against the relay (minutes)")
    ap.add_argument("--serve-rounds", type=int, default=3)
    ap.add_argument("--serve-seconds", type=float, default=10.0)
    args = ap.parse_args(argv)
    load0 = os.getloadavg()[0]
    rows = tick_rows(args.rounds, args.seconds, args.ticks, args.bodies, args.history)
    rows += lookup_rows(args.rounds, args.lookups)
    if args.serve:
        rows += serve_rows(args.serve_rounds, args.serve_seconds)
    print(f"bench_engine: dqpose beside GTSAM 4.3, {args.rounds} rounds alternated; load "
          f"{load0:.1f} at the start, {os.getloadavg()[0]:.1f} at the end; each side's CPU time "
          f"(its thread's), {os.cpu_count()} CPUs")
    print(markdown(HEAD, rows))
    print()
    print(ESTIMATORS)
    return 0


if __name__ == "__main__":
    sys.exit(main())
