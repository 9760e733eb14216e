"""The reliability probe's attacks on a running server, for the bystander benchmark's attack rows
(``tests/bench/bench_bystander.py``): each is ``attack(target, stop)``, run in a process of its
own (as an attacker's client would be) until the ``stop`` event is set, then closing what it
opened. A new attack is a function here and a line in :data:`ATTACKS`.
"""
from __future__ import annotations

import os
import re
import sys
import threading
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass
from typing import Callable, Optional

import grpc
import numpy as np

from dqpose import dq, lie
from dqpose.fusion import Source

#: the world the World attacks meet: bodies, one camera, measurements per second of each body
BODIES, RATE = 10, 30.0
SIGMA = np.eye(6) * 1e-6


def fed_world(target: str, stop) -> None:
    """The world an attack meets: :data:`BODIES` bodies at :data:`RATE` Hz of measurement time,
    published paced on the wall clock into the default world (configured here) by an ordinary
    producer, and an ordinary subscriber reading every answer, until ``stop`` is set."""
    from dqpose.rpc.client import Batch, Client

    def subscriber():
        with Client(target) as reader:
            for _ in reader.subscribe():
                if stop.is_set():
                    return

    names = [f"body{b}" for b in range(BODIES)]
    poses = lie.se3_exp(0.1 * np.random.default_rng(0).normal(size=(BODIES, 6)))

    def batches():
        k, t0 = 0, time.time()
        while not stop.is_set():
            k += 1
            # on the Unix clock: a row's world goes on from the last row's
            yield Batch(poses, np.repeat(SIGMA[None], BODIES, 0), None, ["cam"] * BODIES, names,
                        np.full(BODIES, t0 + k / RATE))
            time.sleep(max(0.0, t0 + k / RATE - time.time()))

    with Client(target) as client:
        client.configure_world([Source("cam", dq.identity())], window=2.0,
                               twist_covariance=np.eye(6) * 1e-2)
        threading.Thread(target=subscriber, daemon=True).start()
        for _ in client.publish(batches(), producer=f"feed-{os.getpid()}"):
            pass


def nothing(target: str, stop) -> None:
    """No attack: the row of what the attacks' background alone costs."""
    stop.wait()


def never_read_subscriptions(target: str, stop, calls: int = 64, again: float = 5.0) -> None:
    """P4: one client opens ``calls`` SubscribeBatches of every body on a channel that buffers
    almost nothing unread (no window growth) and never reads them; every ``again`` s it reads
    how each ended (on stderr), cancels them and opens as many again on a new channel."""
    from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb

    request = wpb.SubscribeRequest(rate_hz=0.0)
    while not stop.is_set():
        channel = grpc.insecure_channel(target, options=[("grpc.http2.bdp_probe", 0),
                                                         ("grpc.http2.lookahead_bytes", 1024)])
        subscribe = channel.unary_stream(
            "/dqpose.v1.World/SubscribeBatches",
            request_serializer=wpb.SubscribeRequest.SerializeToString)
        held = [subscribe(request) for _ in range(calls)]
        stop.wait(again)
        print(f"attack round: {_ended(held)}", file=sys.stderr, flush=True)
        for call in held:
            call.cancel()
        channel.close()


def _ended(calls, wait: float = 2.0) -> str:
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
    return ", ".join(f"{n} {code}" for code, n in sorted(codes.items()))


@dataclass(frozen=True)
class Attack:
    """An attack (``attack(target, stop)``) and the ordinary traffic it meets (``background``,
    the same shape, running for ``warmup`` s before the row's baseline and until its memory has
    been looked at; None: none)."""

    attack: Callable
    background: Optional[Callable] = None
    warmup: float = 3.0


#: the fed world's warm-up: its fits kept (dqpose.world's cache of 4096) filled once, 300 a
#: second, so that the baseline holds them
WORLD_WARMUP = 16.0


#: name -> the attack
ATTACKS = {
    "the world fed and read (no attack)": Attack(nothing, fed_world, WORLD_WARMUP),
    "P4: 64 never-read SubscribeBatches, reopened every 5 s": Attack(
        never_read_subscriptions, fed_world, WORLD_WARMUP),
}
