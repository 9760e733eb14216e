"""``Client.stream_fuse`` on ``rpc.resume.Resuming``: a producer in lockstep with the answers
is served, and a stream whose server went away is reopened on the server that comes back at the
address, every batch answered once the stream resumed (the unanswered ones sent again)."""
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

