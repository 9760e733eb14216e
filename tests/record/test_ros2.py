"""dqpose.record.ros2 (and `dqpose export --ros2`): the bag reads back with rosbags' own reader
and types, the covariance converted to ROS's convention and back to the recorded one."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from dqpose import dq, lie
from dqpose.record.reader import read
from dqpose.record.recorder import Recorder
from dqpose.record.ros2 import export
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as pb
from tests.cli._cli import ROOT
from tests.record import _stream
from tests.record.test_recorder import record_stream


def recording(tmp_path):
    data = _stream.requests(30)
    answers = _stream.answers(data)
    r = Recorder(tmp_path / "rec")
    record_stream(r, data, answers)
    r.plan("ur", lie.se3_exp(np.array([[0, 0, 0.1 * k, 0.05 * k, 0, 0.3] for k in range(4)])))
    r.close()
    fused = [a for got in answers for a in got if not a.HasField("error")]
    return r.files[0], fused


def bag(path):
    ts = get_typestore(Stores.ROS2_HUMBLE)
    out: dict = {}
    with Reader(path) as reader:
        for c, t, raw in reader.messages():
            out.setdefault(c.topic, []).append((c.msgtype, t, ts.deserialize_cdr(raw, c.msgtype)))
    return out


def test_the_bag_reads_back_with_its_types_and_the_covariance_round_trips(tmp_path):
    path, fused = recording(tmp_path)
    counts = export(read(path), tmp_path / "bag")
    got = bag(tmp_path / "bag")
    assert {t: len(m) for t, m in got.items()} == counts
    box = [f for f in fused if f.body == "box"]
    poses = got["/fused/box/pose"]
    assert len(poses) == len(box) > 3
    for (msgtype, arrival, m), f in zip(poses, box):
        assert msgtype == "geometry_msgs/msg/PoseWithCovarianceStamped"
        assert m.header.frame_id == "world"
        # stamped with the pose's own time (this stream's, near 1970), in the bag at arrival
        assert m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 == \
            pytest.approx(f.time, abs=1e-9)
        assert arrival > 1.7e18
        p, o = m.pose.pose.position, m.pose.pose.orientation
        assert (p.x, p.y, p.z, o.w, o.x, o.y, o.z) == (
            f.pose.position.x, f.pose.position.y, f.pose.position.z, f.pose.orientation.w,
            f.pose.orientation.x, f.pose.orientation.y, f.pose.orientation.z)
        T = dq.from_pose([o.w, o.x, o.y, o.z], [p.x, p.y, p.z])
        ros = np.asarray(m.pose.covariance).reshape(6, 6)
        ours = np.asarray(f.covariance).reshape(6, 6)
        assert np.allclose(lie.cov_from_ros(T, ros), ours, rtol=1e-12, atol=1e-20)
        # translation first: ROS's position block is ours rotated into the world frame
        R = dq.to_matrix(T)[:3, :3]
        assert np.allclose(ros[:3, :3], R @ ours[3:, 3:] @ R.T, rtol=1e-12, atol=1e-20)
    tf = got["/tf"]
    assert tf[0][0] == "tf2_msgs/msg/TFMessage" and len(tf) == len(fused)
    t = tf[-1][2].transforms[0]
    assert (t.header.frame_id, t.child_frame_id) == ("world", fused[-1].body)
    assert t.header.stamp.sec + t.header.stamp.nanosec * 1e-9 == \
        pytest.approx(fused[-1].time, abs=1e-9)
    (path_msg,) = got["/fused/cup/path"]
    assert path_msg[0] == "nav_msgs/msg/Path"
    assert [q.pose.position.x for q in path_msg[2].poses] == \
        [f.pose.position.x for f in fused if f.body == "cup"]
    assert [q.header.stamp.nanosec for q in path_msg[2].poses] == \
        [round(f.time * 1e9) for f in fused if f.body == "cup"]
    (plan,) = got["/plans/ur"]
    assert plan[0] == "nav_msgs/msg/Path" and len(plan[2].poses) == 4


def test_export_command_writes_the_bag_and_refuses_an_existing_folder(tmp_path):
    path, fused = recording(tmp_path)
    out = tmp_path / "bag"
    cmd = [sys.executable, "-m", "dqpose.cli", "export", path, "--ros2", str(out)]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert res.returncode == 0, res.stderr
    assert res.stdout.splitlines()[-1] == f"wrote {len(fused) * 2 + 3} messages to {out}"
    assert len(bag(out)["/tf"]) == len(fused)
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert (again.returncode, again.stderr) == (
        2, f"dqpose export: error: --ros2 {out}: exists already (rosbag2 writes a new folder)\n")


def test_error_entries_are_left_out(tmp_path):
    r = Recorder(tmp_path / "rec")
    call = r.call("dqpose.v1.Fusion/StreamFuse", pb.FuseStreamRequest, pb.FusedPose)
    call.answer(pb.FusedPose(body="box", error=pb.FuseError(details="x")))
    r.close()
    assert export(read(r.files[0]), tmp_path / "bag") == {}


def test_a_pose_time_beyond_a_ros_stamp_is_named(tmp_path):
    data = _stream.requests(30)
    answers = [a for got in _stream.answers(data) for a in got if not a.HasField("error")]
    late = pb.FusedPose()
    late.CopyFrom(answers[0])
    late.time = 3e9                     # after 2038: beyond int32 seconds
    r = Recorder(tmp_path / "rec")
    record_stream(r, data[:1], [[late]])
    r.close()
    with pytest.raises(ValueError, match=r"^the fused pose of 'box' at \d+ ns: a time of 3e\+09 "
                                         r"s is beyond a ROS 2 stamp \(int32 seconds\)$"):
        export(read(r.files[0]), tmp_path / "bag")


def test_a_worlds_fixed_frames_are_latched_on_tf_static(tmp_path):
    """A Configure's answer: its statics and sources on ``/tf_static`` (tf2_msgs/TFMessage),
    stamped 0, the connection offered reliable and transient local with a depth of 1 (what
    ``ros2 bag play`` latches, as tf2's static broadcaster offers it)."""
    from rosbags.interfaces import QosDurability, QosReliability

    from tests.record.test_tf_static import CAM, TABLE, config, configure

    r = Recorder(tmp_path / "rec")
    configure(r, config())
    r.close()
    export(read(r.files[0]), tmp_path / "bag")
    ((msgtype, _, m),) = bag(tmp_path / "bag")["/tf_static"]
    assert msgtype == "tf2_msgs/msg/TFMessage"
    got = {(t.header.frame_id, t.child_frame_id): t for t in m.transforms}
    assert set(got) == {("world", "table"), ("tool", "tcp"), ("tool", "wrist"),
                        ("world", "ceiling"), ("world", "arm")}
    for edge, T in ((("world", "table"), TABLE), (("tool", "wrist"), CAM)):
        x = got[edge].transform
        assert (got[edge].header.stamp.sec, got[edge].header.stamp.nanosec) == (0, 0)
        back = dq.from_pose([x.rotation.w, x.rotation.x, x.rotation.y, x.rotation.z],
                            [x.translation.x, x.translation.y, x.translation.z])
        assert np.allclose(dq.to_matrix(back), dq.to_matrix(T), atol=1e-12)
    with Reader(tmp_path / "bag") as reader:
        (c,) = [c for c in reader.connections if c.topic == "/tf_static"]
        (qos,) = c.ext.offered_qos_profiles
    assert (qos.durability, qos.reliability, qos.depth) == (
        QosDurability.TRANSIENT_LOCAL, QosReliability.RELIABLE, 1)
