"""dqpose.rpc.wire's encoders and answer readers: the wire bytes the client writes from arrays are
what protobuf would write, and answers read without message objects are the parser's values."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dqpose.rpc._proto.dqpose.v1 import blending_pb2 as pb
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb
from dqpose.rpc._proto.dqpose.v1 import geometry_pb2 as geo
from dqpose.rpc.fusion_convert import measurement_msgs
from dqpose.rpc.geometry import (
    pose_msgs,
)
from dqpose.rpc.wire import (
    blend_batch_items_wire,
    blend_request_wire,
    blend_responses_from_wire,
    interpolate_request_wire,
    measurements_wire,
    publish_request_wire,
    stamped_poses_wire,
)

# ---- the client's request encoder: wire bytes from arrays, without message objects

_doubles = st.one_of(st.just(0.0), st.just(-0.0), st.floats(allow_nan=True, allow_infinity=True))


def _rows(data, n, width):
    return np.array(data.draw(st.lists(st.lists(_doubles, min_size=width, max_size=width),
                                       min_size=n, max_size=n))).reshape(n, width)


@settings(max_examples=200)
@given(n=st.integers(0, 5), data=st.data())
def test_blend_request_wire_is_what_protobuf_would_send(n, data):
    q = np.array(data.draw(st.lists(st.lists(_doubles, min_size=4, max_size=4), min_size=n,
                                    max_size=n))).reshape(n, 4)
    t = np.array(data.draw(st.lists(st.lists(_doubles, min_size=3, max_size=3), min_size=n,
                                    max_size=n))).reshape(n, 3)
    w = data.draw(st.lists(_doubles, max_size=6))
    method = data.draw(st.sampled_from([0, 1, 3, 6, -1, 2**31 - 1]))
    tol = data.draw(_doubles)
    max_iter = data.draw(st.sampled_from([0, 1, 127, 128, 2**32 - 1]))
    want = pb.BlendRequest(poses=pose_msgs(q, t), weights=w, method=method, tolerance=tol,
                           max_iterations=max_iter)
    got = pb.BlendRequest.FromString(blend_request_wire(q, t, w, method, tol, max_iter))
    # bit for bit, NaN payloads and the sign of zero included
    assert got.SerializeToString() == want.SerializeToString()


_names = st.text(st.characters(codec="utf-8"), max_size=3) | st.sampled_from(["", "x" * 200])


@settings(max_examples=200)
@given(n=st.integers(0, 4), kind=st.sampled_from(["covariances", "weights", None]),
       data=st.data())
def test_measurements_wire_is_what_protobuf_would_send(n, kind, data):
    """StreamFuse's client encoder writes the bytes of measurement_msgs' messages serialised:
    every field, zeros omitted as protobuf omits them, names of any length and alphabet."""
    dqs = np.array(data.draw(st.lists(st.lists(_doubles, min_size=8, max_size=8), min_size=n,
                                      max_size=n))).reshape(n, 8)
    values = np.array(data.draw(st.lists(_doubles, min_size=36 * n, max_size=36 * n)))
    kw = {"covariances": values.reshape(n, 6, 6)} if kind == "covariances" else (
        {"weights": values[:n]} if kind == "weights" else {})
    names = data.draw(st.none() | st.lists(_names, min_size=n, max_size=n))
    bodies = data.draw(st.none() | st.lists(_names, min_size=n, max_size=n))
    times = data.draw(st.none() | st.lists(_doubles, min_size=n, max_size=n))
    with np.errstate(all="ignore"):
        got = measurements_wire(dqs, names=names, bodies=bodies, times=times, **kw)
        want = fpb.FuseStreamRequest(measurements=measurement_msgs(
            dqs, names=names, bodies=bodies, times=times, **kw)).SerializeToString()
    assert got == want


@settings(max_examples=200)
@given(n=st.integers(0, 3), covariances=st.booleans(), producer=_names,
       sequence=st.sampled_from([0, 1, 300, 2**64 - 1]), data=st.data())
def test_publish_request_wire_is_what_protobuf_would_send(n, covariances, producer, sequence,
                                                         data):
    """World.Publish's client encoder: the PublishRequest's bytes, its measurements as field 1,
    then the producer and the sequence (each left out when empty, as protobuf does)."""
    from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb
    from dqpose.rpc.client import Batch
    dqs = np.array(data.draw(st.lists(st.lists(_doubles, min_size=8, max_size=8), min_size=n,
                                      max_size=n))).reshape(n, 8)
    values = np.array(data.draw(st.lists(_doubles, min_size=36 * n, max_size=36 * n)))
    batch = Batch(dqs, values.reshape(n, 6, 6) if covariances else None, None,
                  data.draw(st.lists(_names, min_size=n, max_size=n)),
                  data.draw(st.lists(_names, min_size=n, max_size=n)),
                  data.draw(st.lists(_doubles, min_size=n, max_size=n)))
    with np.errstate(all="ignore"):
        got = publish_request_wire(batch, producer, sequence)
        want = wpb.PublishRequest(measurements=measurement_msgs(*batch), producer=producer,
                                  sequence=sequence).SerializeToString()
    assert got == want


def test_measurements_wire_names_a_name_that_is_not_a_string():
    with pytest.raises(ValueError, match=r"^bodies\[1\]: expected a string, got int"):
        measurements_wire(np.tile([1.0, 0, 0, 0, 0, 0, 0, 0], (2, 1)), bodies=["a", 7])


def test_blend_request_wire_refuses_out_of_range_iterations():
    q, t = np.array([[1.0, 0, 0, 0]]), np.zeros((1, 3))
    for bad in (-1, 2**32, 2.5):
        with pytest.raises(ValueError, match="max_iterations: must be a whole number"):
            blend_request_wire(q, t, max_iterations=bad)


@settings(max_examples=150)
@given(data=st.data())
def test_blend_batch_items_are_what_protobuf_would_send(data):
    # sets of different sizes, some with weights (of any length: the server judges them)
    counts = np.array(data.draw(st.lists(st.integers(0, 4), max_size=6)), dtype=np.int64)
    w_counts = np.array([data.draw(st.integers(0, 4)) for _ in counts], dtype=np.int64)
    q, t = _rows(data, int(counts.sum()), 4), _rows(data, int(counts.sum()), 3)
    w = _rows(data, int(w_counts.sum()), 1).ravel()
    method = data.draw(st.sampled_from([0, 2, 6, -1]))
    tol = data.draw(_doubles)
    max_iter = data.draw(st.sampled_from([0, 3, 200, 2**32 - 1]))
    buf, offsets = blend_batch_items_wire(q, t, counts, w, w_counts, method, tol, max_iter)
    ps, ws = np.cumsum(np.r_[0, counts]), np.cumsum(np.r_[0, w_counts])
    want = [pb.BlendRequest(poses=pose_msgs(q[ps[i]:ps[i + 1]], t[ps[i]:ps[i + 1]]),
                            weights=w[ws[i]:ws[i + 1]], method=method, tolerance=tol,
                            max_iterations=max_iter) for i in range(len(counts))]
    got = pb.BlendBatchRequest.FromString(buf.tobytes())
    assert [r.SerializeToString() for r in got.requests] == [r.SerializeToString() for r in want]
    # every run of items is a batch of its own: what the client sends when it splits
    for i in range(len(counts)):
        one = pb.BlendBatchRequest.FromString(buf[offsets[i]:offsets[i + 1]].tobytes())
        assert [r.SerializeToString() for r in one.requests] == [want[i].SerializeToString()]


@settings(max_examples=100)
@given(n=st.integers(0, 4), data=st.data())
def test_interpolate_request_wire_is_what_protobuf_would_send(n, data):
    times_k, q, t = _rows(data, n, 1).ravel(), _rows(data, n, 4), _rows(data, n, 3)
    times = _rows(data, data.draw(st.integers(0, 5)), 1).ravel()
    mode = data.draw(st.sampled_from([0, 1, 2, -3]))
    want = pb.InterpolateRequest(keyframes=[geo.StampedPose(time=s, pose=p) for s, p in
                                            zip(times_k.tolist(), pose_msgs(q, t))],
                                 times=times, interpolation=mode)
    got = pb.InterpolateRequest.FromString(
        interpolate_request_wire(stamped_poses_wire(times_k, q, t), times, mode))
    assert got.SerializeToString() == want.SerializeToString()


def _answer(data, zeros):
    """A BlendResponse as the server may send it: any value may be zero (then left off)."""
    value = _doubles if zeros else st.floats(allow_nan=True).filter(lambda v: v != 0)
    r = pb.BlendResponse()
    p, o = r.pose.position, r.pose.orientation
    p.x, p.y, p.z = (data.draw(value) for _ in range(3))
    o.w, o.x, o.y, o.z = (data.draw(value) for _ in range(4))
    r.iterations = data.draw(st.sampled_from([0, 1, 27, 127, 128, 1000, 2**32 - 1]))
    r.residual = data.draw(value)
    return r


def _read(r):
    p, o = r.pose.position, r.pose.orientation
    return [o.w, o.x, o.y, o.z, p.x, p.y, p.z], r.iterations, r.residual


@settings(max_examples=150)
@given(m=st.integers(1, 6), data=st.data())
def test_blend_answers_read_without_messages_are_the_parsers_values(m, data):
    # one layout (every value present, the same iterations): what the server sends for a method
    uniform = [_answer(data, zeros=False) for _ in range(m)]
    for r in uniform[1:]:
        r.iterations = uniform[0].iterations
    mixed = [_answer(data, zeros=True) for _ in range(m)]
    for answers in (uniform, mixed):
        raw = pb.BlendBatchResponse(responses=answers).SerializeToString()
        got = blend_responses_from_wire(raw)
        if got is None:       # a layout it does not take (then the client parses with protobuf)
            assert answers is mixed
            continue
        want = [_read(r) for r in pb.BlendBatchResponse.FromString(raw).responses]
        # bit for bit: NaN payloads and the sign of zero included
        assert got[0].tobytes() == np.array([w[0] for w in want], "<f8").reshape(-1, 7).tobytes()
        assert got[1].tolist() == [w[1] for w in want]
        assert got[2].tobytes() == np.array([w[2] for w in want], "<f8").tobytes()


def test_blend_answers_of_one_layout_are_read_without_messages():
    r = pb.BlendResponse(pose=pose_msgs(np.array([[0.5, 0.5, 0.5, 0.5]]),
                                        np.array([[0.1, -0.2, 0.3]]))[0],
                         iterations=3, residual=1e-13)
    got = blend_responses_from_wire(pb.BlendBatchResponse(responses=[r] * 5).SerializeToString())
    assert got is not None
    np.testing.assert_array_equal(got[0], [[0.5, 0.5, 0.5, 0.5, 0.1, -0.2, 0.3]] * 5)
    assert got[1].tolist() == [3] * 5 and got[2].tolist() == [1e-13] * 5
    assert blend_responses_from_wire(b"") is not None
    assert blend_responses_from_wire(b"\x0a\x05junk!") is None
