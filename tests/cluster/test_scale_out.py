"""Scale-out on one machine: ``dqpose cluster`` (``make cluster``) in its own process, its
replicas behind a real HAProxy running docker/haproxy.cfg rewritten for them;
``Client.last_replica`` through it; the shipped configuration starting while a replica's name
does not resolve; a World call's log lines naming its world; a stream whose replica is lost,
without ``reconnect``, ending with an error that says so and names ``reconnect``."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading

import numpy as np
import pytest

from dqpose.cli.cluster import Proxy, Replica, free_port, missing
from dqpose.rpc.client import Client, RpcError
from tests._polling import wait_until
from tests.cluster._cluster import DOCKER, ROOT
from tests.rpc.test_world_service import SOURCES, measurements

IDENTITY = np.array([1.0, 0, 0, 0, 0, 0, 0, 0])
HAPROXY_CFG = os.path.join(DOCKER, "haproxy.cfg")


class Command:
    """``dqpose cluster --replicas 2`` in a process of its own; its standard error read by a
    thread (JSON events in ``events``) once its ``cluster`` event came."""

    def __init__(self):
        self.port = free_port()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "dqpose.cli", "cluster", "--replicas", "2", "--port",
             str(self.port)], cwd=ROOT, stderr=subprocess.PIPE, text=True)
        self.lines: list[str] = []
        self.events: list[dict] = []
        self.started = threading.Event()
        threading.Thread(target=self._read, daemon=True).start()
        if not self.started.wait(180) or not self.cluster:
            self.stop()
            raise AssertionError(f"dqpose cluster did not start: {''.join(self.lines)}")
        self.target = self.cluster["address"]

    @property
    def cluster(self) -> dict:
        return next((e for e in self.events if e.get("event") == "cluster"), {})

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.lines.append(line)
            if line.startswith("{"):
                self.events.append(json.loads(line))
                if self.events[-1].get("event") == "cluster":
                    self.started.set()
        self.started.set()

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)          # Ctrl-C
        try:
            return self.proc.wait(60)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait(10)


@pytest.fixture(scope="module")
def command():
    why = missing("haproxy")
    if why:
        pytest.skip(why)
    c = Command()
    yield c
    c.stop()


def test_make_cluster_serves_its_replicas_behind_haproxy_and_stops_them(command):
    replicas = command.cluster["replicas"]
    assert sorted(replicas) == ["r1", "r2"]
    assert command.target == f"127.0.0.1:{command.port}"
    with Client(command.target) as c:
        assert c.last_replica is None                   # no call yet
        seen = set()
        for _ in range(20):                             # stateless calls: balanced per call
            c.blend(np.stack([IDENTITY, IDENTITY]))
            seen.add(c.last_replica)
        assert seen == {"r1", "r2"}
        assert c.health() == "SERVING" and c.last_replica in replicas
    with Client(command.target, world="cell-3") as c:   # a world's calls: one replica
        owners = set()
        for _ in range(6):
            c.blend(np.stack([IDENTITY, IDENTITY]))
            owners.add(c.last_replica)
        c.configure_world(SOURCES)
        owners.add(c.last_replica)
        with pytest.raises(RpcError) as e:              # refused: said by the same replica
            c.lookup("", "no-such-body")
        assert e.value.code.name == "NOT_FOUND"
        owners.add(c.last_replica)
        acks = list(c.publish([measurements("cam1", [1.0], 0)], producer="cam1"))
        assert acks[0].acked_through == 1
        owners.add(c.last_replica)
        assert len(owners) == 1 and owners <= set(replicas), owners


def test_the_shipped_haproxy_cfg_starts_while_a_replica_does_not_resolve(command):
    """A replica whose name does not resolve (its container not up yet) is left down: HAProxy
    starts and serves with the others (it refused to start: 'could not resolve address')."""
    replica = command.cluster["replicas"]["r1"]["address"]
    proxy = Proxy("haproxy", HAPROXY_CFG, [("r1", replica), ("dqpose-2", "dqpose-2:50051")])
    try:
        with Client(proxy.target) as c:
            for _ in range(5):
                c.blend(np.stack([IDENTITY, IDENTITY]))
                assert c.last_replica == "r1"
    finally:
        proxy.stop()


def test_every_world_log_line_names_its_world():
    replica = Replica("logs", call_log=True)
    try:
        with Client(replica.address, world="cell-9") as c:
            c.configure_world(SOURCES)
            list(c.publish([measurements("cam1", [1.0], 0)], producer="cam1"))
            with pytest.raises(RpcError):
                c.lookup("", "no-such-body")
            with pytest.raises(RpcError):               # ends at its deadline
                list(c.subscribe(["box"], timeout=0.5))
        with Client(replica.address) as c:              # the default world
            c.configure_world(SOURCES)
        replica.signal(signal.SIGTERM)
        assert replica.proc.wait(30) == 0
    finally:
        replica.stop()
    calls = [e for e in replica.events if "rpc" in e and "code" in e]
    world = [(e["rpc"], e.get("world")) for e in calls if e["rpc"] in (
        "Configure", "Publish", "Lookup", "Subscribe", "SubscribeBatches")]
    assert sorted(world) == [("Configure", ""), ("Configure", "cell-9"), ("Lookup", "cell-9"),
                             ("Publish", "cell-9"), ("SubscribeBatches", "cell-9")], calls


def test_a_lost_replica_without_reconnect_is_said_so_naming_reconnect(command):
    """The subscriber's replica SIGKILLed mid-stream, the client made without ``reconnect``:
    the error says the replica was lost and how to have the stream reopened (it was
    'UNKNOWN: Stream removed')."""
    world = "cell-lost"
    stop = threading.Event()
    with Client(command.target, world=world, reconnect=10.0) as producer:
        producer.configure_world(SOURCES)

        def publish():
            def batches():
                k = 0
                while not stop.is_set():
                    yield measurements("cam1", [1.0 + 0.1 * k], k)
                    k += 1
                    stop.wait(0.1)
            try:
                for _ in producer.publish(batches(), producer="cam1"):
                    pass
            except RpcError:
                pass

        publisher = threading.Thread(target=publish, daemon=True)
        publisher.start()
        try:
            with Client(command.target, world=world) as c:
                answers = c.subscribe(["box"])
                next(answers)
                owner = command.cluster["replicas"][c.last_replica]
                os.kill(owner["pid"], signal.SIGKILL)
                with pytest.raises(RpcError) as e:
                    for _ in answers:
                        pass
        finally:
            stop.set()
            publisher.join(30)
    assert e.value.code.name == "UNAVAILABLE", e.value
    assert "replica was lost" in e.value.details and "reconnect=" in e.value.details, e.value
    # the command goes on with the replica that is left, and says which one ended
    assert wait_until(lambda: any(ev.get("event") == "replica_ended" for ev in command.events),
                      timeout=10, poll=0.1), command.lines[-5:]
    assert command.stop() == 0
