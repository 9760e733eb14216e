"""``rpc.resume`` through the client: StreamFuse, World.Publish and World.Subscribe streams whose
server went away reopen on the server that comes back at the address (another replica name):
every batch answered once (the unanswered ones sent again), the world's configuration sent again
first, a subscriber answered by the new server; a producer in lockstep with the answers."""
from __future__ import annotations

import json
import logging
import threading

import numpy as np
import pytest

from dqpose.rpc.client import Client, RpcError
from dqpose.rpc.server import ServerConfig
from tests._polling import wait_until
from tests.cluster._cluster import free_port
from tests.rpc._grpc_server import ServerThread

IDENTITY = np.array([1.0, 0, 0, 0, 0, 0, 0, 0])


def _batch(i: int):
    return np.stack([IDENTITY]), None, None, None, ["body"], [float(i)]


def test_a_producer_in_lockstep_with_the_answers_is_served():
    answered = threading.Event()
    answered.set()

    def lockstep():
        for i in range(50):
            assert answered.wait(10), "no answer to the batch before"
            answered.clear()
            yield _batch(i)

    out = []
    with ServerThread() as s, Client(s.target, reconnect=5.0) as c:
        for a in c.stream_fuse(lockstep()):
            out.append(a.request)
            answered.set()
    assert out == list(range(50))


def test_a_stream_resumes_on_the_server_back_at_its_address(caplog):
    port = free_port()
    first = ServerThread(ServerConfig(port=port, replica_name="before"))
    second: list[ServerThread] = []
    swap = threading.Event()

    def batches():
        for i in range(60):
            if i == 20:
                swap.set()
                assert wait_until(lambda: second, timeout=30, poll=0.01)
            yield _batch(i)
            wait_until(lambda: False, timeout=0.002)

    def swapper():
        swap.wait(30)
        first.stop(grace=0)
        second.append(ServerThread(ServerConfig(port=port, replica_name="after")))

    threading.Thread(target=swapper, daemon=True).start()
    caplog.set_level(logging.INFO, logger="dqpose.client")
    try:
        with Client(f"127.0.0.1:{port}", reconnect=10.0) as c:
            answers = list(c.stream_fuse(batches()))
    finally:
        first.stop()
        for s in second:
            s.stop()
    assert {a.request for a in answers} == set(range(60))
    resumed = [json.loads(r.getMessage()) for r in caplog.records
               if '"stream_resumed"' in r.getMessage()]
    assert [(e["from"], e["to"], e["moved"]) for e in resumed] == [("before", "after", True)]


def test_without_reconnect_a_broken_stream_raises():
    port = free_port()
    s = ServerThread(ServerConfig(port=port))

    def batches():
        for i in range(2000):
            if i == 5:      # from a thread of its own: grpc's thread reads this iterator
                threading.Thread(target=s.stop, kwargs={"grace": 0}, daemon=True).start()
            yield _batch(i)
            wait_until(lambda: False, timeout=0.002)

    with Client(f"127.0.0.1:{port}") as c, pytest.raises(RpcError):
        list(c.stream_fuse(batches()))
    s.stop()


def test_reconnect_is_checked():
    with pytest.raises(ValueError, match="^reconnect: must be a finite number of seconds"):
        Client("127.0.0.1:1", reconnect=-1)



class _Swap:
    """A server named "before" on a free port, replaced by one named "after" on the same port
    when :meth:`now` is called (from any thread)."""

    def __init__(self):
        self.port = free_port()
        self.target = f"127.0.0.1:{self.port}"
        self.first = ServerThread(ServerConfig(port=self.port, replica_name="before"))
        self.second: list[ServerThread] = []

    def now(self) -> None:
        self.first.stop(grace=0)
        self.second.append(ServerThread(ServerConfig(port=self.port, replica_name="after")))

    def hub(self, world: str):
        return self.second[0].running.servicers[0].hubs.get(world) if self.second else None

    def stop(self) -> None:
        self.first.stop()
        for s in self.second:
            s.stop()


def _resumed(caplog) -> list[tuple]:
    return [(e["from"], e["to"], e["moved"]) for e in
            (json.loads(r.getMessage()) for r in caplog.records
             if '"stream_resumed"' in r.getMessage())]


def test_publish_resumes_with_its_world_configured_again(caplog):
    from tests.rpc.test_world_service import SOURCES, measurements
    swap = _Swap()
    swapping = threading.Event()

    def batches():
        for i in range(60):
            if i == 20:
                swapping.set()
                assert wait_until(lambda: swap.second, timeout=30, poll=0.01)
            yield measurements("cam1", [0.01 * i], i)
            wait_until(lambda: False, timeout=0.002)

    threading.Thread(target=lambda: swapping.wait(30) and swap.now(), daemon=True).start()
    caplog.set_level(logging.INFO, logger="dqpose.client")
    try:
        with Client(swap.target, world="cell-1", reconnect=10.0) as c:
            c.configure_world(SOURCES, window=7.0)
            acks = list(c.publish(batches(), producer="cam1"))
            # the new replica has the world as configured, and every batch from the first one
            # its old replica never acknowledged
            cell = swap.hub("cell-1")
            assert cell is not None and cell.world.options.window == 7.0
            newest = c.lookup("", "box").time
    finally:
        swap.stop()
    assert acks == [(i, ()) for i in range(1, 61)]     # each batch acked once, in order
    assert newest == pytest.approx(0.59)
    assert _resumed(caplog) == [("before", "after", True)]


def test_subscribe_reopens_on_the_replica_its_world_moved_to(caplog):
    from tests.rpc.test_world_service import SOURCES, measurements
    swap = _Swap()
    answers: list = []
    failed: list = []
    caplog.set_level(logging.INFO, logger="dqpose.client")
    watcher = Client(swap.target, world="cell-2", reconnect=10.0)

    def watch():
        try:
            for a in watcher.subscribe(["box"]):
                answers.append(a)
        except RpcError as e:
            failed.append(e)

    try:
        watcher.configure_world(SOURCES, window=7.0)
        threading.Thread(target=watch, daemon=True).start()
        with Client(swap.target, world="cell-2", reconnect=10.0) as producer:
            assert wait_until(lambda: swap.first.running.servicers[0].hubs["cell-2"]
                              .subscriptions, timeout=10)
            list(producer.publish([measurements("cam1", [0.0, 0.01], 1)], producer="cam1"))
            assert wait_until(lambda: answers, timeout=10)
            swap.now()
            # the watcher is back by itself, its world configured again before it subscribed
            assert wait_until(lambda: swap.hub("cell-2") is not None
                              and swap.hub("cell-2").subscriptions, timeout=30, poll=0.01)
            assert swap.hub("cell-2").world.options.window == 7.0
            before = len(answers)
            list(producer.publish([measurements("cam1", [1.0, 1.01], 2)], producer="cam1",
                                  first_sequence=2))
            assert wait_until(lambda: len(answers) > before, timeout=10)
    finally:
        watcher.close()
        swap.stop()
    assert failed == [] or failed[0].code.name == "CANCELLED"   # the watcher closed at the end
    assert answers[-1].time >= 1.0 and answers[-1].error is None
    assert ("before", "after", True) in _resumed(caplog)


def test_a_configuration_the_new_server_refuses_ends_the_stream_with_its_error(monkeypatch):
    """Nothing is published into a world the new server could not configure: the producer
    hears why."""
    from dqpose.rpc import world as world_service
    from tests.rpc.test_world_service import SOURCES, measurements
    swap = _Swap()
    swapping = threading.Event()

    def batches():
        for i in range(40):
            if i == 10:
                monkeypatch.setattr(world_service, "MAX_WORLDS", 0)   # the new server is full
                swapping.set()
                assert wait_until(lambda: swap.second, timeout=30, poll=0.01)
            yield measurements("cam1", [0.01 * i], i)

    threading.Thread(target=lambda: swapping.wait(30) and swap.now(), daemon=True).start()
    acks = []
    try:
        with Client(swap.target, world="cell-3", reconnect=10.0) as c:
            c.configure_world(SOURCES)
            with pytest.raises(RpcError) as e:
                for a in c.publish(batches(), producer="cam1"):
                    acks.append(a)
    finally:
        swap.stop()
    assert e.value.code.name == "RESOURCE_EXHAUSTED" and "MAX_WORLDS" in e.value.details
    assert [a.acked_through for a in acks] == list(range(1, len(acks) + 1)) and len(acks) <= 10
    assert swap.hub("cell-3") is None
