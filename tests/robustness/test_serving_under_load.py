"""The server while its heaviest legal requests run (item 1 of issue 18): health and another
client's Blend are answered, and SIGTERM ends it, because what grows with a request runs in the
worker pool, off the event loop. (How fast they are answered is the benchmark's:
tests/bench/bench_bystander.py.)"""
from __future__ import annotations

import threading

import grpc
import pytest

from dqpose import limits
from dqpose.rpc._proto.dqpose.v1 import blending_pb2 as bpb
from dqpose.rpc._proto.dqpose.v1 import blending_pb2_grpc as bpb_grpc
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2_grpc as fpb_grpc
from dqpose.rpc._proto.dqpose.v1 import handeye_pb2_grpc as hpb_grpc
from tests.robustness._served import HEALTH_DEADLINE, Served, pose
from tests.robustness.test_fusion_limits import fuse_request
from tests.robustness.test_handeye_limits import request as calibrate_request


@pytest.mark.heavy
def test_health_a_bystander_and_sigterm_are_answered_while_the_heaviest_requests_run():
    server = Served("--grace", "1")
    try:
        fuse = fuse_request(limits.DEFAULT.max_robust, limits.DEFAULT.max_robust // 3,
                            robust=True)
        calibrate = calibrate_request(limits.DEFAULT.max_pairs, corners=True)
        calls = [lambda: fpb_grpc.FusionStub(server.channel).Fuse(fuse, timeout=300)] * 4 + [
            lambda: hpb_grpc.HandEyeStub(server.channel).Calibrate(calibrate, timeout=300)] * 2
        done = []

        def run(call):
            try:
                call()
                done.append("OK")
            except grpc.RpcError as e:
                done.append(e.code().name)
        threads = [threading.Thread(target=run, args=(c,)) for c in calls]
        for t in threads:
            t.start()
        assert server.health() == "SERVING"
        blend = bpb.BlendRequest(poses=[pose(), pose()])
        answer = bpb_grpc.BlendingStub(server.channel).Blend(blend, timeout=HEALTH_DEADLINE)
        assert answer.pose.orientation.w == 1.0
        for t in threads:
            t.join()
        assert done == ["OK"] * len(calls)
        # SIGTERM while the heaviest run: served and ended within the grace period
        threads = [threading.Thread(target=run, args=(c,)) for c in calls[-2:]]
        for t in threads:
            t.start()
        assert server.health() == "SERVING"
    finally:
        code = server.stop()
    assert code == 0
    for t in threads:
        t.join()
