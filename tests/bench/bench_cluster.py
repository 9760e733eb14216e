"""StreamFuse through HAProxy (the shipped docker/haproxy.cfg) in front of 1, 2 and 3
``dqpose serve`` replicas, against one replica direct; then the failover gap after a SIGKILL, of
StreamFuse streams and of World streams (named worlds) behind HAProxy and nginx.

    .venv/bin/python -m tests.bench.bench_cluster              # ~1.5 min
    .venv/bin/python -m tests.bench.bench_cluster --worlds 24 --seconds 10
    .venv/bin/python -m tests.bench.bench_cluster --world-failover-only

Load: ``--worlds`` worlds, each one ``Client(world=...).stream_fuse`` of one body, 20
measurements a message at one instant (a static fit of 20), in lockstep: a message is sent once
the answer to the one before it came (so the latency is a round trip: client, proxy, server's
queue and fit, back). Measurements/s = 20 x answers/s over ``--seconds``. The client is one
Python process with a thread per world.

Failover: the same load on 3 replicas; the replica holding the most worlds is SIGKILLed; per
world it held, the gap from its last answer before the kill to its first answer after (the
client's backoff, the proxy's reconnect to the replica its hash now picks, the resent message).

World failover: 30 named worlds on 3 fresh replicas behind each proxy, each world one
``Client(world=..., reconnect=10)`` with two producers publishing the box at 10 Hz (the clock's
time as measurement time) and a subscriber at 10 Hz (``WorldLoad``, the cluster test's); the
replica holding the most worlds is SIGKILLed after 3 s. Per moved world: the gap from the
subscriber's last answer before the kill to its first after, the same for the producers' acks
(the later of the two), the 10 Hz ticks never answered in between, and the measurements in the
first fit after the move against the median before it (the window refilling).
"""
from __future__ import annotations

import argparse
import os
import signal
import threading
import time

import numpy as np

from dqpose.rpc.client import Client
from tests.bench._table import markdown
from tests.cluster._cluster import BEHIND_PROXY, Proxy, Replica, missing

PER_MESSAGE = 20
IDENTITY = np.array([1.0, 0, 0, 0, 0, 0, 0, 0])


class World(threading.Thread):
    """One world's lockstep stream; ``answers`` holds (arrival time, round trip s)."""

    def __init__(self, target: str, name: str, stop: threading.Event):
        super().__init__(daemon=True)
        self.target, self.name, self.stop = target, name, stop
        self.answers: list[tuple[float, float]] = []
        self.error: Exception | None = None

    def run(self):
        answered = threading.Event()
        answered.set()
        sent = [0.0]
        poses = np.tile(IDENTITY, (PER_MESSAGE, 1))
        names = [f"s{i % 2}" for i in range(PER_MESSAGE)]

        def batches():
            i = 0
            while not self.stop.is_set():
                answered.wait()
                answered.clear()
                sent[0] = time.perf_counter()
                yield poses, None, None, names, ["body"] * PER_MESSAGE, [float(i)] * PER_MESSAGE
                i += 1

        try:
            with Client(self.target, world=self.name, reconnect=10.0) as c:
                for _ in c.stream_fuse(batches(), window=0.5):
                    now = time.perf_counter()
                    self.answers.append((now, now - sent[0]))
                    answered.set()
        except Exception as e:      # noqa: BLE001 (reported in the table)
            self.error = e


def load(target: str, worlds: int, seconds: float, during=None) -> list[World]:
    stop = threading.Event()
    threads = [World(target, f"cell-{i}", stop) for i in range(worlds)]
    for t in threads:
        t.start()
    time.sleep(1.0)                     # streams open, first answers in
    t0 = time.perf_counter()
    if during is not None:
        during(t0)
    time.sleep(seconds)
    stop.set()
    for t in threads:
        t.join(30)
    for t in threads:
        t.answers = [a for a in t.answers if a[0] >= t0 and a[0] <= t0 + seconds]
    return threads


def row(label: str, threads: list[World], seconds: float) -> list[str]:
    rtt = np.array([r for t in threads for _, r in t.answers]) * 1e3
    n = len(rtt)
    errors = sum(t.error is not None for t in threads)
    return [label, f"{n * PER_MESSAGE / seconds:,.0f}", f"{n / seconds:,.0f}",
            f"{np.percentile(rtt, 50):.2f}", f"{np.percentile(rtt, 99):.2f}", str(errors)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--worlds", type=int, default=12)
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--failover-only", action="store_true", help="only the SIGKILL tables")
    ap.add_argument("--world-failover-only", action="store_true",
                    help="only the World streams' SIGKILL table")
    args = ap.parse_args(argv)
    why = missing("haproxy")
    if why:
        print(why)
        return 2
    if args.world_failover_only:
        print(world_failover_table())
        return 0
    replicas = [Replica(f"r{i + 1}", *BEHIND_PROXY, "--drain", "1") for i in range(3)]
    lines: list[list[str]] = []
    try:
        for _ in () if args.failover_only else (1,):
            lines.append(row("1 replica, direct",
                         load(replicas[0].address, args.worlds, args.seconds), args.seconds))
        for n in () if args.failover_only else (1, 2, 3):
            proxy = Proxy("haproxy", [r.address for r in replicas[:n]])
            try:
                lines.append(row(f"HAProxy, {n} replica{'s' if n > 1 else ''}",
                                 load(proxy.target, args.worlds, args.seconds), args.seconds))
            finally:
                proxy.stop()
        if not args.failover_only:
            print(markdown(["path", "measurements/s", "answers/s", "round trip p50 ms",
                            "p99 ms", "streams failed"], lines))
            print()
        print(failover(replicas, args.worlds, args.seconds))
    finally:
        for r in replicas:
            r.stop()
    print()
    print(world_failover_table())
    print(f"\n{os.cpu_count()} cores; load average {os.getloadavg()[0]:.1f}")
    return 0


def failover(replicas: list[Replica], worlds: int, seconds: float) -> str:
    import grpc

    from dqpose.rpc import routing
    proxy = Proxy("haproxy", [r.address for r in replicas])
    try:
        owners = {}
        with grpc.insecure_channel(proxy.target) as ch:
            health = ch.unary_unary("/grpc.health.v1.Health/Check")
            for i in range(worlds):
                _, call = health.with_call(b"", metadata=[(routing.WORLD_HEADER, f"cell-{i}")],
                                           timeout=10)
                owners[f"cell-{i}"] = dict(call.initial_metadata())[routing.REPLICA_HEADER]
        victim_name = max(set(owners.values()), key=list(owners.values()).count)
        victim = next(r for r in replicas if r.name == victim_name)
        killed = [0.0]

        def kill(t0):
            def later():
                time.sleep(seconds / 2)
                killed[0] = time.perf_counter()
                victim.proc.send_signal(signal.SIGKILL)
            threading.Thread(target=later, daemon=True).start()

        threads = load(proxy.target, worlds, seconds, during=kill)
    finally:
        proxy.stop()
    gaps = []
    for t in threads:
        if owners[t.name] != victim_name:
            continue
        before = [a for a, _ in t.answers if a < killed[0]]
        after = [a for a, _ in t.answers if a >= killed[0]]
        gaps.append((after[0] - before[-1]) if before and after else float("inf"))
    gaps_ms = np.array(gaps) * 1e3
    errors = sum(t.error is not None for t in threads)
    for t in threads:
        if t.error is not None:
            print(f"{t.name}: {t.error}")
            break
    return markdown(["SIGKILL of the replica with most worlds", "worlds moved",
                     "gap median ms", "gap max ms", "streams failed"],
                    [[f"{victim_name} of 3", f"{len(gaps)} of {worlds}",
                      f"{np.median(gaps_ms):.0f}", f"{gaps_ms.max():.0f}", str(errors)]])



def world_failover_table(worlds: int = 30, before: float = 3.0, after: float = 4.0) -> str:
    rows = [world_failover(kind, worlds, before, after)
            for kind in ("haproxy", "nginx") if missing(kind) is None]
    return markdown(["SIGKILL, World streams", "worlds moved", "subscriber gap median ms",
                     "max ms", "producers' gap max ms", "ticks missed median (max)",
                     "fit after / before", "errors"], rows)


def world_failover(kind: str, worlds: int, before: float, after: float) -> list[str]:
    """One row: ``worlds`` WorldLoads behind ``kind``, the busiest replica SIGKILLed."""
    from tests.cluster._cluster import PERIOD, Cluster, WorldLoad

    cluster = Cluster(kind, "--drain", "1" if kind == "haproxy" else "0")
    try:
        target = cluster.proxy.target
        owners = {f"cell-{i}": _owner(target, f"cell-{i}") for i in range(worlds)}
        victim = max(set(owners.values()), key=list(owners.values()).count)
        stop = threading.Event()
        t0 = time.monotonic()
        loads = [WorldLoad(target, w, t0, stop) for w in owners]
        time.sleep(before)
        killed = time.monotonic()
        cluster.replica(victim).proc.send_signal(signal.SIGKILL)
        time.sleep(after)
        stop.set()
        for w in loads:
            w.end()
    finally:
        cluster.stop()
    sub_gaps, ack_gaps, missed, refill = [], [], [], []
    for w in loads:
        if owners[w.name] != victim:
            continue
        sub_gaps.append(_gap([at for at, _ in w.answers], killed))
        ack_gaps.append(max(_gap([at for at, _ in acks], killed) for acks in w.acks.values()))
        times = [a.time for _, a in w.answers]
        last = max((t for (at, _), t in zip(w.answers, times) if at < killed), default=None)
        first = min((t for (at, _), t in zip(w.answers, times) if at >= killed), default=None)
        if last is not None and first is not None:
            missed.append(round((first - last) / PERIOD) - 1)
        counts = [sum(s.count for s in a.fused.sources) for at, a in w.answers
                  if a.fused is not None]
        arrivals = [at for at, a in w.answers if a.fused is not None]
        k = next((i for i, at in enumerate(arrivals) if at >= killed), None)
        if k:
            refill.append((counts[k], float(np.median(counts[:k]))))
    errors = sum(len(w.errors) for w in loads)
    sub_ms, ack_ms = np.array(sub_gaps) * 1e3, np.array(ack_gaps) * 1e3
    fit = (f"{np.median([a for a, _ in refill]):.0f} / {np.median([b for _, b in refill]):.0f}"
           if refill else "-")
    return [f"{victim} of 3, {'HAProxy' if kind == 'haproxy' else 'nginx'}",
            f"{len(sub_gaps)} of {worlds}", f"{np.median(sub_ms):.0f}", f"{sub_ms.max():.0f}",
            f"{ack_ms.max():.0f}",
            f"{np.median(missed):.0f} ({max(missed)})" if missed else "-", fit, str(errors)]


def _gap(arrivals: list[float], killed: float) -> float:
    """Last arrival before ``killed`` to the first after (inf when either is missing)."""
    before = [a for a in arrivals if a < killed]
    after = [a for a in arrivals if a >= killed]
    return (after[0] - before[-1]) if before and after else float("inf")


def _owner(target: str, world: str) -> str:
    import grpc

    from dqpose.rpc import routing
    with grpc.insecure_channel(target) as ch:
        _, call = ch.unary_unary("/grpc.health.v1.Health/Check").with_call(
            b"", metadata=[(routing.WORLD_HEADER, world)], timeout=10)
    return dict(call.initial_metadata())[routing.REPLICA_HEADER]


if __name__ == "__main__":
    raise SystemExit(main())
