"""Extreme values (hypothesis) get a finite answer or a field error; oversized requests and answers
are RESOURCE_EXHAUSTED; deadlines."""
from __future__ import annotations

import json
import logging
import math
import queue
import re
import urllib.request

import grpc
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from dqpose.rpc._proto.dqpose.v1 import blending_pb2 as pb
from dqpose.rpc._proto.dqpose.v1 import blending_pb2_grpc as pb_grpc
from dqpose.rpc._proto.dqpose.v1 import geometry_pb2 as geo
from tests.rpc._grpc_server import ServerThread
from tests.rpc.server._blending import (
    MAX_BYTES,
    MAX_POSES,
    NAN,
    _code,
    _poses,
    blend_req,
    pose_msg,
    random_poses,
    socket_free_port,
)

# ---------------------------------------------------------------------------- extreme values

# Every refusal names a field of the request, whatever the values: no internal variable (tau,
# dqs, q, a) may leak into a message.
FIELD_PATH = re.compile(r"^(keyframes|times|poses|weights|method|tolerance|max_iterations|requests"
                        r"|interpolation)(\[\d+\])?(\.\w+(\[\d+\])?)*: ")
BIG = 1.7976931348623157e308
FINITE = st.sampled_from([0.0, -0.0, 1.0, -1.0, 0.5, 1e308, -1e308, BIG, -BIG, 1e300, -1e300,
                          1e150, -1e154, 5e-324, -5e-324, 2.2250738585072014e-308, 1e-300])
# (a translation of 1e150 is within what the core takes, 1e154 is not)
EXTREME = FINITE | st.sampled_from([NAN, float("inf"), float("-inf")]) | st.floats()
UNIT = st.sampled_from([(1.0, 0, 0, 0), (0.0, 1, 0, 0), (0.0, 0, 0, -1), (0.6, 0.8, 0, 0),
                        (0.5, 0.5, 0.5, 0.5), (-0.5, 0.5, -0.5, 0.5), (0.0, 0.6, 0, -0.8)])
# Counts at the server's limits as well as small ones.
COUNT = st.integers(1, 4) | st.integers(0, 4) | st.sampled_from([MAX_POSES, MAX_POSES + 1])
POSE_FIELDS = ("position.x", "position.y", "position.z", "orientation.w", "orientation.x",
               "orientation.y", "orientation.z")


def _set(msg, path: str, value) -> None:
    *parents, leaf = path.split(".")
    for name in parents:
        msg = getattr(msg, name)
    setattr(msg, leaf, value)


@st.composite
def _with_extremes(draw, values: list, poses: list) -> None:
    """A plain request's values and poses with up to three of them made extreme (in place), so
    that one extreme value usually gets past the checks into the math."""
    for _ in range(draw(st.integers(0, 3))):
        if poses and (not values or draw(st.booleans())):
            i = draw(st.integers(0, len(poses) - 1))
            _set(poses[i], draw(st.sampled_from(POSE_FIELDS)), draw(EXTREME))
        elif values:
            values[draw(st.integers(0, len(values) - 1))] = draw(EXTREME)


@st.composite
def plain_poses(draw, n: int) -> list:
    """``n`` plain poses: unit orientations, positions within +-10 m (at most 4 distinct)."""
    distinct = draw(st.lists(st.tuples(UNIT, st.tuples(*[st.floats(-10, 10)] * 3)),
                             min_size=1, max_size=4))
    return [pose_msg(*distinct[i % len(distinct)]) for i in range(n)]


@st.composite
def extreme_blend_requests(draw, small=False):
    poses = draw(plain_poses(draw(st.integers(1, 3) if small else COUNT)))
    weights = draw(st.just([]) | st.lists(st.floats(0, 10), min_size=len(poses),
                                          max_size=len(poses)))
    draw(_with_extremes(weights, poses))
    return pb.BlendRequest(
        poses=poses, weights=weights,
        method=draw(st.sampled_from(list(range(7)) * 3 + [7, -1, 2**31 - 1])),
        tolerance=draw(st.just(0.0) | st.floats(1e-15, 1e-3) | EXTREME),
        max_iterations=draw(st.sampled_from([0, 1, 2, 1000, 1001, 2**32 - 1])))


@st.composite
def extreme_interpolate_requests(draw):
    # Plain increasing times in [-1, 1] at an extreme scale: at BIG the keyframe span overflows,
    # at 5e-324 neighbouring times are subnormal or collapse into one.
    k = draw(st.integers(2, 4) | st.integers(2, 4) | COUNT)
    unit = st.floats(-1, 1) | st.sampled_from([-1.0, -0.5, 0.0, 0.5, 1.0])
    plain_k = sorted(draw(st.lists(unit, min_size=min(k, 2), max_size=k, unique=True)))
    lo, hi = (plain_k[0], plain_k[-1]) if plain_k else (0.0, 0.0)
    plain = draw(st.lists(st.floats(lo, hi) | st.sampled_from(plain_k or [0.0]), min_size=1,
                          max_size=4))
    scale = draw(st.sampled_from([1.0, 1e-300, 5e-324, 1e300, 1e308, BIG]))
    times_k = [scale * s for s in plain_k]
    times = [scale * plain[i % len(plain)] for i in range(draw(COUNT))]
    kf = [geo.StampedPose(time=s, pose=p) for s, p in zip(times_k, draw(plain_poses(k)))]
    values = times_k + times
    draw(_with_extremes(values, [f.pose for f in kf]))
    for f, s in zip(kf, values):
        f.time = s
    return pb.InterpolateRequest(keyframes=kf, times=values[len(kf):],
                                 interpolation=draw(st.sampled_from([0, 1, 2] * 3 + [3, -1])))


def _answer_or_field_error(call, check):
    try:
        check(call())
    except grpc.RpcError as e:
        # RESOURCE_EXHAUSTED: over one of the server's limits (service/limits.py), named too
        assert e.code() in (grpc.StatusCode.INVALID_ARGUMENT,
                            grpc.StatusCode.RESOURCE_EXHAUSTED), (e.code(), e.details())
        assert FIELD_PATH.match(e.details()), e.details()


def _finite_pose(p):
    v = [p.position.x, p.position.y, p.position.z, p.orientation.w, p.orientation.x,
         p.orientation.y, p.orientation.z]
    assert np.isfinite(v).all(), p


@given(extreme_blend_requests())
def test_extreme_blend_requests_get_a_finite_answer_or_a_field_error(stub, request_):
    def check(r):
        _finite_pose(r.pose)
        assert math.isfinite(r.residual)
    _answer_or_field_error(lambda: stub.Blend(request_, timeout=10), check)
    _answer_or_field_error(lambda: list(stub.BlendStream(iter([request_]), timeout=10)),
                           lambda rs: [check(r) for r in rs])


@given(st.lists(extreme_blend_requests(small=True), min_size=1, max_size=3).flatmap(
    lambda rs: COUNT.map(lambda n: [rs[i % len(rs)] for i in range(n)])))
def test_extreme_blend_batches_get_finite_answers_or_a_field_error(stub, requests_):
    def check(r):
        for one in r.responses:
            _finite_pose(one.pose)
            assert math.isfinite(one.residual)
    _answer_or_field_error(
        lambda: stub.BlendBatch(pb.BlendBatchRequest(requests=requests_), timeout=10), check)


@given(extreme_interpolate_requests())
def test_extreme_interpolate_requests_get_finite_answers_or_a_field_error(stub, request_):
    def check(r):
        assert len(r.samples) == len(request_.times)
        for s in r.samples:
            _finite_pose(s.pose)
    _answer_or_field_error(lambda: stub.Interpolate(request_, timeout=10), check)


def test_oversized_request_is_resource_exhausted_and_the_server_stays_up(stub):
    big = blend_req(*_poses(MAX_POSES), weights=[1.0] * MAX_POSES)
    big.weights.extend([1.0] * (MAX_BYTES // 8))
    assert big.ByteSize() > MAX_BYTES
    with pytest.raises(grpc.RpcError) as e:
        stub.Blend(big, timeout=10)
    assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert "larger than max" in e.value.details()
    assert stub.Blend(blend_req(*_poses(2)), timeout=10).pose.orientation.w == pytest.approx(1.0)


# An answer over the server's --max-message-bytes: gRPC would refuse to send it after the call
# was recorded as OK, with a traceback in the log; the server must say RESOURCE_EXHAUSTED itself,
# naming the size, the limit and what to do, and log and count that.

SMALL_BYTES = 16 * 1024


def _oversized_calls(stub, rng):
    """(rpc, call of the first k items, message start, n) for answers over SMALL_BYTES to
    requests of n items under it."""
    q, t = random_poses(rng, 2)
    kf = [geo.StampedPose(time=float(i), pose=pose_msg(q[i], t[i])) for i in range(2)]
    times = rng.uniform(0, 1, 1000)
    # 15 bytes a request in the batch, 17 an answer (which carries an empty position).
    batch = [pb.BlendRequest(poses=[geo.Pose(orientation=geo.Quaternion(w=1.0))])] * 1000
    return [
        ("Interpolate", lambda k: stub.Interpolate(
            pb.InterpolateRequest(keyframes=kf, times=list(times[:k])), timeout=10),
         "times: the response to 1000 times is ", 1000),
        ("BlendBatch", lambda k: stub.BlendBatch(
            pb.BlendBatchRequest(requests=batch[:k]), timeout=10),
         "requests: the response to 1000 requests is ", 1000),
    ]


def test_an_answer_over_the_message_limit_is_resource_exhausted_logged_and_counted(caplog):
    caplog.set_level(logging.INFO, logger="dqpose.calls")
    rng = np.random.default_rng(12)
    # The client may send and receive more than the server: only the server's limit is tested.
    big = [("grpc.max_send_message_length", 1 << 24), ("grpc.max_receive_message_length", 1 << 24)]
    with socket_free_port() as port, ServerThread(max_message_bytes=SMALL_BYTES, max_poses=2000,
                                                  metrics_port=port) as s:
        with grpc.insecure_channel(s.target, options=big) as ch:
            stub = pb_grpc.BlendingStub(ch)
            for rpc, call, start, n in _oversized_calls(stub, rng):
                code, details = _code(lambda: call(n))
                assert code == grpc.StatusCode.RESOURCE_EXHAUSTED, (rpc, code, details)
                m = re.fullmatch(re.escape(start) + rf"(\d+) bytes, over the server's max message "
                                 rf"size of {SMALL_BYTES} bytes; send about (\d+) \w+ per call, "
                                 rf"or fewer", details)
                assert m and int(m[1]) > SMALL_BYTES, details
                assert _code(lambda: call(int(m[2])))[0] == grpc.StatusCode.OK, rpc
        text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read().decode()
        s.stop()
        s.running.calls.flush()
    for rpc in ("Interpolate", "BlendBatch"):
        assert re.search(rf'dqpose_grpc_calls_total\{{code="RESOURCE_EXHAUSTED",'
                         rf'rpc="{rpc}"\}} 1\.0', text), text
        assert re.search(rf'dqpose_grpc_calls_total\{{code="OK",rpc="{rpc}"\}} 1\.0', text), text
    calls = [json.loads(line) for r in caplog.records if r.name == "dqpose.calls"
             for line in r.getMessage().splitlines()]
    assert [(c["rpc"], c["code"]) for c in calls] == [
        ("Interpolate", "RESOURCE_EXHAUSTED"), ("Interpolate", "OK"),
        ("BlendBatch", "RESOURCE_EXHAUSTED"), ("BlendBatch", "OK")]
    errors = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert not errors, [r.getMessage() for r in errors]


def test_a_stream_answer_over_the_message_limit_is_resource_exhausted(caplog):
    caplog.set_level(logging.INFO, logger="dqpose.calls")
    # 22 bytes in, 24 out (the answer carries an empty position): a limit of 23 takes the
    # request and cannot send its answer.
    req = pb.BlendRequest(poses=[geo.Pose(orientation=geo.Quaternion(w=0.6, x=0.8))])
    assert req.ByteSize() <= 23
    with ServerThread(max_message_bytes=23) as s, grpc.insecure_channel(s.target) as ch:
        stream = pb_grpc.BlendingStub(ch).BlendStream(iter([req]), timeout=10)
        code, details = _code(lambda: list(stream))
        s.stop()
        s.running.calls.flush()
    assert code == grpc.StatusCode.RESOURCE_EXHAUSTED, (code, details)
    assert details.startswith("requests[0].request: the response to 1 request is 24 bytes, over "
                              "the server's max message size of 23 bytes"), details
    calls = [json.loads(line) for r in caplog.records if r.name == "dqpose.calls"
             for line in r.getMessage().splitlines()]
    assert [(c["rpc"], c["code"]) for c in calls] == [("BlendStream", "RESOURCE_EXHAUSTED")]
    errors = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert not errors, [r.getMessage() for r in errors]


def test_expired_deadline_is_deadline_exceeded(stub):
    # A stream the client never feeds: the deadline, not the work, ends it.
    requests: queue.Queue = queue.Queue()
    stream = stub.BlendStream(iter(requests.get, None), timeout=0.3)
    try:
        with pytest.raises(grpc.RpcError) as e:
            next(stream)
        assert e.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED
    finally:
        requests.put(None)
    assert stub.Blend(blend_req(*_poses(2)), timeout=10).pose.orientation.w == pytest.approx(1.0)


def test_never_returns_nan_for_cancelling_rotations(stub):
    # Two opposite 180-degree turns blended linearly: no defined mean for some methods; whatever
    # the server answers must be finite or an INVALID_ARGUMENT.
    q = np.array([[0.0, 1, 0, 0], [0.0, 0, 1, 0]])
    t = np.zeros((2, 3))
    for m in (pb.METHOD_DLB, pb.METHOD_LOG, pb.METHOD_LIN, pb.METHOD_DEC, pb.METHOD_DIB):
        try:
            r = stub.Blend(blend_req(q, t, method=m), timeout=10)
        except grpc.RpcError as e:
            assert e.code() == grpc.StatusCode.INVALID_ARGUMENT
            continue
        p = r.pose
        assert np.isfinite([p.position.x, p.position.y, p.position.z, p.orientation.w,
                            p.orientation.x, p.orientation.y, p.orientation.z, r.residual]).all()
