"""Blending against the probe's requests: its limits refused naming the limit and its flag, and
its largest legal requests answered off the event loop."""
from __future__ import annotations

import grpc
import numpy as np
import pytest

from dqpose.rpc import geometry
from dqpose.rpc._proto.dqpose.v1 import blending_pb2 as pb
from dqpose.rpc._proto.dqpose.v1 import blending_pb2_grpc as pb_grpc
from tests.robustness._served import code_of, served


@pytest.fixture(scope="module")
def server():
    with served() as s:
        yield s


def poses(n, seed=0):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return geometry.pose_msgs(q / np.linalg.norm(q, axis=1, keepdims=True), rng.normal(size=(n, 3)))


def test_max_iterations_over_the_limit_is_refused_naming_it(server):
    request = pb.BlendRequest(poses=poses(3), max_iterations=2_000_000)
    code, details = code_of(lambda: pb_grpc.BlendingStub(server.channel).Blend(request, timeout=30))
    assert code == grpc.StatusCode.RESOURCE_EXHAUSTED, (code, details)
    assert details == ("max_iterations: 2000000, over the server's limit max_iterations = 1000 "
                       "iterations (dqpose serve --max-iterations)")


def test_the_limit_is_the_one_its_flag_sets():
    # the flag the refusal names is the one that moves the limit
    with served("--max-iterations", "5") as s:
        blend = pb_grpc.BlendingStub(s.channel).Blend
        code, details = code_of(lambda: blend(pb.BlendRequest(poses=poses(3), max_iterations=6),
                                              timeout=30))
        assert code == grpc.StatusCode.RESOURCE_EXHAUSTED, (code, details)
        assert details == ("max_iterations: 6, over the server's limit max_iterations = 5 "
                           "iterations (dqpose serve --max-iterations)")
        assert code_of(lambda: blend(pb.BlendRequest(poses=poses(3), max_iterations=5),
                                     timeout=30))[0] == grpc.StatusCode.OK
