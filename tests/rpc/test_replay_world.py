"""dqpose.rpc.replay_world and replay_remote (with the hubs' recording hooks): a World run recorded
by a real server, two producers publishing at once from threads of their own while two
subscribers come and go, replays in this process and into a real server to every ack and every
subscriber's answer byte for byte; one changed measurement in the file is found in a
subscriber's answers, both ways; two named worlds replay each into its own, both ways."""
from __future__ import annotations

import dataclasses
import threading

import grpc
import numpy as np
import pytest

from dqpose.record.reader import read
from dqpose.record.recorder import Recorder
from dqpose.rpc import replay, replay_world
from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb
from dqpose.rpc.client import Client
from dqpose.rpc.server import ServerConfig
from tests._polling import wait_until
from tests.rpc._grpc_server import ServerThread
from tests.rpc.test_world_service import SOURCES, TWIST, Collector, measurements

pytest.importorskip("foxglove", reason="the [record] extra")

REQUESTS, PER = 30, 3


def _world(server):
    """The server's default world (its cell of the World servicer)."""
    (w,) = [s for s in server.running.servicers if s.NAME == replay_world.NAME]
    return w.hub("", make=True)


def _produce(target: str, source: str, seed: int, gate: threading.Barrier) -> None:
    batches = [measurements(source, 0.01 * (k * PER + np.arange(PER)) + seed * 1e-3,
                            seed * 1000 + k, body="box" if k % 2 else "cup")
               for k in range(REQUESTS)]
    with Client(target) as c:
        gate.wait(10)
        assert len(list(c.publish(batches, producer=source))) == REQUESTS


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    recorder = Recorder(tmp_path_factory.mktemp("world"))
    with ServerThread(ServerConfig(port=0, recorder=recorder)) as s, Client(s.target) as c:
        c.configure_world(SOURCES, twist_covariance=TWIST, window=10.0)
        early = Collector(s.target)
        # early's and the recorder's own (every body of a recorded world is recorded)
        assert wait_until(lambda: len(_world(s).subscriptions) == 2, timeout=10)
        gate = threading.Barrier(3)
        producers = [threading.Thread(target=_produce, args=(s.target, src, k + 1, gate))
                     for k, src in enumerate(("cam1", "cam2"))]
        for p in producers:
            p.start()
        gate.wait(10)
        late = Collector(s.target, bodies=["box"], rate_hz=20.0, relative_to="cup")
        for p in producers:
            p.join(60)
        assert wait_until(lambda: early.answers and late.answers, timeout=10)
        early.stop()
        late.stop()
        assert wait_until(lambda: len(_world(s).subscriptions) == 1, timeout=10)
    recorder.close()
    assert recorder.dropped == 0
    return read(recorder.files[0]), len(early.answers), len(late.answers)


def test_a_world_run_replays_to_every_ack_and_answer(recording):
    rec, early, late = recording
    report = replay.replay(rec, replay.InProcess())
    assert report.difference is None, str(report.difference)
    rpcs = sorted(c.rpc for c in rec.calls.values())
    assert rpcs == sorted([replay_world.CONFIGURE, replay_world.PUBLISH, replay_world.PUBLISH,
                           replay_world.SUBSCRIBE, replay_world.SUBSCRIBE,
                           replay_world.SUBSCRIBE])       # the recorder's own
    assert report.calls == 6 and report.requests == 1 + 2 * REQUESTS + 3
    assert report.skipped == []
    # every ack, and at least every answer the subscribers got
    assert report.answers >= 1 + 2 * REQUESTS + early + late > 1 + 2 * REQUESTS


def _changed(rec):
    """``rec`` with its first Publish request's first measurement moved by 1 mm."""
    k = next(i for i, e in enumerate(rec.events) if e.kind == "request"
             and rec.calls[e.call].rpc == replay_world.PUBLISH)
    request = wpb.PublishRequest.FromString(rec.events[k].data)
    request.measurements[0].pose.position.x += 1e-3
    events = list(rec.events)
    events[k] = dataclasses.replace(events[k], data=request.SerializeToString())
    return dataclasses.replace(rec, events=events)


def test_a_changed_measurement_is_found_in_a_subscribers_answers(recording):
    rec, _, _ = recording
    report = replay.replay(_changed(rec), replay.InProcess())
    assert report.difference is not None
    assert rec.calls[report.difference.call.id].rpc == replay_world.SUBSCRIBE
    assert "pose.position.x recorded" in report.difference.what, report.difference.what


def _into_a_server(rec):
    with ServerThread() as s, grpc.insecure_channel(s.target) as ch:
        return replay.replay(rec, replay.Remote(ch))


def test_the_world_replays_into_a_server(recording):
    rec, early, late = recording
    report = _into_a_server(rec)
    assert report.difference is None, str(report.difference)
    assert report.calls == 6 and report.skipped == []
    assert report.requests == 1 + 2 * REQUESTS + 3
    assert report.answers >= 1 + 2 * REQUESTS + early + late


def test_a_changed_measurement_is_found_through_a_server(recording):
    rec, _, _ = recording
    report = _into_a_server(_changed(rec))
    assert report.difference is not None
    assert rec.calls[report.difference.call.id].rpc == replay_world.SUBSCRIBE
    assert "pose.position.x recorded" in report.difference.what, report.difference.what


def test_two_named_worlds_replay_each_into_its_own(tmp_path):
    # The same body names in two worlds with different data: replayed into one world, each
    # world's answers would mix the other's measurements.
    recorder = Recorder(tmp_path)
    with ServerThread(ServerConfig(port=0, recorder=recorder)) as s:
        subs = []
        for name in ("cell-a", "cell-b"):
            with Client(s.target, world=name) as c:
                c.configure_world(SOURCES, twist_covariance=TWIST, window=10.0)
            subs.append(Collector(s.target, world=name))
        (w,) = [x for x in s.running.servicers if x.NAME == replay_world.NAME]
        assert wait_until(lambda: all(len(w.hub(n).subscriptions) == 2    # and the recorder's
                                      for n in ("cell-a", "cell-b")), timeout=10)
        for k, name in enumerate(("cell-a", "cell-b")):
            batches = [measurements("cam1", 0.01 * (j * PER + np.arange(PER)), 100 * k + j,
                                    body="box") for j in range(10)]
            with Client(s.target, world=name) as c:
                assert len(list(c.publish(batches, producer="cam1"))) == 10
        assert wait_until(lambda: all(len(x.answers) > 0 for x in subs), timeout=10)
        for x in subs:
            x.stop()
        assert wait_until(lambda: all(len(w.hub(n).subscriptions) == 1
                                      for n in ("cell-a", "cell-b")), timeout=10)
    recorder.close()
    rec = read(recorder.files[0])
    assert sorted(c.world for c in rec.calls.values()) == ["cell-a"] * 4 + ["cell-b"] * 4
    for report in (replay.replay(rec, replay.InProcess()), _into_a_server(rec)):
        assert report.difference is None, str(report.difference)
        assert report.calls == 8
        assert report.answers >= 2 * (1 + 10) + sum(len(x.answers) for x in subs)
