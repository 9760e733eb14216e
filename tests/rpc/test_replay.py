"""dqpose.rpc.replay: a recorded StreamFuse run (and a Fuse, and a refused stream) replays to
every answer byte for byte, in this process and against a server; a server with another option,
or a recording made with another one, is reported at the first difference; a recording that
fell behind replays up to where it is missing messages."""
from __future__ import annotations

import grpc
import numpy as np
import pytest

from dqpose import dq
from dqpose.record.reader import read
from dqpose.record.recorder import Recorder
from dqpose.rpc import replay
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as pb
from dqpose.rpc.client import Client
from dqpose.rpc.server import ServerConfig
from tests._polling import wait_until
from tests.record import _stream
from tests.rpc._grpc_server import ServerThread
from tests.rpc.test_record import stream_bytes


def record_run(directory, data, **recorder):
    """A recording of StreamFuse with ``data``, a Fuse and a refused stream, through a server."""
    r = Recorder(directory, **recorder)
    with ServerThread(ServerConfig(port=0, recorder=r)) as s:
        stream_bytes(s.target, data)
        poses = dq.normalize(np.array([[1, 0, 0, 0, 0, 0.1, 0, 0], [1, 0.02, 0, 0, 0, 0.1, 0, 0]]))
        Client(s.target).fuse(poses, weights=[1.0, 3.0])
        with grpc.insecure_channel(s.target) as ch, pytest.raises(grpc.RpcError):
            ch.unary_unary("/dqpose.v1.Fusion/Fuse")(pb.FuseRequest(measurements=[
                pb.Measurement(weight=-1.0)]).SerializeToString(), timeout=10)
        with pytest.raises(grpc.RpcError):
            stream_bytes(s.target, [pb.FuseStreamRequest(output_rate=-1).SerializeToString()])
    return read(r.files[0])


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    return record_run(tmp_path_factory.mktemp("rec"), _stream.requests(40))


def test_replay_in_process_reproduces_every_answer(recording):
    report = replay.replay(recording, replay.InProcess())
    assert report.difference is None and report.cut is None and report.skipped == []
    assert report.calls == 4 and report.requests == 40 + 1 + 1 + 1
    refused = [c for c in recording.calls.values() if c.code == "INVALID_ARGUMENT"]
    assert [c.rpc for c in refused] == ["dqpose.v1.Fusion/Fuse", "dqpose.v1.Fusion/StreamFuse"]
    assert refused[0].details.startswith("measurements[0]")
    assert report.answers == sum(e.kind == "answer" for e in recording.events) > 16


def test_replay_against_a_server_reproduces_every_answer(recording):
    with ServerThread() as s, grpc.insecure_channel(s.target) as ch:
        report = replay.replay(recording, replay.Remote(ch))
    assert report.difference is None and report.calls == 4
    assert report.answers == sum(e.kind == "answer" for e in recording.events)


def test_a_server_with_another_option_is_reported_at_the_first_difference(recording):
    # 3 measurements a request at most: each request of 4 becomes an error entry
    with ServerThread(ServerConfig(port=0, max_poses=3)) as s, \
            grpc.insecure_channel(s.target) as ch:
        report = replay.replay(recording, replay.Remote(ch))
    d = report.difference
    assert d is not None and d.call.rpc == "dqpose.v1.Fusion/StreamFuse" and d.answer == 0
    assert report.calls == 1
    assert str(d).startswith("call 1 (dqpose.v1.Fusion/StreamFuse), answer 0: body 'box' at ")
    assert "recorded" in str(d) and "given" in str(d)


def test_a_tampered_answer_is_named_by_its_field():
    data = _stream.requests(10)
    want = [a.SerializeToString() for got in _stream.answers(data) for a in got]
    changed = pb.FusedPose.FromString(want[2])
    changed.covariance[7] = np.nextafter(changed.covariance[7], 1.0)   # one ulp
    got = want[:2] + [changed.SerializeToString()] + want[3:]
    call = read_call()
    d = replay.compare_outcomes(call, replay.Outcome(want), replay.Outcome(got))
    assert d is not None and d.answer == 2
    assert f"covariance[7] recorded {pb.FusedPose.FromString(want[2]).covariance[7]!r}, " \
           f"given {changed.covariance[7]!r}" in d.what
    assert replay.compare_outcomes(call, replay.Outcome(want), replay.Outcome(want[:-1])) \
        .what == f"{len(want)} answers recorded, {len(want) - 1} given"


def read_call():
    from dqpose.record.reader import Call
    return Call(1, "dqpose.v1.Fusion/StreamFuse", "dqpose.v1.FuseStreamRequest",
                "dqpose.v1.FusedPose", False, "OK")


def test_two_recordings_with_another_window_differ_at_the_first_answer_it_changes(tmp_path):
    data = _stream.requests(40)
    a = record_run(tmp_path / "a", data)
    narrow = _stream.requests(40, window=0.05)
    b = record_run(tmp_path / "b", narrow)
    same = record_run(tmp_path / "c", data)
    assert replay.compare(a, same).difference is None
    d = replay.compare(a, b).difference
    assert d is not None and "not the same requests" in d.what   # the options differ
    # the same requests, answered with another window: the servicer's default differs
    b.events = [e if e.kind != "request" or e.data != narrow[0] else
                type(e)(e.kind, e.call, e.ns, data[0]) for e in b.events]
    d = replay.compare(a, b).difference
    assert d is not None and d.answer > 0     # the first answers are fused over one window
    assert "pose.position.x recorded " in d.what or "covariance[" in d.what, d.what


def test_a_recording_that_fell_behind_replays_up_to_the_gap(tmp_path):
    data = _stream.requests(40)
    r = Recorder(tmp_path, queue=20)
    r.stall.set()
    with ServerThread(ServerConfig(port=0, recorder=r)) as s:
        stream_bytes(s.target, data)
        r.stall.clear()
        wait_until(lambda: r.written >= 20, 10)
        stream_bytes(s.target, data[:5])
    rec = read(r.files[0])
    report = replay.replay(rec, replay.InProcess())
    assert report.difference is None
    assert report.cut.startswith("not replayable after ")
    assert "messages dropped by the recorder there" in report.cut
    assert report.calls == 1 and report.requests < 20     # only the first call, cut short
