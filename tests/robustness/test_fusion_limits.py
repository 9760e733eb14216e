"""Fusion against the probe's requests: one StreamFuse message never holds the server (rates and
times checked for what the tick loop can do, the answers of one message bounded), a body's
window bounded and never poisoned, robust fits within their limits, every refusal naming the
field, the limit and its flag."""
from __future__ import annotations

import grpc
import numpy as np
import pytest

from service import limits
from service.rpc.fusion import Fusion
from service.rpc.server import ServerConfig
from service.rpc._proto.dqpose.v1 import fusion_pb2 as pb
from service.rpc._proto.dqpose.v1 import fusion_pb2_grpc as pb_grpc

from _served import code_of, pose, served


@pytest.fixture(scope="module")
def server():
    with served() as s:
        yield s


def measurement(t, body="b", source="s"):
    return pb.Measurement(body=body, source=source, time=t, pose=pose())


def stream(server, requests, timeout=30.0):
    """Every answer of a StreamFuse call of ``requests``."""
    return list(pb_grpc.FusionStub(server.channel).StreamFuse(iter(requests), timeout=timeout))


def errors(answers):
    return [a.error.details for a in answers if a.HasField("error")]


# ---- D1: one message must never hang the server

@pytest.mark.parametrize("rate", [1e8, 1e300])
def test_an_output_rate_beyond_the_limit_is_refused_naming_it(server, rate):
    code, details = code_of(lambda: stream(server, [
        pb.FuseStreamRequest(output_rate=rate, measurements=[measurement(0.0)])]))
    assert code == grpc.StatusCode.RESOURCE_EXHAUSTED, (code, details)
    assert details.startswith("requests[0].output_rate: "), details
    assert "max_output_rate" in details and "--max-output-rate" in details, details
    assert server.health() == "SERVING"


@pytest.mark.parametrize("t", [1e300, 1e17, -1e11])
def test_a_time_beyond_the_limit_is_an_error_entry_and_the_stream_goes_on(server, t):
    answers = stream(server, [
        pb.FuseStreamRequest(output_rate=10.0, measurements=[measurement(0.0)]),
        pb.FuseStreamRequest(measurements=[measurement(t)]),
        pb.FuseStreamRequest(measurements=[measurement(0.05 * k) for k in range(1, 5)])])
    (e,) = [a for a in answers if a.request == 1]
    assert e.error.measurement == 0
    assert e.error.details.startswith("requests[1].measurements[0].time: "), e.error.details
    assert "max_time" in e.error.details and "--max-time" in e.error.details
    # the body was not moved by it: the next message's measurements are fused at their ticks
    later = [a for a in answers if a.request == 2]
    assert later and not errors(later)
    assert all(0.0 <= a.time <= 0.2 for a in later)
    assert server.health() == "SERVING"


def test_the_answers_of_one_message_are_bounded_the_latest_kept():
    # a 1e6 s window at 1000 Hz, reached by one message: 1e9 ticks due at once
    bounds = limits.Limits(max_fused_per_request=10 * (2 + limits.ANSWER_ROWS))
    fusion = Fusion(ServerConfig(limits=bounds))
    first = pb.FuseStreamRequest(output_rate=1000.0, measurements=[measurement(0.0)])
    first.options.window = 1e6
    state = fusion.stream_options(first)
    fusion.stream_step(state, first, 0, 0)
    answers = fusion.stream_step(state, pb.FuseStreamRequest(measurements=[measurement(1e6)]),
                                 1, 1)
    fused = [a for a in answers if not a.HasField("error")]
    assert len(fused) == 10
    assert fused[-1].time <= 1e6 and fused[0].time > 1e6 - 0.011
    (skip,) = errors(answers)
    assert skip.startswith("requests[1]: body 'b': 999999990 ticks from "), skip
    assert "max_fused_per_request" in skip and "--max-fused-per-request" in skip
    # the skipped ticks are not due again
    assert not fusion.stream_step(state, pb.FuseStreamRequest(
        measurements=[measurement(1e6 - 1e-4)]), 2, 2)
