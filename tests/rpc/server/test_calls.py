"""Every Blending RPC through the generated stubs against a real server, and bad input answered
INVALID_ARGUMENT naming the field."""
from __future__ import annotations

import grpc
import numpy as np
import pytest

from dqpose import dq
from dqpose.interpolate import interpolate
from dqpose.rpc._proto.dqpose.v1 import blending_pb2 as pb
from dqpose.rpc._proto.dqpose.v1 import geometry_pb2 as geo
from tests.rpc.server._blending import (
    MAX_POSES,
    NAN,
    _poses,
    blend_req,
    msg_to_dq,
    pose_msg,
    random_poses,
    same_pose,
)

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
