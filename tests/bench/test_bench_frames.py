"""The ListFrames benchmark's harness, small: its world has the 1,000 frames it names, the bytes
it times are the world's frames, and a request to one body changes that body's frame alone."""
import numpy as np

from dqpose.rpc._proto.dqpose.v1 import world_pb2 as pb
from dqpose.rpc.world_frames import frames_of, list_frames
from tests.bench import bench_frames as bf


def test_the_timed_bytes_are_the_worlds_1000_frames_and_follow_a_request():
    hub = bf.world()
    before = frames_of(pb.FrameList.FromString(list_frames(hub, pb.ListFramesRequest())))
    assert len(before) == 1000 and before == hub.world.frames()
    hub.world.ingest(["b0"], ["cam0"], np.array([5.0]), bf.ONE[None], np.eye(6)[None] * 1e-6)
    after = frames_of(pb.FrameList.FromString(list_frames(hub, pb.ListFramesRequest())))
    changed = [a.name for a, b in zip(after, before) if a != b]
    assert changed == ["b0"] and after[1].newest == 5.0
    assert bf.per_call(hub, 3) > 0.0
