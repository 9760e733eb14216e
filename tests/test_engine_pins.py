"""One engine (issue 38's pin): with one source, the same options and the same measurements,
StreamFuse at output rate r and a world's Subscribe at rate r give the same answers (body,
time, pose, covariance) bit for bit, r > 0 and r = 0. In process: the Fusion servicer's path
(request bytes in, answer bytes out) against a world's hub fed the same measurements as Publish
requests."""
from __future__ import annotations

import numpy as np
import pytest

from dqpose import dq, lie
from dqpose.fusion import Source
from dqpose.hub import Subscription
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb
from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb
from dqpose.rpc.client_types import Batch
from dqpose.rpc.fusion import Fusion
from dqpose.rpc.fusion_convert import options_msg
from dqpose.rpc.wire import measurements_wire, publish_request_wire
from dqpose.rpc.world import World, interest
from dqpose.rpc.world_convert import world_config

SOURCE = Source("cam", lie.se3_exp(np.array([0.1, -0.2, 0.3, 0.5, 0.1, 1.0])), latency=0.02)
COV = np.diag([4e-5, 4e-5, 9e-5, 1e-6, 1e-6, 4e-6])
WINDOW, TWIST = 0.15, np.eye(6) * 0.5
BODIES = ("box", "cup")


def batches(seed: int = 3, requests: int = 80) -> list[Batch]:
    """Requests of one to three measurements of the bodies, moving, 7 to 13 ms apart (a
    camera that sees one body at a time, or both)."""
    rng = np.random.default_rng(seed)
    out, t = [], 100.0
    for _ in range(requests):
        n = int(rng.integers(1, 4))
        bodies = [BODIES[int(rng.integers(0, 2))] for _ in range(n)]
        times = t + np.sort(rng.uniform(0.0, 0.006, n))
        poses = np.array([dq.mul(lie.se3_exp(np.array([0.2, 0.1 * k, -0.3, k, 0.5, 1.0])
                                              + (tk - 100.0) * np.array([0.3, -0.1, 0.2, 0.1,
                                                                         0.05, -0.2])),
                                 lie.se3_exp(rng.multivariate_normal(np.zeros(6), COV)))
                          for k, tk in zip((BODIES.index(b) for b in bodies), times)])
        out.append(Batch(poses, np.repeat(COV[None], n, 0), None, ["cam"] * n, bodies, times))
        t += float(rng.uniform(0.007, 0.013))
    return out


def stream_fuse(rate: float, data: list[Batch]) -> list[fpb.FusedPose]:
    f = Fusion()
    first = fpb.FuseStreamRequest(output_rate=rate, options=options_msg(
        sources=[SOURCE], window=WINDOW, twist_covariance=TWIST)).SerializeToString()
    state, answers, n = f.start_stream(first)
    out, next_id = list(answers), n
    for r, b in enumerate(data, start=1):
        got, n = f.stream_step_wire(state, measurements_wire(*b), r, next_id)
        out += got
        next_id += n
    return out


def subscribed(rate: float, data: list[Batch]) -> list[fpb.FusedPose]:
    server = World()
    hub = server.hub("", make=True)
    # configured as StreamFuse's options are: through their message (the extrinsic's bits)
    server.configure(hub, world_config([SOURCE], window=WINDOW, buffer=1.0,
                                       twist_covariance=TWIST))
    given: list = []
    hub.subscribe(Subscription(interest(wpb.SubscribeRequest(rate_hz=rate)), given.extend))
    for r, b in enumerate(data):
        ack = server.publish_bytes(hub, publish_request_wire(b, "cam", r + 1), r, "call")
        assert not ack.errors, ack
    return [fpb.FusedPose.FromString(a) for a in given]


def pinned(answers) -> list[tuple]:
    return [(a.body, a.time, a.pose.SerializeToString(), tuple(a.covariance)) for a in answers
            if not a.HasField("error")]


@pytest.mark.parametrize("rate", [20.0, 0.0])
def test_stream_fuse_and_a_world_subscribe_give_the_same_answers_bit_for_bit(rate):
    data = batches()
    fused, world = stream_fuse(rate, data), subscribed(rate, data)
    assert not any(a.HasField("error") for a in fused + world)
    assert len(pinned(fused)) > (25 if rate else 70)
    assert pinned(world) == pinned(fused)
    # and both name the same fused measurements (numbered over the stream and the world)
    assert [list(a.measurements) for a in world] == [list(a.measurements) for a in fused]
