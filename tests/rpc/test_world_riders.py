"""Sources riding on bodies through a real server on 127.0.0.1: a camera on the arm's tool
configured, the tool and the camera's box published, the box looked up (World) and streamed
(StreamFuse); an arm whose source rides on a body refused FAILED_PRECONDITION."""
from __future__ import annotations

import grpc
import numpy as np
import pytest

from dqpose import dq
from dqpose.fusion import Source
from dqpose.rpc.client import Batch, Client, RpcError
from dqpose.world import Measurement
from tests.rpc._grpc_server import ServerThread
from tests.test_riders import BOX, COV_CAM, COV_X, RATE, N, X, scene, tool_at

SOURCES = [Source("arm"), Source("cam", extrinsic=X, extrinsic_covariance=COV_X, parent="tool")]


@pytest.fixture(scope="module")
def target():
    with ServerThread() as s:
        yield s.target


def batch(ms) -> Batch:
    return Batch(np.array([m.pose for m in ms]), np.array([m.covariance for m in ms]), None,
                 [m.source for m in ms], [m.body for m in ms], np.array([m.time for m in ms]))


def test_a_camera_on_the_tool_gives_a_lookup_of_the_box(target):
    with Client(target, world="riders") as c:
        config = c.configure_world(SOURCES, window=0.5, buffer=5.0)
        assert [s.parent for s in config.sources] == ["", "tool"]
        acks = list(c.publish([batch(scene())], producer="p"))
        assert not acks[0].errors
        got = c.lookup("", "box")
        np.testing.assert_allclose(got.pose * np.sign(got.pose[0]), BOX, rtol=0, atol=1e-9)
        assert np.all(np.linalg.eigvalsh(got.covariance) > 0)
        # the box in the tool's frame at the tool's newest
        t = got.time
        rel = c.lookup("tool", "box", t)
        want = dq.mul(dq.conj(tool_at(t)), BOX)
        np.testing.assert_allclose(rel.pose * np.sign(rel.pose[0] * want[0]), want, rtol=0,
                                   atol=1e-9)


def test_stream_fuse_resolves_a_parent_as_the_world_does(target):
    late = 10.0 + (N - 1) / RATE + 0.25      # the tool known up to 0.25 s before
    cam = dq.conj(dq.mul(tool_at(late), X))
    row = Measurement("cam", "box", late, dq.mul(cam, BOX), COV_CAM)
    with Client(target) as c:
        answers = list(c.stream_fuse([batch(scene()), batch([row])], sources=SOURCES,
                                     window=0.5))
    box = [a for a in answers if a.body == "box"]
    assert [a.request for a in box] == [0, 1] and box[0].error is None, answers
    f = box[0].fused
    np.testing.assert_allclose(f.mean * np.sign(f.mean[0]), BOX, rtol=0, atol=1e-9)
    # the late row is the answer's last measurement, dropped with the reason
    f, ids = box[1].fused, box[1].measurements
    assert len(f.dropped) == 1 and f.dropped[0].index == len(ids) - 1 and ids[-1] == 2 * N
    assert f.dropped[0].reason.startswith(
        f"measurement {len(ids) - 1} (cam): its parent 'tool' is not known at 10.55"), f.dropped
    np.testing.assert_allclose(f.mean * np.sign(f.mean[0]), BOX, rtol=0, atol=1e-9)


def test_an_arm_whose_source_rides_on_a_body_is_failed_precondition(target):
    with Client(target, world="riders-arm") as c:
        with pytest.raises(RpcError) as e:
            c.configure_world([Source("ur", parent="base")], arms={"ur": "ur"})
    assert e.value.code == grpc.StatusCode.FAILED_PRECONDITION
    assert e.value.details.startswith("config.arms['ur']: source 'ur' rides on 'base'"), \
        e.value.details


def test_a_rider_beside_an_acceleration_psd_is_invalid_argument(target):
    with Client(target, world="riders-psd") as c:
        with pytest.raises(RpcError) as e:
            c.configure_world(SOURCES, window=0.5, acceleration_psd=np.eye(6) * 1e-3)
    assert e.value.code == grpc.StatusCode.INVALID_ARGUMENT
    assert e.value.details.startswith("config.sources[1].parent: source 'cam' rides on 'tool'"), \
        e.value.details
