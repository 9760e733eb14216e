"""A World's frames fixed in their parents on ``/tf_static`` (issue 39): a Configure's answer,
the configuration in force, becomes one ``foxglove.FrameTransforms`` of its statics and sources,
stamped 0, repeated at the start of each later file (latched, as tf2's ``/tf_static``); read back
by mcap's own reader with the schema the file embeds."""
from __future__ import annotations

import numpy as np
from mcap.reader import make_reader

from dqpose import dq
from dqpose.record.recorder import Recorder
from dqpose.record.schemas import message_class
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb
from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb
from dqpose.rpc.geometry import dq_to_pose
from tests.record import _stream
from tests.record.test_recorder import record_stream

RPC = "dqpose.v1.World/Configure"
TABLE = dq.from_pose([np.cos(0.3), 0, 0, np.sin(0.3)], [0.8, -0.2, 0.0])
TCP = dq.from_pose([1, 0, 0, 0], [0, 0, 0.12])
CAM = dq.from_pose([np.cos(0.2), np.sin(0.2), 0, 0], [0.05, 0, 0.03])
ROOM = dq.from_pose([0, 1, 0, 0], [0.5, 0, 2.0])


def config() -> wpb.WorldConfig:
    """A table in the world, a tool-centre offset on body "tool", a camera riding on it, a
    camera on the ceiling and one source with no extrinsic (the identity)."""
    return wpb.WorldConfig(
        statics=[wpb.StaticTransform(parent="", child="table", pose=dq_to_pose(TABLE)),
                 wpb.StaticTransform(parent="tool", child="tcp", pose=dq_to_pose(TCP),
                                     covariance=list(np.eye(6).ravel() * 1e-6))],
        sources=[fpb.Source(name="wrist", parent="tool", extrinsic=dq_to_pose(CAM)),
                 fpb.Source(name="ceiling", extrinsic=dq_to_pose(ROOM)),
                 fpb.Source(name="arm")])


def configure(recorder: Recorder, answer: wpb.WorldConfig, world: str = "cell") -> None:
    call = recorder.call(RPC, wpb.WorldConfig, wpb.WorldConfig, world)
    call.request(answer)
    call.answer(answer)
    call.end("OK")


def tf_static(path) -> list:
    """``(log_time, FrameTransforms)`` of the file's ``/tf_static``, decoded with its schema."""
    with open(path, "rb") as f:
        got = [(s, m) for s, c, m in make_reader(f).iter_messages(log_time_order=False)
               if c.topic == "/tf_static"]
    return [(m.log_time, message_class(s.data, s.name).FromString(m.data)) for s, m in got]


def edges(msg) -> dict:
    """parent, child -> (stamp ns, T_parent_child)."""
    return {(x.parent_frame_id, x.child_frame_id): (
        x.timestamp.seconds * 10**9 + x.timestamp.nanos,
        dq.from_pose([x.rotation.w, x.rotation.x, x.rotation.y, x.rotation.z],
                     [x.translation.x, x.translation.y, x.translation.z]))
        for x in msg.transforms}


def test_a_configure_is_one_static_message_of_its_statics_and_sources(tmp_path):
    r = Recorder(tmp_path)
    configure(r, config())
    r.close()
    ((_, msg),) = tf_static(r.files[0])
    got = edges(msg)
    want = {("world", "table"): TABLE, ("tool", "tcp"): TCP, ("tool", "wrist"): CAM,
            ("world", "ceiling"): ROOM, ("world", "arm"): dq.identity()}
    assert set(got) == set(want)
    for k, T in want.items():
        stamp, pose = got[k]
        assert stamp == 0       # valid at every time
        np.testing.assert_allclose(dq.to_matrix(pose), dq.to_matrix(T), atol=1e-12,
                                   err_msg=str(k))


def test_the_last_configuration_is_repeated_in_every_later_file(tmp_path):
    r = Recorder(tmp_path, max_bytes=4000)
    first = config()
    configure(r, first)
    del first.statics[0]
    configure(r, first)             # the table gone: the second message has no table
    data = _stream.requests(30)
    record_stream(r, data, _stream.answers(data))
    r.close()
    assert len(r.files) > 2
    (_, a), (_, b) = tf_static(r.files[0])
    assert ("world", "table") in edges(a) and ("world", "table") not in edges(b)
    for path in r.files[1:]:
        ((_, msg),) = tf_static(path)           # once, at the file's start
        assert edges(msg).keys() == edges(b).keys()


def test_a_world_with_no_fixed_frame_writes_none(tmp_path):
    r = Recorder(tmp_path)
    configure(r, wpb.WorldConfig(sources=[fpb.Source(name="")]))
    r.close()
    assert tf_static(r.files[0]) == []
