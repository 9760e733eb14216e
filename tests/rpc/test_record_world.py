"""A recorded world through a real server (issue 37, item 7): every body is recorded though no
client subscribes, by the recorder's own subscriber at its rate of measurement time, and a fused
pose's views and ROS 2 messages are stamped with the pose's own time while the MCAP log time
(and the bag's) stays its arrival; read back by mcap's and rosbags' own readers."""
from __future__ import annotations

import json
import time

import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from dqpose import dq
from dqpose.frames import Static
from dqpose.record.reader import read
from dqpose.record.recorder import Recorder
from dqpose.record.ros2 import export
from dqpose.record.schemas import message_class
from dqpose.rpc.client import Client
from dqpose.rpc.server import ServerConfig
from tests.rpc._grpc_server import ServerThread
from tests.rpc.test_world_service import EXTRINSICS, SOURCES, TWIST, joined, measurements

#: the world's measurements are stamped in Unix seconds (2017: far from the arrival, now)
T0 = 1.5e9
RATE = 10.0
STEP, STEPS = 0.02, 120          # 2.4 s of measurement time
#: a static of the world: a table fixed in camera 1's frame
TABLE = dq.from_pose([np.cos(0.4), 0.0, np.sin(0.4), 0.0], [0.2, -0.1, 1.3])


def stamped(ts) -> float:
    return ts.seconds + ts.nanos * 1e-9


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    folder = tmp_path_factory.mktemp("world")
    recorder = Recorder(folder / "runs", world_rate=RATE)
    started = time.time_ns()
    with ServerThread(ServerConfig(port=0, recorder=recorder)) as s, Client(s.target) as c:
        c.configure_world(SOURCES, twist_covariance=TWIST, window=10.0,
                          statics=[Static("cam1", "table", TABLE)])
        batches = [joined(measurements("cam1", [T0 + STEP * k], k, body="box"),
                          measurements("cam1", [T0 + STEP * k], 1000 + k, body="cup"))
                   for k in range(STEPS)]
        assert len(list(c.publish(batches, producer="cam1"))) == STEPS   # no one subscribes
    (path,) = recorder.files
    with open(path, "rb") as f:
        got = [(ch.topic, sc, m) for sc, ch, m in make_reader(f).iter_messages(
            log_time_order=False)]
    return folder, path, got, started


def test_every_body_is_recorded_by_the_recorders_own_subscriber(recorded):
    _, _, got, _ = recorded
    calls = [json.loads(m.data) for t, _, m in got if t == "/dqpose/calls"]
    (begin,) = [c for c in calls if c.get("internal")]
    assert (begin["rpc"], begin["event"]) == ("dqpose.v1.World/Subscribe", "begin")
    assert {"call": begin["call"], "event": "end", "code": "OK", "details": ""} in calls
    for body in ("box", "cup"):
        poses = [(sc, m) for t, sc, m in got if t == f"/fused/{body}"]
        # ticks at RATE Hz of measurement time (each body's own phase) over the stream's span
        assert abs(len(poses) - STEP * (STEPS - 1) * RATE) <= 2, len(poses)
        PoseInFrame = message_class(poses[0][0].data, "foxglove.PoseInFrame")
        times = np.array([stamped(PoseInFrame.FromString(m.data).timestamp) for _, m in poses])
        assert np.allclose(np.diff(times), 1 / RATE, atol=1e-6)
        assert T0 <= times[0] and times[-1] <= T0 + STEP * (STEPS - 1)


def test_views_carry_the_poses_time_and_are_logged_at_arrival(recorded):
    _, _, got, started = recorded
    answers = [(sc, m) for t, sc, m in got if t == "/dqpose/dqpose.v1.World/Subscribe/answers"]
    Fused = message_class(answers[0][0].data, "dqpose.v1.FusedPose")
    fused = [Fused.FromString(m.data) for _, m in answers]
    cup = [f.time for f in fused if f.body == "cup" and f.HasField("pose")]
    tf = [(sc, m) for t, sc, m in got if t == "/tf"]
    FrameTransforms = message_class(tf[0][0].data, "foxglove.FrameTransforms")
    cup_tf = [(stamped(x.timestamp), m.log_time) for _, m in tf
              for x in FrameTransforms.FromString(m.data).transforms if x.child_frame_id == "cup"]
    assert [t for t, _ in cup_tf] == pytest.approx(cup, abs=1e-6)
    assert all(started <= ns <= time.time_ns() for _, ns in cup_tf)
    ellipsoids = [(sc, m) for t, sc, m in got if t == "/fused/ellipsoids"]
    SceneUpdate = message_class(ellipsoids[0][0].data, "foxglove.SceneUpdate")
    cup_e = [stamped(e.timestamp) for _, m in ellipsoids
             for e in SceneUpdate.FromString(m.data).entities if e.id == "cup"]
    assert cup_e == pytest.approx(cup, abs=1e-6)


def test_the_worlds_sources_and_statics_are_on_tf_static_as_configured(recorded):
    """Configure's answer through the server: each source in the world at its extrinsic, the
    static in its parent, one message, stamped 0 (valid at every time), logged at its
    arrival."""
    _, _, got, started = recorded
    (tf,) = [(sc, m) for t, sc, m in got if t == "/tf_static"]
    msg = message_class(tf[0].data, "foxglove.FrameTransforms").FromString(tf[1].data)
    assert started <= tf[1].log_time <= time.time_ns()
    edges = {(x.parent_frame_id, x.child_frame_id): x for x in msg.transforms}
    want = {("world", name): T for name, T in EXTRINSICS.items()} | {("cam1", "table"): TABLE}
    assert set(edges) == set(want)
    for edge, T in want.items():
        x = edges[edge]
        assert stamped(x.timestamp) == 0
        got_T = dq.from_pose([x.rotation.w, x.rotation.x, x.rotation.y, x.rotation.z],
                             [x.translation.x, x.translation.y, x.translation.z])
        np.testing.assert_allclose(dq.to_matrix(got_T), dq.to_matrix(T), atol=1e-12)


def test_the_ros2_bag_stamps_the_poses_time(recorded):
    folder, path, got, started = recorded
    export(read(path), folder / "bag")
    ts = get_typestore(Stores.ROS2_HUMBLE)
    with Reader(folder / "bag") as reader:
        msgs = [(c.topic, t, ts.deserialize_cdr(raw, c.msgtype))
                for c, t, raw in reader.messages()]
    poses = [(t, m) for topic, t, m in msgs if topic == "/fused/cup/pose"]
    PoseInFrame = next(message_class(sc.data, "foxglove.PoseInFrame") for t, sc, _ in got
                       if t == "/fused/cup")
    views = [stamped(PoseInFrame.FromString(m.data).timestamp) for t, _, m in got
             if t == "/fused/cup"]
    assert [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for _, m in poses] == \
        pytest.approx(views, abs=1e-6)
    assert all(started <= t <= time.time_ns() for t, _ in poses)


@pytest.mark.parametrize("rate, problem", [
    ("0", "--record-rate: must be > 0, got 0"),
    ("2000", "--record-rate: 2000 Hz, over the server's limit max_output_rate = 1000 Hz "
             "(dqpose serve --max-output-rate)")])
def test_a_record_rate_out_of_range_is_one_line(tmp_path, rate, problem):
    import subprocess
    import sys

    from tests.cli._cli import ROOT

    res = subprocess.run([sys.executable, "-m", "dqpose.cli", "serve", "--port", "0",
                          "--record", str(tmp_path), "--record-rate", rate],
                         capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert (res.returncode, res.stderr) == (2, f"dqpose serve: error: {problem}\n")
