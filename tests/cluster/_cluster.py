"""A cluster on 127.0.0.1: ``dqpose serve`` replicas (processes) behind a real HAProxy or nginx
running the shipped config (docker/haproxy.cfg, docker/nginx.conf) rewritten for them as
``dqpose cluster`` does (:mod:`dqpose.cli.cluster`: ``Replica``, ``Proxy``); ``WorldLoad``, one
world's producers and subscriber through it (the cluster test's and bench_cluster's)."""
from __future__ import annotations

import os
import threading
import time

from dqpose.cli import cluster
from dqpose.cli.cluster import (  # noqa: F401 (the tests' names)
    BEHIND_PROXY,
    Replica,
    free_port,
    missing,
)
from dqpose.rpc.client import Client
from tests.rpc.test_world_service import SOURCES, measurements

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
DOCKER = os.path.join(ROOT, "docker")


class Proxy(cluster.Proxy):
    """The shipped config of ``kind`` ("haproxy" or "nginx") in front of ``addresses`` (the
    replicas named r1, r2, ... in order), on a free loopback port (``.target``)."""

    def __init__(self, kind: str, addresses: list[str]):
        super().__init__(kind, os.path.join(DOCKER, cluster.PROXIES[kind][2]),
                         [(f"r{k + 1}", a) for k, a in enumerate(addresses)])


class Cluster:
    """Three replicas (r1, r2, r3) behind one proxy."""

    def __init__(self, kind: str, *flags: str):
        self.replicas: list[Replica] = []
        self.proxy = None
        try:
            for i in range(3):
                self.replicas.append(Replica(f"r{i + 1}", *BEHIND_PROXY, *flags))
            self.proxy = Proxy(kind, [r.address for r in self.replicas])
        except BaseException:
            self.stop()
            raise

    def replica(self, name: str) -> Replica:
        return next(r for r in self.replicas if r.name == name)

    def restart(self, name: str) -> Replica:
        """Replica ``name`` (which has exited) started again on its port, as an orchestrator
        restarts it: the proxy's configuration stays as it is."""
        k = next(i for i, r in enumerate(self.replicas) if r.name == name)
        old = self.replicas[k]
        assert old.proc.poll() is not None, f"replica {name} still runs"
        self.replicas[k] = Replica(name, *old.flags, port=old.port)
        return self.replicas[k]

    def stop(self) -> None:
        if self.proxy is not None:
            self.proxy.stop()
        for r in self.replicas:
            r.stop()


def wait(seconds: float) -> None:
    """A pause the proxies' timers need (a health check's interval), not a bound on anything."""
    time.sleep(seconds)


PERIOD = 0.1     # s between one producer's batches (measurement time is the clock's)


class WorldLoad:
    """One world through the proxy: its client (configured, ``reconnect``), two producers
    (cam1, cam2) publishing the box at the clock's time, a subscriber; every ack and answer kept
    with its arrival time, every error raised kept."""

    def __init__(self, target: str, name: str, t0: float, stop: threading.Event):
        self.name, self.t0, self.stop = name, t0, stop
        self.client = Client(target, world=name, reconnect=10.0)
        self.client.configure_world(SOURCES, window=1.0)
        self.sent: dict[str, list[float]] = {"cam1": [], "cam2": []}
        self.acks: dict[str, list] = {"cam1": [], "cam2": []}
        self.answers: list = []
        self.errors: list[str] = []
        self.closing = False
        self.producers = [threading.Thread(target=self._produce, args=(s, k), daemon=True)
                          for k, s in enumerate(self.sent)]
        self.watcher = threading.Thread(target=self._watch, daemon=True)
        for t in [self.watcher, *self.producers]:
            t.start()

    def _produce(self, source: str, seed: int) -> None:
        def batches():
            k = 0
            while not self.stop.is_set():
                t = round(time.monotonic() - self.t0, 3)
                self.sent[source].append(t)
                yield measurements(source, [t], 1000 * seed + k)
                k += 1
                self.stop.wait(PERIOD)

        try:
            for a in self.client.publish(batches(), producer=source):
                self.acks[source].append((time.monotonic(), a))
        except Exception as e:          # noqa: BLE001 (every failure is the finding)
            self.errors.append(f"{self.name} {source}: {e}")

    def _watch(self) -> None:
        try:
            for a in self.client.subscribe(["box"], rate_hz=1 / PERIOD):
                self.answers.append((time.monotonic(), a))
        except Exception as e:          # noqa: BLE001
            if not self.closing:
                self.errors.append(f"{self.name} subscriber: {e}")

    def answered_after(self, t: float) -> bool:
        return (any(at > t for at, _ in self.answers)
                and all(any(at > t for at, _ in acks) for acks in self.acks.values()))

    def missing(self, t: float) -> str:
        """What has not answered since ``t``."""
        late = [f"{s} acks" for s, acks in self.acks.items() if not any(at > t for at, _ in acks)]
        late += [] if any(at > t for at, _ in self.answers) else ["subscriber"]
        return f"{self.name}: {', '.join(late)} {self.errors}"

    def end(self) -> None:
        """Producers finish (every batch acked), then the subscriber is closed."""
        for p in self.producers:
            p.join(30)
        self.closing = True
        self.client.close()
        self.watcher.join(30)
