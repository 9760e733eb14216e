"""The reliability probe's attacks on a running server (issue 36), for the bystander benchmark's
attack rows (``tests/bench/bench_bystander.py``) and their smoke test: each is
``attack(served, stop, **kw)``, run in a process of its own (as an attacker's client would be)
until the ``stop`` event is set, then closing what it opened and returning its outcome, a
``Counter`` of what the server did with it ("refused max_time": 3000, ...). A new attack is a
function here and a line in :data:`ATTACKS`, with the server it needs (:class:`Setup`) and the
outcome the server must give it.

P7 and P8 (a damaged or oversized recording) are not here: they reach the file readers of
``dqpose replay`` and ``export``, never a running server.
"""
from __future__ import annotations

import contextlib
import os
import re
import socket
import subprocess
import threading
import time
import urllib.error
import urllib.request
from collections import Counter, deque
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass, field
from typing import Callable, Optional

import grpc
import numpy as np

from dqpose import dq, lie
from dqpose.fusion import Source
from dqpose.rpc.calls import MAX_DETAILS

#: the world the World attacks meet: bodies, one camera, measurements per second of each body
BODIES, RATE = 10, 30.0
SIGMA = np.eye(6) * 1e-6
NAMES = [f"body{b}" for b in range(BODIES)]


@dataclass(frozen=True)
class Served:
    """How an attack reaches the server: its address, the bearer token it was started with, the
    ports of its live WebSocket and metrics (None: not served)."""

    target: str
    token: Optional[str] = None
    live_port: Optional[int] = None
    metrics_port: Optional[int] = None

    @property
    def metadata(self) -> Optional[list]:
        return [("authorization", f"Bearer {self.token}")] if self.token else None

    def client(self, world: Optional[str] = None):
        from dqpose.rpc.client import Client
        return Client(self.target, token=self.token, world=world)


@dataclass(frozen=True)
class Setup:
    """What ``dqpose serve`` needs for an attack: its flags, the token its ``--token-file``
    holds, the port given to ``--metrics-port``."""

    flags: tuple = ()
    token: Optional[str] = None
    metrics_port: Optional[int] = None


def served(target: str, events: list, setup: Setup) -> Served:
    """A server of ``setup`` at ``target`` that logged ``events`` before serving."""
    live = [e["port"] for e in events if e.get("event") == "live"]
    return Served(target, setup.token, live[0] if live else None, setup.metrics_port)


class Unavailable(Exception):
    """A setup this machine cannot make (a tmpfs without root)."""


@contextlib.contextmanager
def default_server(tmp: str):
    """``dqpose serve`` with its default flags."""
    yield Setup()


TOKEN = "bystander-bench-token"


@contextlib.contextmanager
def live_with_token(tmp: str):
    """``--token-file`` with ``--live`` on the loopback and the metrics port."""
    path = os.path.join(tmp, "token")
    with open(path, "w") as f:
        f.write(TOKEN + "\n")
    with socket.socket() as s:          # a free port (--metrics-port 0 does not say which)
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    yield Setup(("--live", "127.0.0.1:0", "--token-file", path, "--metrics-port", str(port)),
                TOKEN, port)


#: the issue's full disk
DISK = "120k"


@contextlib.contextmanager
def recording_to_a_small_disk(tmp: str):
    """``--record`` into a :data:`DISK` tmpfs (mounted here, root only; unmounted after)."""
    disk = os.path.join(tmp, "disk")
    os.makedirs(disk, exist_ok=True)
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={DISK}", "tmpfs", disk],
                         capture_output=True, text=True)
    if res.returncode:
        raise Unavailable(f"cannot mount a tmpfs: {res.stderr.strip()}")
    try:
        yield Setup(("--record", os.path.join(disk, "runs")))
    finally:
        subprocess.run(["umount", "-l", disk], check=True)


def run(fn: Callable, served: Served, stop, out, kw: dict) -> None:
    """``fn(served, stop, **kw)`` in an attacker's process: its outcome sent on ``out``."""
    try:
        outcome = fn(served, stop, **kw)
    except Exception as e:      # said as the outcome: a row must show an attack that broke
        outcome = Counter({f"raised {type(e).__name__}: {str(e)[:200]}": 1})
    out.send(outcome)


def surprises(outcome: Counter, expected, allowed=()) -> list:
    """What is wrong with ``outcome``: an ``expected`` key it lacks, a key neither expected nor
    ``allowed``."""
    return ([f"no {k!r}" for k in expected if not outcome[k]]
            + [f"{k!r} x{n}" for k, n in outcome.items() if n and k not in expected
               and k not in allowed])


def said(outcome: Counter) -> str:
    return ", ".join(f"{n} {k}" for k, n in sorted(outcome.items()) if n)


# ---- the ordinary traffic an attack meets

def fed_world(served: Served, stop) -> Counter:
    """The world an attack meets: :data:`BODIES` bodies at :data:`RATE` Hz of measurement time,
    published paced on the wall clock into the default world (configured here) by an ordinary
    producer, and an ordinary subscriber reading every answer, until ``stop`` is set. Its
    outcome: acks and answers, and the errors among them."""
    from dqpose.rpc.client import Batch, RpcError
    outcome: Counter = Counter()
    reader = served.client()

    def subscriber():
        try:
            for a in reader.subscribe():
                outcome["answers" if a.error is None else "answer errors"] += 1
        except RpcError as e:
            if not stop.is_set():       # else: closed below
                outcome[f"subscription ended {e.code.name}"] += 1

    poses = lie.se3_exp(0.1 * np.random.default_rng(0).normal(size=(BODIES, 6)))

    def batches():
        k, t0 = 0, time.time()
        while not stop.is_set():
            k += 1
            # on the Unix clock: a row's world goes on from the last row's
            yield Batch(poses, np.repeat(SIGMA[None], BODIES, 0), None, ["cam"] * BODIES, NAMES,
                        np.full(BODIES, t0 + k / RATE))
            time.sleep(max(0.0, t0 + k / RATE - time.time()))

    with served.client() as client:
        client.configure_world([Source("cam", dq.identity())], window=2.0,
                               twist_covariance=np.eye(6) * 1e-2)
        reading = threading.Thread(target=subscriber, daemon=True)
        reading.start()
        # a producer of its own: a name a world has seen is numbered on from where it was
        for ack in client.publish(batches(), producer=f"feed-{os.getpid()}-{time.time_ns()}"):
            outcome["acks" if not ack.errors else "ack errors"] += 1
        reader.close()
        reading.join(10)
    return outcome


#: what the fed world must see beside any attack: its acks and answers, no error
FED = ("acks", "answers")


def nothing(served: Served, stop) -> Counter:
    """No attack: the row of what the attacks' background alone costs."""
    stop.wait()
    return Counter()


# ---- P1: times the server's limits refuse

def _refusal(details: str) -> str:
    """An ack error's kind: the limit it names, else its field (indices left out)."""
    for limit in ("max_time_jump", "max_time"):
        if limit in details:
            return f"refused {limit}"
    return "refused " + re.sub(r"\[\d+\]", "[]", details.split(":")[0].split(".", 1)[-1])


def far_times(served: Served, stop, period: float = 0.01) -> Counter:
    """P1, mixed into the fed world: every ``period`` s one request of this producer's, either
    each body at 1e300, 1e11 and -1e11 s (beyond ``max_time``) or each body twice
    (``max_time_jump`` past its newest: a jump only another producer may confirm)."""
    from dqpose.limits import DEFAULT
    from dqpose.rpc.client import Batch
    outcome: Counter = Counter()
    sizes: deque = deque()

    def batches():
        k = 0
        while not stop.is_set():
            k += 1
            if k % 2:
                bodies, times = NAMES * 3, np.repeat([1e300, 1e11, -1e11], BODIES)
            else:
                bodies = NAMES * 2
                times = np.full(2 * BODIES, time.time() + 2 * DEFAULT.max_time_jump + k * 1e-3)
            sizes.append(len(bodies))
            yield Batch(np.repeat(dq.identity()[None], len(bodies), 0), None, None,
                        ["cam"] * len(bodies), bodies, times)
            stop.wait(period)

    with served.client() as client:
        for ack in client.publish(batches(), producer=f"p1-{os.getpid()}"):
            outcome["accepted"] += sizes.popleft() - len(ack.errors)
            for _, _, details in ack.errors:
                outcome[_refusal(details)] += 1
    return outcome


# ---- P2: names of a megabyte

def _publish_raw(served: Served, requests, outcome: Counter) -> None:
    """Publish requests of ready bytes on one stream; their ack errors counted."""
    from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb
    sizes: deque = deque()

    def sent():
        for n, data in requests:
            sizes.append(n)
            yield data

    with grpc.insecure_channel(served.target) as ch:
        for data in ch.stream_stream("/dqpose.v1.World/Publish")(sent(),
                                                                 metadata=served.metadata):
            ack = wpb.PublishAck.FromString(data)
            outcome["accepted"] += max(0, sizes.popleft() - len(ack.errors))
            for e in ack.errors:
                outcome[_refusal(e.details)] += 1
                if len(e.details.encode()) > MAX_DETAILS:
                    outcome["details over MAX_DETAILS"] += 1


def long_names(served: Served, stop, producers: int = 300, bodies: int = 300,
               size: int = 10**6) -> Counter:
    """P2, rounds into the fed world until ``stop``: ``producers`` Publish requests each from a
    producer of another ``size``-byte name, ``bodies`` requests each of a body of another
    ``size``-byte name; a Lookup of a ``size``-byte body and in a ``size``-byte world, and one
    of an unknown body (its NOT_FOUND names the world's bodies)."""
    from dqpose.rpc.client import Batch
    from dqpose.rpc.wire import publish_request_wire
    outcome: Counter = Counter()

    def long(k: int) -> str:
        return f"{os.getpid()}-{k}-".ljust(size, "x")

    def one(body: str) -> Batch:
        return Batch(dq.identity()[None], SIGMA[None], None, ["cam"], [body],
                     np.array([time.time()]))

    def requests(n, make):
        for k in range(n):
            if stop.is_set():
                return
            yield 1, make(k)

    def lookup(what: str, request, metadata=None):
        try:
            lookup_call(request, metadata=(served.metadata or []) + (metadata or []),
                        timeout=30)
            outcome[f"Lookup {what}: OK"] += 1
        except grpc.RpcError as e:
            outcome[f"Lookup {what}: {e.code().name}"] += 1
            if len(e.details() or "") > MAX_DETAILS:
                outcome["details over MAX_DETAILS"] += 1

    from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb
    with grpc.insecure_channel(served.target) as ch:
        lookup_call = ch.unary_unary("/dqpose.v1.World/Lookup",
                                     request_serializer=wpb.LookupRequest.SerializeToString)
        k = 0
        while not stop.is_set():
            _publish_raw(served, requests(producers, lambda i: publish_request_wire(
                one(NAMES[0]), long(k + i), 0)), outcome)
            _publish_raw(served, requests(bodies, lambda i: publish_request_wire(
                one(long(k + i)), "p2", 0)), outcome)
            k += producers + bodies
            lookup("of a long body", wpb.LookupRequest(source=long(k)))
            lookup("in a long world", wpb.LookupRequest(source=NAMES[0]),
                   [("x-dqpose-world", long(k))])
            lookup("of an unknown body", wpb.LookupRequest(source="nobody"))
    return outcome


# ---- P3: the costliest legal Publish

def costliest_publish(served: Served, stop, n: int = 1000,
                      rate: Optional[float] = None) -> Counter:
    """P3: in a plain and a robust world of their own, each with a subscriber at ``rate`` Hz
    (None: the server's default ``max_output_rate``, 1 kHz), one Publish request after the
    other (each acked before the next) of ``n`` measurements of one body at ``n`` times 1 ms
    apart, 2 s after the last request's (its window holds this request's alone): a tick due
    every ms, each fusing all ``n``, more than ``max_fused_per_request`` affords. (At rate 0 a
    request is answered once a body, at its newest measurement: one fit of ``n``, far within
    the budget.)"""
    from dqpose.limits import DEFAULT
    from dqpose.rpc.client import Batch, RpcError
    rate = DEFAULT.max_output_rate if rate is None else rate
    outcome: Counter = Counter()
    worlds = {"p3-plain": False, "p3-robust": True}
    readers = [served.client(world) for world in worlds]

    def subscriber(reader):
        try:
            for a in reader.subscribe(rate_hz=rate):
                if a.error is None:
                    outcome["answers"] += 1
                elif "max_fused_per_request" in a.error:
                    outcome["ticks skipped (max_fused_per_request)"] += 1
                else:
                    outcome["answer errors"] += 1
        except RpcError as e:
            if not stop.is_set():       # else: closed below
                outcome[f"subscription ended {e.code.name}"] += 1

    clients = [served.client(world) for world in worlds]
    reading = [threading.Thread(target=subscriber, args=(r,), daemon=True) for r in readers]
    for c, robust, t in zip(clients, worlds.values(), reading):
        c.configure_world(window=1.0, buffer=10.0, robust=robust)
        t.start()
    stop.wait(0.5)          # the subscriptions open before the first request
    poses = lie.se3_exp(1e-3 * np.random.default_rng(0).normal(size=(n, 6)))
    k, t0 = 0, time.time()      # on from any earlier run's times in these worlds
    while not stop.is_set():
        for c in clients:
            times = t0 + 2 * k + np.arange(n) * 1e-3
            [ack] = c.publish([Batch(poses, np.repeat(SIGMA[None], n, 0), None, ["cam"] * n,
                                     ["box"] * n, times)], producer="p3", first_sequence=0)
            outcome["acked" if not ack.errors else "ack errors"] += 1
        k += 1
    for c in clients + readers:
        c.close()
    for t in reading:
        t.join(10)
    return outcome


# ---- P4: subscriptions never read

def never_read_subscriptions(served: Served, stop, calls: int = 64, again: float = 5.0) -> Counter:
    """P4: one client opens ``calls`` SubscribeBatches of every body on a channel that buffers
    almost nothing unread (no window growth) and never reads them; every ``again`` s it reads
    how each ended, cancels them and opens as many again on a new channel."""
    from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb

    request = wpb.SubscribeRequest(rate_hz=0.0)
    outcome: Counter = Counter()
    while not stop.is_set():
        channel = grpc.insecure_channel(served.target, options=[
            ("grpc.http2.bdp_probe", 0), ("grpc.http2.lookahead_bytes", 1024)])
        subscribe = channel.unary_stream(
            "/dqpose.v1.World/SubscribeBatches",
            request_serializer=wpb.SubscribeRequest.SerializeToString)
        held = [subscribe(request, metadata=served.metadata) for _ in range(calls)]
        stop.wait(again)
        outcome.update(_ended(held))
        for call in held:
            call.cancel()
        channel.close()
    return outcome


def _ended(calls, wait: float = 2.0) -> Counter:
    """How ``calls`` ended: each read for at most ``wait`` s together, its status counted by
    code and the limit its text names (still open: OPEN)."""
    codes: Counter = Counter()

    def drain(call):
        try:
            for _ in call:
                pass
            return "OK"
        except grpc.RpcError as e:
            limit = re.search(r"limit (\w+)", e.details() or "")
            return e.code().name + (f" {limit[1]}" if limit else "")

    with ThreadPoolExecutor(len(calls)) as pool:
        futures = [pool.submit(drain, c) for c in calls]
        deadline = time.monotonic() + wait
        for f in futures:
            try:
                codes[f.result(max(0.0, deadline - time.monotonic()))] += 1
            except FutureTimeout:
                codes["OPEN"] += 1
        for c in calls:
            c.cancel()
    return codes


# ---- P5: the live view and the metrics without the token

def unauthenticated_live(served: Served, stop) -> Counter:
    """P5: one client after the other opening the live WebSocket as Foxglove does
    (``foxglove.sdk.v1``) without the token: from a web page's Origin, without an Origin, with
    a wrong ``?token=``; and scraping the metrics port without the token."""
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect
    url = f"ws://127.0.0.1:{served.live_port}"
    tries = {"no token, Origin http://evil.example": (url, "http://evil.example"),
             "no token": (url, None), "a wrong token": (f"{url}/?token=wrong", None)}
    outcome: Counter = Counter()
    while not stop.is_set():
        for what, (u, origin) in tries.items():
            try:
                with connect(u, subprotocols=["foxglove.sdk.v1"], origin=origin,
                             open_timeout=30):
                    outcome[f"live, {what}: let in"] += 1
            except InvalidStatus as e:
                outcome[f"live, {what}: {e.response.status_code}"] += 1
        try:
            urllib.request.urlopen(f"http://127.0.0.1:{served.metrics_port}/metrics",
                                   timeout=30).read()
            outcome["metrics, no token: 200"] += 1
        except urllib.error.HTTPError as e:
            outcome[f"metrics, no token: {e.code}"] += 1
    return outcome


# ---- P6: recording to a full disk

def fill_the_disk(served: Served, stop, period: float = 0.01, every: float = 0.25) -> Counter:
    """P6, on a server recording to a small disk: a Fuse call of 50 random poses (little to
    compress) every ``period`` s, every ``every`` s what the health service says of the
    recording (``dqpose.record``) and of the server ("")."""
    from dqpose.record import HEALTH_SERVICE
    from dqpose.rpc.client import RpcError
    rng = np.random.default_rng(7)
    outcome: Counter = Counter()
    asked = 0.0
    with served.client() as c:
        while not stop.is_set():
            try:
                c.fuse(dq.normalize(rng.normal(size=(50, 8))), weights=np.ones(50))
                outcome["Fuse OK"] += 1
            except RpcError as e:
                outcome[f"Fuse {e.code.name}"] += 1
            if time.monotonic() - asked > every:
                asked = time.monotonic()
                for service in (HEALTH_SERVICE, ""):
                    outcome[f"health {service or 'server'} {c.health(service)}"] += 1
            stop.wait(period)
    return outcome


@dataclass(frozen=True)
class Attack:
    """An attack (``attack(served, stop)``) and the ordinary traffic it meets (``background``,
    the same shape, running for ``warmup`` s before the row's baseline and until its memory has
    been looked at; None: none), on a server of ``setup``; the outcome keys it must show
    (``expected``) and may show (``allowed``); ``quick``, its arguments for a short run of
    ``quick_seconds``."""

    attack: Callable
    background: Optional[Callable] = None
    warmup: float = 3.0
    setup: Callable = default_server
    expected: tuple = ()
    allowed: tuple = ()
    quick: dict = field(default_factory=dict)
    quick_seconds: float = 1.0


#: the fed world's warm-up: its fits kept (dqpose.world's cache of 4096) filled once, 300 a
#: second, so that the baseline holds them
WORLD_WARMUP = 16.0


#: name -> the attack
ATTACKS = {
    "the world fed and read (no attack)": Attack(nothing, fed_world, WORLD_WARMUP),
    "P1: bodies at 1e300, 1e11, -1e11 s and one producer's jumps, 100 requests/s": Attack(
        far_times, fed_world, WORLD_WARMUP,
        expected=("refused max_time", "refused max_time_jump")),
    "P2: 300 producers and 300 bodies of 1 MB names, Lookups of 1 MB names, in rounds": Attack(
        long_names, fed_world, WORLD_WARMUP,
        expected=("refused producer", "refused measurements[].body",
                  "Lookup of a long body: INVALID_ARGUMENT",
                  # gRPC's own bound on a header (16 KiB), before any handler
                  "Lookup in a long world: RESOURCE_EXHAUSTED",
                  "Lookup of an unknown body: NOT_FOUND"),
        quick=dict(producers=2, bodies=2)),
    "P3: the costliest legal Publish, 1,000 measurements, a 1 kHz subscriber, plain and robust "
    "world, back to back": Attack(
        costliest_publish, fed_world, WORLD_WARMUP,
        expected=("acked", "answers", "ticks skipped (max_fused_per_request)")),
    "P4: 64 never-read SubscribeBatches, reopened every 5 s": Attack(
        never_read_subscriptions, fed_world, WORLD_WARMUP,
        expected=("RESOURCE_EXHAUSTED max_peer_subscriptions",
                  "RESOURCE_EXHAUSTED max_write_wait"),
        # an admitted one is ended a second after its first write waited
        quick=dict(again=2.5), quick_seconds=2.5),
    "P5: WebSocket clients without the token on --live, metrics scraped without it": Attack(
        unauthenticated_live, fed_world, WORLD_WARMUP, live_with_token,
        expected=("live, no token, Origin http://evil.example: 403", "live, no token: 401",
                  "live, a wrong token: 401", "metrics, no token: 401")),
    f"P6: Fuse calls recorded (--record) to a full {DISK} tmpfs": Attack(
        fill_the_disk, setup=recording_to_a_small_disk,
        expected=("Fuse OK", "health server SERVING", "health dqpose.record NOT_SERVING"),
        allowed=("health dqpose.record SERVING",)),
}
