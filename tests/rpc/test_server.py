"""The gRPC server, through the generated stubs, against a real server on 127.0.0.1."""
from __future__ import annotations

import json
import logging
import math
import os
import queue
import re
import shutil
import signal
import subprocess
import sys
import threading
import urllib.request

import grpc
import numpy as np
import pytest
from _grpc_server import ServerThread, make_pki
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha.proto_reflection_descriptor_database import (
    ProtoReflectionDescriptorDatabase,
)
from hypothesis import given
from hypothesis import strategies as st

from dqpose import dq
from dqpose.interpolate import interpolate
from dqpose.rpc._proto.dqpose.v1 import blending_pb2 as pb
from dqpose.rpc._proto.dqpose.v1 import blending_pb2_grpc as pb_grpc
from dqpose.rpc._proto.dqpose.v1 import geometry_pb2 as geo
from dqpose.rpc.server import ServerConfig, start

MAX_POSES = 200
MAX_BYTES = 64 * 1024
ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


@pytest.fixture(scope="module")
def server():
    with ServerThread(max_poses=MAX_POSES, max_message_bytes=MAX_BYTES) as s:
        yield s


@pytest.fixture(scope="module")
def stub(server):
    with grpc.insecure_channel(server.target) as ch:
        yield pb_grpc.BlendingStub(ch)


def random_poses(rng, n):
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q, rng.uniform(-1, 1, size=(n, 3))


def pose_msg(q, t):
    return geo.Pose(position=geo.Vector3(x=t[0], y=t[1], z=t[2]),
                    orientation=geo.Quaternion(w=q[0], x=q[1], y=q[2], z=q[3]))


def msg_to_dq(p):
    o, t = p.orientation, p.position
    return dq.from_pose([o.w, o.x, o.y, o.z], [t.x, t.y, t.z])


def same_pose(a, b, atol=1e-9):
    s = np.sign(np.dot(a[:4], b[:4]))
    np.testing.assert_allclose(s * a, b, atol=atol)


def blend_req(q, t, weights=(), method=pb.METHOD_UNSPECIFIED, **kw):
    return pb.BlendRequest(poses=[pose_msg(a, b) for a, b in zip(q, t)], weights=list(weights),
                           method=method, **kw)


# --------------------------------------------------------------------------- every RPC

@pytest.mark.parametrize("method, name, n", [
    (pb.METHOD_UNSPECIFIED, "dib", 10), (pb.METHOD_DIB, "dib", 10), (pb.METHOD_DLB, "dlb", 10),
    (pb.METHOD_SCLERP, "sclerp", 2), (pb.METHOD_LIN, "lin", 10), (pb.METHOD_DEC, "dec", 10),
    (pb.METHOD_LOG, "log", 10)])
def test_blend_matches_the_core(stub, method, name, n):
    rng = np.random.default_rng(n + method)
    q, t = random_poses(rng, n)
    w = rng.uniform(0.1, 2.0, n)
    r = stub.Blend(blend_req(q, t, w, method), timeout=10)
    same_pose(msg_to_dq(r.pose), dq.blend(dq.from_pose(q, t), w, name))
    if name == "dib":
        assert r.iterations > 0 and r.residual < 1e-9
    else:
        assert r.iterations == 0


def test_blend_defaults_equal_weights_and_honours_tolerance_and_iterations(stub):
    q, t = random_poses(np.random.default_rng(7), 6)
    r = stub.Blend(blend_req(q, t), timeout=10)
    same_pose(msg_to_dq(r.pose), dq.dib(dq.from_pose(q, t)))
    one = stub.Blend(blend_req(q, t, max_iterations=1), timeout=10)
    assert one.iterations == 1 and one.residual > r.residual
    loose = stub.Blend(blend_req(q, t, tolerance=1e-2), timeout=10)
    assert loose.iterations < r.iterations


@pytest.mark.parametrize("interp, mode", [(geo.INTERPOLATION_UNSPECIFIED, "screw"),
                                          (geo.INTERPOLATION_SCREW, "screw"),
                                          (geo.INTERPOLATION_TOOL_LINEAR, "tool_linear")])
def test_interpolate_matches_the_domain_function(stub, interp, mode):
    rng = np.random.default_rng(11)
    q, t = random_poses(rng, 4)
    times_k = np.array([0.0, 0.5, 1.5, 2.0])
    times = rng.uniform(0, 2, 100)
    req = pb.InterpolateRequest(
        keyframes=[geo.StampedPose(time=s, pose=pose_msg(a, b)) for s, a, b in zip(times_k, q, t)],
        times=times.tolist(), interpolation=interp)
    r = stub.Interpolate(req, timeout=10)
    assert [s.time for s in r.samples] == times.tolist()
    want = interpolate(times_k, dq.from_pose(q, t), times, mode)
    for s, w in zip(r.samples, want):
        same_pose(msg_to_dq(s.pose), w)


def test_blend_stream_answers_each_request_in_order(stub):
    rng = np.random.default_rng(5)
    reqs = [blend_req(*random_poses(rng, 5), method=pb.METHOD_DLB) for _ in range(50)]
    got = list(stub.BlendStream(iter(reqs), timeout=10))
    assert len(got) == 50
    for req, r in zip(reqs, got):
        same_pose(msg_to_dq(r.pose), msg_to_dq(stub.Blend(req, timeout=10).pose), atol=1e-12)


def test_blend_stream_names_the_bad_request(stub):
    rng = np.random.default_rng(6)
    reqs = [blend_req(*random_poses(rng, 3)) for _ in range(5)]
    reqs[3].poses[1].orientation.Clear()
    call = stub.BlendStream(iter(reqs), timeout=10)
    got = []
    with pytest.raises(grpc.RpcError) as e:
        for r in call:
            got.append(r)
    assert len(got) == 3
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert e.value.details() == "requests[3].poses[1].orientation: zero quaternion"


def test_blend_batch_answers_each_request_in_order(stub):
    rng = np.random.default_rng(8)
    reqs = [blend_req(*random_poses(rng, int(rng.integers(2, 8))), method=m)
            for m in (pb.METHOD_DIB, pb.METHOD_DLB, pb.METHOD_LOG) for _ in range(20)]
    got = stub.BlendBatch(pb.BlendBatchRequest(requests=reqs), timeout=10).responses
    assert len(got) == len(reqs)
    for req, r in zip(reqs, got):
        one = stub.Blend(req, timeout=10)
        same_pose(msg_to_dq(r.pose), msg_to_dq(one.pose), atol=1e-12)
        assert (r.iterations, r.residual) == (one.iterations, one.residual)


@pytest.mark.parametrize("breaks, message", [
    (lambda reqs: reqs[3].poses[1].orientation.Clear(),
     "requests[3].poses[1].orientation: zero quaternion"),
    (lambda reqs: reqs[2].weights.extend([1.0, -1.0, 1.0]),
     "requests[2].weights[1]: negative weight -1"),
    (lambda reqs: reqs.clear(), "requests: empty request: no requests"),
])
def test_blend_batch_names_the_bad_request(stub, breaks, message):
    rng = np.random.default_rng(9)
    reqs = [blend_req(*random_poses(rng, 3)) for _ in range(5)]
    breaks(reqs)
    with pytest.raises(grpc.RpcError) as e:
        stub.BlendBatch(pb.BlendBatchRequest(requests=reqs), timeout=10)
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert e.value.details() == message


def test_bytes_that_are_not_a_blend_request_are_invalid_argument(server):
    # Blend decodes request bytes itself (service/csrc/wire.c, then protobuf as the fallback),
    # so undecodable bytes must come back as INVALID_ARGUMENT, not INTERNAL.
    with grpc.insecure_channel(server.target) as ch:
        raw = ch.unary_unary("/dqpose.v1.Blending/Blend", request_serializer=None,
                             response_deserializer=pb.BlendResponse.FromString)
        with pytest.raises(grpc.RpcError) as e:
            raw(b"\x0a\xff\xff\xff", timeout=10)   # a Pose whose length runs past the end
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert e.value.details() == "request: not a valid dqpose.v1.BlendRequest message"
        # and the same connection still serves a good request
        q, t = random_poses(np.random.default_rng(3), 3)
        ok = raw(blend_req(q, t).SerializeToString(), timeout=10)
        same_pose(msg_to_dq(ok.pose), dq.dib(dq.from_pose(q, t)))
        # BlendBatch and BlendStream take bytes too
        batch = ch.unary_unary("/dqpose.v1.Blending/BlendBatch", request_serializer=None,
                               response_deserializer=pb.BlendBatchResponse.FromString)
        with pytest.raises(grpc.RpcError) as e:
            batch(b"\x0a\x02\xff\xff", timeout=10)
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert e.value.details() == "request: not a valid dqpose.v1.BlendBatchRequest message"
        stream = ch.stream_stream("/dqpose.v1.Blending/BlendStream", request_serializer=None,
                                  response_deserializer=pb.BlendResponse.FromString)
        good = blend_req(q, t).SerializeToString()
        got = []
        with pytest.raises(grpc.RpcError) as e:
            for r in stream(iter([good, b"\x0a\xff\xff\xff", good]), timeout=10):
                got.append(r)
        assert len(got) == 1 and e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert e.value.details() == ("requests[1].request: not a valid dqpose.v1.BlendRequest "
                                     "message")
        assert len(batch(pb.BlendBatchRequest(requests=[blend_req(q, t)] * 3).SerializeToString(),
                         timeout=10).responses) == 3


# --------------------------------------------------------------------------- bad input

def _interp_req(times_k=(0.0, 1.0, 2.0), times=(0.5,), bad_key=None, interp=0):
    kf = [geo.StampedPose(time=s, pose=pose_msg([1, 0, 0, 0], [0, 0, 0])) for s in times_k]
    if bad_key is not None:
        kf[bad_key].pose.orientation.w = 0.0
    return pb.InterpolateRequest(keyframes=kf, times=list(times), interpolation=interp)


def _poses(n, fix=None):
    q = np.tile([1.0, 0, 0, 0], (n, 1))
    t = np.zeros((n, 3))
    for (i, what), v in (fix or {}).items():
        (q if what == "q" else t)[i] = v
    return q, t


NAN = float("nan")
BAD_INPUTS = [
    ("Blend", blend_req(*_poses(3, {(1, "t"): [0, NAN, 0]})),
     "poses[1].position: contains NaN or infinity"),
    ("Blend", blend_req(*_poses(3, {(2, "q"): [NAN, 0, 0, 0]})),
     "poses[2].orientation: contains NaN or infinity"),
    ("Blend", blend_req(*_poses(4, {(3, "q"): [0, 0, 0, 0]})),
     "poses[3].orientation: zero quaternion"),
    ("Blend", blend_req(*_poses(2, {(0, "q"): [2, 0, 0, 0]})),
     "poses[0].orientation: quaternion norm 2 is not unit (off by 1, beyond the tolerance 0.001 "
     "within which it is normalised); if it is a rotation, divide it by its norm"),
    ("Blend", blend_req(*_poses(3), weights=[1, -1, 1]), "weights[1]: negative weight -1"),
    ("Blend", blend_req(*_poses(3), weights=[0, 0, 0]),
     "weights: all weights are zero (the weights need a positive sum)"),
    ("Blend", blend_req(*_poses(3), weights=[1, NAN, 1]), "weights[1]: contains NaN or infinity"),
    ("Blend", blend_req(*_poses(3), weights=[1, 2]),
     "weights: length 2 does not match the number of poses (3)"),
    ("Blend", pb.BlendRequest(), "poses: empty request: no poses"),
    ("Blend", blend_req(*_poses(MAX_POSES + 1)),
     f"poses: {MAX_POSES + 1} poses exceed the server limit of {MAX_POSES}"),
    ("Blend", blend_req(*_poses(3), method=pb.METHOD_SCLERP),
     "poses: sclerp blends exactly 2 poses, got 3"),
    ("Blend", blend_req(*_poses(2), method=42), "method: unknown Method value 42"),
    ("Blend", blend_req(*_poses(2), tolerance=-1.0), "tolerance: must be finite and >= 0"),
    ("Blend", blend_req(*_poses(2), tolerance=NAN), "tolerance: must be finite and >= 0"),
    ("Interpolate", _interp_req(times_k=(0.0, 1.0, 0.5)),
     "keyframes[2].time: 0.5 is not after the previous keyframe time 1.0"),
    ("Interpolate", _interp_req(times_k=(0.0, 1.0, 1.0)),
     "keyframes[2].time: 1.0 is not after the previous keyframe time 1.0"),
    ("Interpolate", _interp_req(times=(0.5, 2.5)),
     "times[1]: 2.5 is outside the keyframe range [0.0, 2.0]"),
    ("Interpolate", _interp_req(times=(NAN,)), "times[0]: contains NaN or infinity"),
    ("Interpolate", _interp_req(times_k=(-1e308, 1e308), times=(1e308,)),
     "keyframes[1].time: the span from the previous keyframe time -1e+308 to 1e+308 overflows"),
    ("Interpolate", _interp_req(times_k=(0.0,)), "keyframes: need at least 2 keyframes, got 1"),
    ("Interpolate", _interp_req(times=()), "times: empty request: no times"),
    ("Interpolate", pb.InterpolateRequest(), "keyframes: empty request: no keyframes"),
    ("Interpolate", _interp_req(bad_key=1), "keyframes[1].pose.orientation: zero quaternion"),
    ("Interpolate", _interp_req(interp=7), "interpolation: unknown Interpolation value 7"),
    ("Interpolate", _interp_req(times=np.linspace(0, 2, MAX_POSES + 1)),
     f"times: {MAX_POSES + 1} times exceed the server limit of {MAX_POSES}"),
]


@pytest.mark.parametrize("rpc, request_, message", BAD_INPUTS,
                         ids=[m.split(":")[0] + "-" + str(i)
                              for i, (_, _, m) in enumerate(BAD_INPUTS)])
def test_bad_input_is_invalid_argument_naming_the_field(stub, rpc, request_, message):
    with pytest.raises(grpc.RpcError) as e:
        getattr(stub, rpc)(request_, timeout=10)
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert e.value.details().startswith(message), e.value.details()


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


# --------------------------------------------------------------------------- health, reflection

def test_health_is_serving(server):
    with grpc.insecure_channel(server.target) as ch:
        h = health_pb2_grpc.HealthStub(ch)
        for name in ("", "dqpose.v1.Blending"):
            r = h.Check(health_pb2.HealthCheckRequest(service=name), timeout=5)
            assert r.status == health_pb2.HealthCheckResponse.SERVING


def test_reflection_lists_and_describes_the_services(server):
    with grpc.insecure_channel(server.target) as ch:
        db = ProtoReflectionDescriptorDatabase(ch)
        services = set(db.get_services())
        assert {"dqpose.v1.Blending", "grpc.health.v1.Health"} <= services
        fd = db.FindFileContainingSymbol("dqpose.v1.Blending")
        assert fd.package == "dqpose.v1"
        assert [m.name for m in fd.service[0].method] == ["Blend", "Interpolate", "BlendStream",
                                                          "BlendBatch"]
        # method symbols resolve too (ghz looks them up; the Python pool alone cannot)
        assert db.FindFileContainingSymbol("dqpose.v1.Blending.Blend").name == fd.name


def _grpcurl() -> str | None:
    """grpcurl from PATH or Go's bin dir, installed with `go install` when Go is present."""
    found = shutil.which("grpcurl")
    if found:
        return found
    go = shutil.which("go")
    if not go:
        return None
    gobin = subprocess.run([go, "env", "GOPATH"], capture_output=True, text=True).stdout.strip()
    exe = os.path.join(gobin, "bin", "grpcurl")
    if not os.path.exists(exe):
        try:
            subprocess.run([go, "install", "github.com/fullstorydev/grpcurl/cmd/grpcurl@v1.9.4"],
                           capture_output=True, timeout=600, check=True)
        except (subprocess.SubprocessError, OSError):
            return None
    return exe if os.path.exists(exe) else None


def test_grpcurl_lists_services_and_calls_blend_with_json(server):
    exe = _grpcurl()
    if exe is None:
        pytest.skip("grpcurl not installed and `go install github.com/fullstorydev/grpcurl/"
                    "cmd/grpcurl@v1.9.4` failed or Go is missing")
    out = subprocess.run([exe, "-plaintext", server.target, "list"], capture_output=True,
                         text=True, timeout=60, check=True).stdout.split()
    assert "dqpose.v1.Blending" in out and "grpc.health.v1.Health" in out
    body = {"poses": [{"position": {"x": 0.1}, "orientation": {"w": 1}},
                      {"position": {"x": 0.3}, "orientation": {"w": 1}}],
            "weights": [1, 1], "method": "METHOD_DLB"}
    res = subprocess.run([exe, "-plaintext", "-d", json.dumps(body), server.target,
                          "dqpose.v1.Blending/Blend"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["pose"]["position"]["x"] == pytest.approx(0.2)
    body["poses"][1]["orientation"] = {}
    res = subprocess.run([exe, "-plaintext", "-d", json.dumps(body), server.target,
                          "dqpose.v1.Blending/Blend"], capture_output=True, text=True, timeout=60)
    assert "InvalidArgument" in res.stderr and "poses[1].orientation: zero quaternion" in res.stderr


# --------------------------------------------------------------------------- security

def _blend_ok(channel, metadata=None):
    return pb_grpc.BlendingStub(channel).Blend(blend_req(*_poses(2)), timeout=5, metadata=metadata)


def _code(fn):
    try:
        fn()
    except grpc.RpcError as e:
        return e.code(), e.details()
    return grpc.StatusCode.OK, ""


def test_bearer_token_accepted_and_rejected():
    with ServerThread(token="s3cret-token") as s, grpc.insecure_channel(s.target) as ch:
        assert _blend_ok(ch, [("authorization", "Bearer s3cret-token")]).pose.orientation.w == 1.0
        code, details = _code(lambda: _blend_ok(ch))
        assert code == grpc.StatusCode.UNAUTHENTICATED and "missing bearer token" in details
        code, details = _code(lambda: _blend_ok(ch, [("authorization", "Bearer s3cret-tokeX")]))
        assert code == grpc.StatusCode.UNAUTHENTICATED
        assert details == "authorization: invalid bearer token"
        stream = pb_grpc.BlendingStub(ch).BlendStream(iter([blend_req(*_poses(2))]), timeout=5)
        assert _code(lambda: list(stream))[0] == grpc.StatusCode.UNAUTHENTICATED
        # health stays open for load balancers and HEALTHCHECK
        r = health_pb2_grpc.HealthStub(ch).Check(health_pb2.HealthCheckRequest(), timeout=5)
        assert r.status == health_pb2.HealthCheckResponse.SERVING


@pytest.fixture(scope="module")
def pki():
    return make_pki()


def test_tls_accepted_with_the_ca_and_rejected_without(pki):
    with ServerThread(tls_cert=pki["server_cert"], tls_key=pki["server_key"]) as s:
        creds = grpc.ssl_channel_credentials(pki["ca"])
        with grpc.secure_channel(s.target, creds) as ch:
            assert _blend_ok(ch).pose.orientation.w == 1.0
        with grpc.secure_channel(s.target, grpc.ssl_channel_credentials(pki["other_ca"])) as ch:
            assert _code(lambda: _blend_ok(ch))[0] == grpc.StatusCode.UNAVAILABLE
        with grpc.insecure_channel(s.target) as ch:  # plaintext against TLS
            assert _code(lambda: _blend_ok(ch))[0] == grpc.StatusCode.UNAVAILABLE


def test_mtls_needs_a_client_certificate_from_the_client_ca(pki):
    with ServerThread(tls_cert=pki["server_cert"], tls_key=pki["server_key"],
                      client_ca=pki["ca"]) as s:
        good = grpc.ssl_channel_credentials(pki["ca"], pki["client_key"], pki["client_cert"])
        with grpc.secure_channel(s.target, good) as ch:
            assert _blend_ok(ch).pose.orientation.w == 1.0
        for creds in (grpc.ssl_channel_credentials(pki["ca"]),
                      grpc.ssl_channel_credentials(pki["ca"], pki["other_client_key"],
                                                   pki["other_client_cert"])):
            with grpc.secure_channel(s.target, creds) as ch:
                assert _code(lambda: _blend_ok(ch))[0] == grpc.StatusCode.UNAVAILABLE


# --------------------------------------------------------------------------- lifecycle

def test_second_server_on_the_same_port_fails(server):
    import asyncio

    from dqpose.rpc.server import AddressInUse

    with pytest.raises(AddressInUse, match=f"^cannot listen on 127.0.0.1:{server.port}: address "
                                           f"already in use$") as e:
        asyncio.run(start(ServerConfig(port=server.port)))
    assert e.value.setting == "port"
    res = subprocess.run([sys.executable, "-m", "dqpose.cli", "serve", "--port", str(server.port)],
                         capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert res.returncode == 2
    # one line, ours (not gRPC core's bind log), naming the flag to change
    assert res.stderr == (f"dqpose serve: error: cannot listen on 127.0.0.1:{server.port}: "
                          f"address already in use; choose another --port\n")


def test_metrics_port_in_use_names_the_metrics_flag(server):
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        res = subprocess.run([sys.executable, "-m", "dqpose.cli", "serve", "--port", "0",
                              "--metrics-port", str(port)],
                             capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert res.returncode == 2
    assert res.stderr == (f"dqpose serve: error: cannot serve metrics on 127.0.0.1:{port}: "
                          f"address already in use; choose another --metrics-port\n")


def test_concurrent_clients_get_their_own_answers(server):
    errors = []

    def worker(seed):
        rng = np.random.default_rng(seed)
        with grpc.insecure_channel(server.target) as ch:
            s = pb_grpc.BlendingStub(ch)
            for _ in range(40):
                q, t = random_poses(rng, 5)
                try:
                    same_pose(msg_to_dq(s.Blend(blend_req(q, t), timeout=10).pose),
                              dq.dib(dq.from_pose(q, t)))
                except Exception as e:  # collected: assertion errors in threads are lost
                    errors.append(e)

    threads = [threading.Thread(target=worker, args=(i,)) for i in range(8)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert not errors, errors[:3]


def test_metrics_count_calls():
    with socket_free_port() as port, ServerThread(metrics_port=port) as s:
        with grpc.insecure_channel(s.target) as ch:
            _blend_ok(ch)
            _code(lambda: pb_grpc.BlendingStub(ch).Blend(pb.BlendRequest(), timeout=5))
        text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read().decode()
    assert re.search(r'dqpose_grpc_calls_total\{code="OK",rpc="Blend"\} 1\.0', text)
    assert re.search(r'dqpose_grpc_calls_total\{code="INVALID_ARGUMENT",rpc="Blend"\} 1\.0', text)
    assert 'dqpose_grpc_call_seconds_count{rpc="Blend"} 2.0' in text


class socket_free_port:
    def __enter__(self):
        import socket

        with socket.socket() as so:
            so.bind(("127.0.0.1", 0))
            return so.getsockname()[1]

    def __exit__(self, *exc):
        pass


def test_sigterm_drains_in_flight_calls_and_exits_zero():
    proc = subprocess.Popen([sys.executable, "-m", "dqpose.cli", "serve", "--port", "0",
                             "--grace", "20"], cwd=ROOT, stderr=subprocess.PIPE, text=True)
    try:
        first = json.loads(proc.stderr.readline())
        assert first["event"] == "serving"
        target = first["address"]
        with grpc.insecure_channel(target) as ch:
            stub = pb_grpc.BlendingStub(ch)
            requests: queue.Queue = queue.Queue()
            stream = stub.BlendStream(iter(requests.get, None), timeout=60)
            requests.put(blend_req(*_poses(2)))
            next(stream)
            watch = health_pb2_grpc.HealthStub(ch).Watch(health_pb2.HealthCheckRequest(),
                                                         timeout=60)
            assert next(watch).status == health_pb2.HealthCheckResponse.SERVING

            proc.send_signal(signal.SIGTERM)
            assert next(watch).status == health_pb2.HealthCheckResponse.NOT_SERVING
            watch.cancel()
            # the stream that was open before SIGTERM keeps working until the client ends it
            for _ in range(5):
                requests.put(blend_req(*_poses(3)))
                assert next(stream).pose.orientation.w == pytest.approx(1.0)
            requests.put(None)
            assert list(stream) == []
            # new calls are refused once the server drains
            assert _code(lambda: _blend_ok(ch))[0] == grpc.StatusCode.UNAVAILABLE
        assert proc.wait(timeout=30) == 0
        lines = [json.loads(x) for x in proc.stderr.read().splitlines() if x.startswith("{")]
        calls = [x for x in lines if "rpc" in x]
        assert any(x["rpc"] == "BlendStream" and x["code"] == "OK" and x["messages"] == 6
                   for x in calls), calls
        assert all(isinstance(x["ms"], float) for x in calls)
        assert lines[-1] == {"event": "stopped"}
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _call_lines(caplog) -> list[dict]:
    return [json.loads(line) for r in caplog.records if r.name == "dqpose.calls"
            for line in r.getMessage().splitlines()]


def test_calls_cut_when_the_grace_period_ends_are_logged_and_counted(caplog):
    # Streams still open when the grace period runs out are cancelled by gRPC; their handlers
    # record them as they unwind, which must happen before the last flush and before the
    # metrics close: every call that started gets exactly one line and one sample.
    from dqpose.fusion import Source
    from dqpose.rpc import fusion_convert
    from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb

    caplog.set_level(logging.INFO, logger="dqpose.calls")
    first = fpb.FuseStreamRequest(options=fusion_convert.options_msg(sources=[Source("cam")]))
    first.measurements.extend(fusion_convert.measurement_msgs(
        dq.from_pose([1.0, 0, 0, 0], [0.1, 0.2, 0.3])[None], np.eye(6)[None] * 1e-4,
        names=["cam"], bodies=["box"]))
    with socket_free_port() as port:
        s = ServerThread(metrics_port=port)
        with grpc.insecure_channel(s.target) as ch:
            blends: queue.Queue = queue.Queue()
            blend = pb_grpc.BlendingStub(ch).BlendStream(iter(blends.get, None), timeout=60)
            fuses: queue.Queue = queue.Queue()
            fuse = ch.stream_stream(
                "/dqpose.v1.Fusion/StreamFuse",
                request_serializer=fpb.FuseStreamRequest.SerializeToString,
                response_deserializer=fpb.FusedPose.FromString)(iter(fuses.get, None), timeout=60)
            for _ in range(3):
                blends.put(blend_req(*_poses(2)))
                next(blend)
            fuses.put(first)
            assert next(fuse).HasField("pose")
            s.stop(grace=0.2)               # both streams are still open
            blends.put(None)
            fuses.put(None)
        metrics = s.running.metrics
    calls = sorted((c["rpc"], c["code"], c["messages"]) for c in _call_lines(caplog))
    assert calls == [("BlendStream", "CANCELLED", 3), ("StreamFuse", "CANCELLED", 1)], calls
    from prometheus_client import generate_latest
    text = generate_latest(metrics._registry).decode()
    for rpc in ("BlendStream", "StreamFuse"):
        assert re.search(rf'dqpose_grpc_calls_total\{{code="CANCELLED",rpc="{rpc}"\}} 1\.0',
                         text), text


def test_blend_stream_cancelled_mid_way_leaves_the_server_serving(stub):
    # The server reads ahead of its replies; a client that leaves with requests still unread
    # must end the reading task too, and the next stream must see only its own replies.
    rng = np.random.default_rng(21)
    reqs = [blend_req(*random_poses(rng, 4)) for _ in range(300)]
    call = stub.BlendStream(iter(reqs), timeout=10)
    next(call)
    call.cancel()
    with pytest.raises(grpc.RpcError) as e:
        for _ in call:
            pass
    assert e.value.code() == grpc.StatusCode.CANCELLED
    fresh = [blend_req(*random_poses(rng, 3), method=pb.METHOD_DLB) for _ in range(20)]
    got = list(stub.BlendStream(iter(fresh), timeout=10))
    assert len(got) == 20
    for req, r in zip(fresh, got):
        same_pose(msg_to_dq(r.pose), msg_to_dq(stub.Blend(req, timeout=10).pose), atol=1e-12)


# --------------------------------------------------------------------------- shutdown

def _serve(*flags) -> tuple[subprocess.Popen, str]:
    """``dqpose serve --port 0 FLAGS`` in its own process; (process, address) once it serves."""
    proc = subprocess.Popen([sys.executable, "-m", "dqpose.cli", "serve", "--port", "0", *flags],
                            cwd=ROOT, stderr=subprocess.PIPE, text=True)
    line = proc.stderr.readline()
    try:
        first = json.loads(line)
    except ValueError:
        proc.kill()
        raise AssertionError(line + proc.stderr.read()) from None
    assert first["event"] == "serving", first
    return proc, first["address"]


def _log_after(proc) -> list[dict]:
    """The JSON lines the server logs until it exits (it must exit with 0)."""
    assert proc.wait(timeout=60) == 0
    return [json.loads(x) for x in proc.stderr.read().splitlines() if x.startswith("{")]


@pytest.mark.parametrize("run", range(3))
def test_calls_arriving_after_sigterm_are_unavailable_never_cancelled(run):
    # UNAVAILABLE is what retry policies retry (on another server where there is one);
    # CANCELLED is not retried. A call may still be served if it reaches the server before the
    # signal does; from the first refusal on, every call is refused, the same way.
    proc, target = _serve()
    try:
        with grpc.insecure_channel(target) as ch:
            assert _code(lambda: _blend_ok(ch))[0] == grpc.StatusCode.OK
            proc.send_signal(signal.SIGTERM)
            codes = []
            while not codes or codes[-1] == grpc.StatusCode.OK:
                codes.append(_code(lambda: _blend_ok(ch))[0])
                assert len(codes) < 1000, "still served long after SIGTERM"
            assert codes[-1] == grpc.StatusCode.UNAVAILABLE, codes[-1]
            for _ in range(5):
                code, details = _code(lambda: _blend_ok(ch))
                assert code == grpc.StatusCode.UNAVAILABLE, code
                assert details == "server is shutting down", details
        lines = _log_after(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    blends = [x["code"] for x in lines if x.get("rpc") == "Blend"]
    # every call answered is logged once, with the code its client got
    assert blends == ["OK"] + [c.name for c in codes] + ["UNAVAILABLE"] * 5, blends


def test_health_says_not_serving_for_the_drain_delay_before_the_listener_closes():
    proc, target = _serve("--drain", "5")
    try:
        with grpc.insecure_channel(target) as ch:
            health = health_pb2_grpc.HealthStub(ch)

            def check():
                return health.Check(health_pb2.HealthCheckRequest(), timeout=5).status

            assert check() == health_pb2.HealthCheckResponse.SERVING
            proc.send_signal(signal.SIGTERM)
            status = check()
            while status == health_pb2.HealthCheckResponse.SERVING:
                status = check()
            # a load balancer polling health sees NOT_SERVING, not a closed port
            assert status == health_pb2.HealthCheckResponse.NOT_SERVING
            assert _code(lambda: _blend_ok(ch))[0] == grpc.StatusCode.UNAVAILABLE
            assert proc.poll() is None
        lines = _log_after(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert {"event": "shutting_down", "drain_s": 5.0, "grace_s": 10.0} in lines


def test_an_open_health_watch_ends_at_shutdown_and_does_not_hold_the_process():
    # A grace period of ten minutes: the process ends long before it only if the watch ends.
    proc, target = _serve("--grace", "600", "--drain", "0.2")
    try:
        with grpc.insecure_channel(target) as ch:
            watch = health_pb2_grpc.HealthStub(ch).Watch(health_pb2.HealthCheckRequest(),
                                                         timeout=60)
            assert next(watch).status == health_pb2.HealthCheckResponse.SERVING
            proc.send_signal(signal.SIGTERM)
            assert next(watch).status == health_pb2.HealthCheckResponse.NOT_SERVING
            assert list(watch) == []        # ended by the server, with OK
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


# --------------------------------------------------------------------------- start options

@pytest.mark.parametrize("field, value, message", [
    ("port", 116686, "port: must be within 0..65535, got 116686"),
    ("port", -1, "port: must be within 0..65535, got -1"),
    ("port", 5.5, "port: must be an integer, got 5.5"),
    ("metrics_port", 0, "metrics_port: must be within 1..65535, got 0"),
    ("max_message_bytes", -1, "max_message_bytes: must be within 1..2147483647, got -1"),
    ("max_message_bytes", 2**31, "max_message_bytes: must be within 1..2147483647, got 2147483648"),
    ("max_poses", 0, "max_poses: must be within 1..2147483647, got 0"),
    ("max_poses", -5, "max_poses: must be within 1..2147483647, got -5"),
    ("grace_s", -1.0, "grace_s: must be a finite number of seconds >= 0, got -1"),
    ("grace_s", math.nan, "grace_s: must be a finite number of seconds >= 0, got nan"),
    ("drain_s", -0.5, "drain_s: must be a finite number of seconds >= 0, got -0.5"),
    ("keepalive_s", 0.0, "keepalive_s: must be within 0.001..2147483 seconds, got 0"),
    ("keepalive_s", math.inf, "keepalive_s: must be within 0.001..2147483 seconds, got inf"),
])
def test_start_options_out_of_range_are_a_value_error_naming_the_field(field, value, message):
    import asyncio

    with pytest.raises(ValueError) as e:
        ServerConfig(**{"port": 0, field: value})
    assert str(e.value) == message
    cfg = ServerConfig(port=0)
    setattr(cfg, field, value)          # changed after construction: start() checks again
    with pytest.raises(ValueError) as e:
        asyncio.run(start(cfg))
    assert str(e.value) == message


def _bad_pem(pki) -> list[tuple[dict, str]]:
    """(ServerConfig PEM fields, the message) for a bad certificate, a bad or mismatched key
    and a garbage client CA."""
    from cryptography.hazmat.primitives import serialization

    cert, key = pki["server_cert"], pki["server_key"]
    broken = cert[:100] + cert[-40:]          # PEM armour around a broken body
    encrypted = serialization.load_pem_private_key(key, None).private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
        serialization.BestAvailableEncryption(b"secret"))
    return [
        (dict(tls_cert=b"not a certificate", tls_key=key),
         "tls_cert: no PEM certificate in it"),
        (dict(tls_cert=broken, tls_key=key), "tls_cert: no PEM certificate in it"),
        (dict(tls_cert=key, tls_key=key), "tls_cert: no PEM certificate in it"),
        (dict(tls_cert=cert, tls_key=b"garbage"), "tls_key: no PEM private key in it"),
        (dict(tls_cert=cert, tls_key=pki["client_key"]),
         "tls_key: the private key does not match the certificate"),
        # gRPC cannot use it; OpenSSL would ask for the password on the terminal
        (dict(tls_cert=cert, tls_key=encrypted),
         "tls_key: encrypted private keys are not supported"),
        (dict(tls_cert=cert, tls_key=key, client_ca=b"garbage"),
         "client_ca: no PEM certificate in it"),
        (dict(tls_cert=cert, tls_key=key, client_ca="\u00e9t\u00e9".encode()),
         "client_ca: no PEM certificate in it"),
    ]


def test_bad_certificates_keys_and_client_cas_are_named_before_binding(pki):
    import asyncio

    for fields, message in _bad_pem(pki):
        with pytest.raises(ValueError) as e:
            asyncio.run(start(ServerConfig(port=0, **fields)))
        assert str(e.value) == message, fields


def test_serve_names_the_bad_pem_file_and_the_problem(pki, tmp_path):
    for i, (fields, message) in enumerate(_bad_pem(pki)):
        args = []
        for field, data in fields.items():
            path = tmp_path / f"{i}-{field}.pem"
            path.write_bytes(data)
            args += ["--" + field.replace("_", "-"), str(path)]
        setting, problem = message.split(": ", 1)
        flag = "--" + setting.replace("_", "-")
        res = subprocess.run([sys.executable, "-m", "dqpose.cli", "serve", "--port", "0", *args],
                             capture_output=True, text=True, timeout=30, cwd=ROOT)
        assert res.returncode == 2, res.stderr
        assert res.stderr == (f"dqpose serve: error: {flag} {tmp_path}/{i}-{setting}.pem: "
                              f"{problem}\n")
