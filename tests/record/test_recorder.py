"""dqpose.record.recorder: a call recorded, read back by mcap's own readers with every CRC
checked and its messages decoded with the schemas the file embeds; the Foxglove views; rotation;
a stalled writer that drops, counts and marks the file."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Message
from mcap.stream_reader import StreamReader

from dqpose import dq, lie
from dqpose.record import topics, views
from dqpose.record.reader import read
from dqpose.record.recorder import Recorder
from dqpose.record.schemas import message_class
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as pb
from tests._polling import wait_until
from tests.record import _stream

RPC = "dqpose.v1.Fusion/StreamFuse"


def record_stream(recorder, data, answers):
    call = recorder.call(RPC, pb.FuseStreamRequest, pb.FusedPose)
    for d, got in zip(data, answers):
        call.request(d)
        for a in got:
            call.answer(a)
    call.end("OK")
    return call


def messages(path):
    """(topic, schema name, encoding, schema data, message data, log_time) of every message,
    from mcap's indexed reader (the summary) after its stream reader checked every CRC."""
    with open(path, "rb") as f:
        assert sum(isinstance(r, Message) for r in StreamReader(f, validate_crcs=True).records)
    with open(path, "rb") as f:
        return [(c.topic, s.name, s.encoding, s.data, m.data, m.log_time)
                for s, c, m in make_reader(f).iter_messages(log_time_order=False)]


@pytest.fixture()
def scene():
    data = _stream.requests(30)
    return data, _stream.answers(data)


def test_a_call_reads_back_with_the_schemas_in_the_file(tmp_path, scene):
    data, answers = scene
    r = Recorder(tmp_path)
    record_stream(r, data, answers)
    r.close()
    assert r.dropped == 0 and len(r.files) == 1
    got = messages(r.files[0])
    by_topic: dict = {}
    for topic, name, enc, schema, msg, _ in got:
        by_topic.setdefault(topic, []).append((name, enc, schema, msg))
    reqs = by_topic[topics.requests_topic(RPC)]
    assert [m for *_, m in reqs] == data      # every request, byte for byte, in order
    name, enc, schema, _ = reqs[0]
    assert (name, enc) == ("dqpose.v1.FuseStreamRequest", "protobuf")
    Request = message_class(schema, name)
    first = Request.FromString(reqs[0][3])
    assert first.output_rate == _stream.RATE and len(first.measurements) == 4
    assert [s.name for s in first.options.sources] == ["cam", "arm"]
    ans = by_topic[topics.answers_topic(RPC)]
    flat = [a for got in answers for a in got]
    assert len(ans) == len(flat) > 0
    Fused = message_class(ans[0][2], "dqpose.v1.FusedPose")
    for (_, _, _, m), a in zip(ans, flat):
        assert m == a.SerializeToString()
        back = Fused.FromString(m)
        assert list(back.covariance) == list(a.covariance) and back.body == a.body
    # the call's beginning and end, in JSON
    calls = [json.loads(m) for *_, m in by_topic[topics.CALLS_TOPIC]]
    assert [c["event"] for c in calls] == ["begin", "end"]
    assert calls[0]["rpc"] == RPC and calls[1]["code"] == "OK"


def test_fused_poses_are_drawn_with_foxglove_schemas(tmp_path, scene):
    data, answers = scene
    r = Recorder(tmp_path)
    record_stream(r, data, answers)
    r.close()
    got = messages(r.files[0])
    flat = [a for a_s in answers for a in a_s if not a.HasField("error")]
    last = {a.body: a for a in flat}
    poses = [g for g in got if g[0] == topics.pose_topic("box")]
    assert len(poses) == sum(a.body == "box" for a in flat)
    PoseInFrame = message_class(poses[-1][3], "foxglove.PoseInFrame")
    p = PoseInFrame.FromString(poses[-1][4])
    want = last["box"].pose
    assert p.frame_id == "world"
    assert (p.pose.position.x, p.pose.orientation.w, p.pose.orientation.z) == \
        (want.position.x, want.orientation.w, want.orientation.z)
    # stamped with the pose's own time (this stream's: seconds after 0, so near 1970), logged
    # at its arrival
    def stamped(ts) -> float:
        return ts.seconds + ts.nanos * 1e-9

    assert stamped(p.timestamp) == pytest.approx(want_time := last["box"].time, abs=1e-9)
    assert 0 < want_time < 1 and poses[-1][5] > 1.7e18
    tf = [g for g in got if g[0] == topics.TF_TOPIC]
    FrameTransforms = message_class(tf[-1][3], "foxglove.FrameTransforms")
    t = FrameTransforms.FromString(tf[-1][4]).transforms[0]
    assert t.parent_frame_id == "world" and t.child_frame_id == flat[-1].body
    assert stamped(t.timestamp) == pytest.approx(flat[-1].time, abs=1e-9)
    scene_msgs = [g for g in got if g[0] == topics.ELLIPSOIDS_TOPIC]
    SceneUpdate = message_class(scene_msgs[-1][3], "foxglove.SceneUpdate")
    entity = SceneUpdate.FromString(scene_msgs[-1][4]).entities[0]
    assert entity.frame_id == entity.id == flat[-1].body
    assert stamped(entity.timestamp) == pytest.approx(flat[-1].time, abs=1e-9)
    assert len(tf) == len(flat)
    # the sphere's axes and diameters give back the position block of the covariance
    s = entity.spheres[0]
    o = s.pose.orientation
    R = dq.to_matrix(dq.from_pose([o.w, o.x, o.y, o.z], [0, 0, 0]))[:3, :3]
    d = np.array([s.size.x, s.size.y, s.size.z]) / (2 * views.ELLIPSOID_SIGMAS)
    cov = np.asarray(flat[-1].covariance).reshape(6, 6)[3:, 3:]
    assert np.allclose(R @ np.diag(d**2) @ R.T, cov, rtol=1e-9, atol=1e-18)
    stats = [json.loads(g[4]) for g in got if g[0] == topics.stats_topic("cup")]
    assert stats[-1]["time"] == last["cup"].time and stats[-1]["dof"] == last["cup"].dof
    c = np.asarray(last["cup"].covariance).reshape(6, 6)
    assert stats[-1]["sigma_position"] == pytest.approx(np.sqrt(np.linalg.eigvalsh(c[3:, 3:])[-1]))


def test_ellipsoid_axes_of_a_rotated_covariance():
    R = dq.to_matrix(lie.se3_exp([0.3, -1.1, 0.4, 0, 0, 0]))[:3, :3]
    cov = R @ np.diag([4e-6, 1e-6, 9e-6]) @ R.T
    s, q = views.ellipsoid_axes(cov)
    V = dq.to_matrix(dq.from_pose(q, [0, 0, 0]))[:3, :3]
    assert np.allclose(V @ np.diag(s**2) @ V.T, cov, atol=1e-18)
    assert np.allclose(sorted(s), [1e-3, 2e-3, 3e-3])


def test_files_rotate_by_size_and_each_reads_back(tmp_path, scene):
    data, answers = scene
    r = Recorder(tmp_path, max_bytes=4000)
    call = record_stream(r, data, answers)
    r.close()
    assert call.alive and r.dropped == 0
    assert len(r.files) > 2 and sorted(os.listdir(tmp_path)) == sorted(
        os.path.basename(f) for f in r.files)
    recordings = [read(f) for f in r.files]
    # every request is in exactly one file, in order; later files say the call began earlier
    assert [e.data for rec in recordings for e in rec.events if e.kind == "request"] == data
    assert not recordings[0].calls[1].continued
    assert all(rec.calls[1].continued for rec in recordings[1:] if rec.events)
    assert recordings[-1].calls[1].code == "OK"


def complete(path) -> bool:
    try:
        return bool(read(path).events)
    except ValueError:          # still being written
        return False


def test_files_rotate_by_age(tmp_path, scene):
    data, answers = scene
    r = Recorder(tmp_path, max_seconds=0.05)
    call = r.call(RPC, pb.FuseStreamRequest, pb.FusedPose)
    call.request(data[0])
    wait_until(lambda: len(r.files) == 1 and r.written == 2, 10)
    wait_until(lambda: complete(r.files[0]), 10)    # closed once 0.05 s old
    call.request(data[1])
    r.close()
    assert len(r.files) == 2
    assert [e.data for e in read(r.files[1]).events] == [data[1]]


def test_a_stalled_writer_drops_counts_and_marks_the_file(tmp_path, scene):
    data, answers = scene
    r = Recorder(tmp_path, queue=10)
    r.stall.set()
    call = r.call(RPC, pb.FuseStreamRequest, pb.FusedPose)
    for d in data:                 # 1 begin + 30 requests into a queue of 10: 21 dropped
        call.request(d)
    assert r.dropped == 21
    r.stall.clear()
    wait_until(lambda: r.written == 10, 10)
    call.request(b"after")    # room again: the marker goes before it
    r.close()
    rec = read(r.files[0])
    assert [e.data for e in rec.events] == data[:9] + [b"after"]
    assert len(rec.dropped) == 1
    gap = rec.dropped[0]
    assert gap.count == 21 and gap.at == 9
    assert gap.first_dropped <= rec.events[-1].ns


def test_a_call_whose_beginning_was_dropped_records_nothing(tmp_path, scene):
    data, _ = scene
    r = Recorder(tmp_path, queue=1)
    r.stall.set()
    r.call(RPC, pb.FuseStreamRequest, pb.FusedPose)         # fills the queue
    late = r.call(RPC, pb.FuseStreamRequest, pb.FusedPose)  # dropped
    assert not late.alive
    r.stall.clear()
    wait_until(lambda: r.written == 1, 10)
    late.request(data[0])      # its requests cannot be replayed: dropped too
    r.close()
    assert r.dropped == 2
    rec = read(r.files[0])
    assert list(rec.calls) == [1] and rec.events == []


def test_bad_settings_name_the_argument(tmp_path):
    for kw, name in (({"max_bytes": 0}, "max_bytes"), ({"max_seconds": -1.0}, "max_seconds"),
                     ({"queue": 0}, "queue")):
        with pytest.raises(ValueError, match=f"^{name}:"):
            Recorder(tmp_path, **kw)


def test_a_truncated_file_is_refused_naming_it(tmp_path, scene):
    data, answers = scene
    r = Recorder(tmp_path)
    record_stream(r, data, answers)
    r.close()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(open(r.files[0], "rb").read()[:-100])
    with pytest.raises(ValueError, match="cut.mcap: not a complete MCAP recording"):
        read(cut)


def test_a_plan_is_a_path_of_poses(tmp_path):
    path = lie.se3_exp(np.array([[0, 0, 0.1 * k, 0.05 * k, 0, 0.3] for k in range(5)]))
    r = Recorder(tmp_path)
    r.plan("ur", path)
    r.close()
    (topic, name, _, schema, data, _), = messages(r.files[0])
    assert (topic, name) == (topics.plan_topic("ur"), "foxglove.PosesInFrame")
    msg = message_class(schema, name).FromString(data)
    q, t = dq.to_pose(path)
    assert msg.frame_id == "world" and len(msg.poses) == 5
    assert [p.position.x for p in msg.poses] == t[:, 0].tolist()
    assert [p.orientation.z for p in msg.poses] == q[:, 3].tolist()


def test_a_writer_that_dies_is_logged_once_and_what_follows_failed(tmp_path, scene, caplog):
    data, _ = scene
    r = Recorder(tmp_path)
    heard = []
    r.watch(lambda: heard.append(r.failure))
    call = r.call(RPC, pb.FuseStreamRequest, pb.FusedPose)
    r._proc.kill()
    r._proc.wait()
    for d in data:      # none waits: the pipe's end is gone
        call.request(d)
    wait_until(lambda: (call.request(data[0]) or True) and r._closed, 10)
    before = r.failed
    call.request(data[1])
    assert r.failed == before + 1 and r.dropped == 0
    r.close()
    assert heard == ["the writer process ended"] == [r.failure]
    assert sum('"event": "recording_failed"' in rec.getMessage() for rec in caplog.records) == 1


def test_the_writer_runs_niced_below_the_server(tmp_path):
    from dqpose.record.writer import WRITER_NICE

    r = Recorder(tmp_path)
    try:
        pid = r._proc.pid
        mine = os.getpriority(os.PRIO_PROCESS, 0)
        # it nices itself once started: until then it has the server's priority
        wait_until(lambda: os.getpriority(os.PRIO_PROCESS, pid) != mine, timeout=30)
        assert os.getpriority(os.PRIO_PROCESS, pid) == min(19, mine + WRITER_NICE)
    finally:
        r.close()
