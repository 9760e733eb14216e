"""StreamFuse's C path (service/csrc/wire.c dq_wire_fuse_stream through
dqpose.rpc.wire.fuse_stream_from_wire and Fusion.stream_step_wire) against the protobuf path
it replaces: on generated, damaged and re-encoded requests a stream fed bytes answers exactly
what a stream fed parsed messages answers (fused poses, error entries and their texts, the
measurements in each window); the decoder reads what protobuf reads and refuses (None) what it
refuses or does not handle."""
from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from google.protobuf.message import DecodeError
from hypothesis import given, settings
from hypothesis import strategies as st

from dqpose import dq, fusion
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as pb
from dqpose.rpc.fusion import Fusion
from dqpose.rpc.fusion_convert import measurement_msgs, measurements_to_arrays, options_msg
from dqpose.rpc.server import ServerConfig
from dqpose.rpc.varint import varint
from dqpose.rpc.wire import fuse_stream_from_wire
from tests.rpc._mutate import damaged
from tests.rpc.test_wire import PADS, _key, reencode

SOURCES = [fusion.Source("cam", latency=0.03), fusion.Source("arm", latency=0.004)]
NESTED = {"stream": {3: "measurement"}, "measurement": {4: "pose"},
          "pose": {1: None, 2: None}}
EDGES = [0.0, -0.0, float("nan"), float("inf"), -1.0, 1e-320, 2.0]


def spd(rng):
    A = rng.normal(size=(6, 6))
    return A @ A.T * 1e-4 + np.eye(6) * 1e-6


@st.composite
def measurement(draw, t):
    """Mostly valid; the rest on the edges of every rule both paths apply."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    tol = dq.UNIT_TOL
    q *= 1 + draw(st.sampled_from([0.0] * 5 + [0.99 * tol, -0.99 * tol, 1.01 * tol, -1.0, 1e300]))
    T = np.array(draw(st.sampled_from([[1.0, 0, 0, 0]] + [q.tolist()] * 4 +
                                      [[0.0] * 4, [float("nan"), 0, 0, 0]])))
    pose = np.concatenate([T, [0.0] * 4])
    # math.hypot scales, so the 1e300 edge cannot overflow the norm
    p = dq.from_pose(T, [0.0, 0, 0]) if np.all(np.isfinite(T)) and abs(
        math.hypot(*T) - 1) <= tol else None
    kind = draw(st.sampled_from(["cov", "cov", "cov", "none", "weight", "asym", "notpd", "nan",
                                 "count", "both", "edge_asym"]))
    cov, weight = spd(rng), None
    if kind == "none":
        cov = None
    elif kind == "weight":
        cov, weight = None, draw(st.sampled_from(EDGES))
    elif kind == "asym":
        cov[0, 1] += 1e-3
    elif kind == "edge_asym":        # just inside and just outside the 1e-9 tolerance
        cov[2, 4] += np.abs(cov).max() * draw(st.sampled_from([0.9e-9, 1.1e-9]))
    elif kind == "notpd":
        cov[3, 3] = -cov[3, 3]
    elif kind == "nan":
        cov[5, 0] = float("nan")
    msg = measurement_msgs((p if p is not None else pose)[None],
                           None if cov is None else cov[None],
                           None if weight is None else [weight],
                           names=[draw(st.sampled_from(["cam", "cam", "arm", "", "cam3"]))],
                           bodies=[draw(st.sampled_from(["a", "a", "b", "", "c"]))],
                           times=[draw(st.sampled_from([t, t, t, t - 1.0, float("nan")]))])[0]
    if p is None:                    # the pose as given, not as measurement_msgs would fix it
        msg.pose.orientation.w, msg.pose.orientation.x, msg.pose.orientation.y, \
            msg.pose.orientation.z = T.tolist()
    if kind == "count":
        del msg.covariance[-1]
    elif kind == "both":
        msg.weight = 2.0
    return msg


@st.composite
def requests(draw, r):
    n = draw(st.integers(0, 5))
    return pb.FuseStreamRequest(measurements=[draw(measurement(0.01 * r + 0.002 * k))
                                              for k in range(n)])


def protobuf_step(f: Fusion, state, data: bytes, r: int, first_id: int):
    """The answers of the protobuf path alone."""
    try:
        request = pb.FuseStreamRequest.FromString(data)
    except DecodeError:
        return None, 0
    return f.stream_step(state, request, r, first_id), len(request.measurements)


def streams(rate: float, with_sources: bool):
    f = Fusion(ServerConfig(max_poses=6))
    first = pb.FuseStreamRequest(output_rate=rate, options=options_msg(
        sources=SOURCES if with_sources else (), window=0.1))
    return f, f.stream_options(first), f.stream_options(first)


def run_both(datas, rate=0.0, with_sources=True, decoded=None):
    """Feeds the same request bytes to a stream through each path; asserts equal answers."""
    f, a, b = streams(rate, with_sources)
    ida = idb = 0
    for r, data in enumerate(datas, start=1):
        want, na = protobuf_step(f, a, data, r, ida)
        got, nb = f.stream_step_wire(b, data, r, idb)
        if want is None:             # protobuf refuses the bytes: one error entry, none used
            assert len(got) == 1 and got[0].error.measurement == -1 and nb == 0
            assert "not a valid dqpose.v1.FuseStreamRequest" in got[0].error.details
            continue
        if decoded is not None:
            decoded.append(fuse_stream_from_wire(data) is not None)
        assert [m.SerializeToString() for m in got] == [m.SerializeToString() for m in want]
        assert na == nb
        ida += na
        idb += nb
    assert a.tracker.bodies == b.tracker.bodies
    for body in a.tracker.bodies:
        wa, wb = a.tracker.window_of(body), b.tracker.window_of(body)
        for x, y in zip(wa, wb):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


@settings(max_examples=150, deadline=None)
@given(st.lists(st.integers(0, 4), min_size=1, max_size=4), st.data(), st.booleans())
def test_stream_of_generated_requests_answers_as_the_protobuf_path(sizes, data, with_sources):
    reqs = [data.draw(requests(r)) for r in range(1, len(sizes) + 1)]
    run_both([q.SerializeToString() for q in reqs], with_sources=with_sources)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(0, 4), min_size=2, max_size=6), st.data())
def test_stream_with_output_ticks_answers_as_the_protobuf_path(sizes, data):
    reqs = [data.draw(requests(r)) for r in range(1, len(sizes) + 1)]
    run_both([q.SerializeToString() for q in reqs], rate=50.0)


@settings(max_examples=200, deadline=None)
@given(requests(1), st.data())
def test_damaged_requests_answer_as_the_protobuf_path(req, data):
    raw = damaged(req.SerializeToString(), data)
    run_both([raw], with_sources=data.draw(st.booleans()))


@settings(max_examples=150, deadline=None)
@given(requests(1), st.data())
def test_padded_varints_answer_as_the_protobuf_path(req, data):
    raw = reencode(req.SerializeToString(), "stream", lambda: data.draw(PADS), NESTED)
    run_both([raw])


def good(n, t0=0.0, bodies=("a", "b")):
    rng = np.random.default_rng(n)
    q = rng.normal(size=(n, 4))
    Z = dq.from_pose(q / np.linalg.norm(q, axis=1, keepdims=True), rng.normal(size=(n, 3)))
    return measurement_msgs(Z, [spd(rng) for _ in range(n)],
                            names=[("cam", "arm")[k % 2] for k in range(n)],
                            bodies=[bodies[k % len(bodies)] for k in range(n)],
                            times=t0 + 0.001 * np.arange(n))


def test_plain_requests_take_the_c_path_and_agree():
    datas = [pb.FuseStreamRequest(measurements=good(4, 0.01 * r)).SerializeToString()
             for r in range(1, 6)]
    decoded: list = []
    run_both(datas, decoded=decoded)
    assert decoded == [True] * 5
    w = fuse_stream_from_wire(datas[0])
    req = pb.FuseStreamRequest.FromString(datas[0])
    m = measurements_to_arrays(req.measurements)
    np.testing.assert_array_equal(w.poses, m.poses)
    np.testing.assert_array_equal(w.times, m.times)
    np.testing.assert_array_equal(w.covariances, 0.5 * (m.covariances +
                                                         np.swapaxes(m.covariances, 1, 2)))
    assert w.bodies == m.bodies and w.sources == m.sources and not w.codes.any()


def test_what_the_c_path_leaves_to_protobuf():
    plain = pb.FuseStreamRequest(measurements=good(2))
    assert fuse_stream_from_wire(plain.SerializeToString()) is not None
    others = [pb.FuseStreamRequest(measurements=good(2), output_rate=1.0),
              pb.FuseStreamRequest(measurements=good(2), options=pb.FusionOptions()),
              pb.FuseStreamRequest(measurements=good(2, bodies=("caf\u00e9",)))]
    datas = [o.SerializeToString() for o in others]
    # an unknown field in a measurement, and at the request's level
    m = good(1)[0].SerializeToString() + _key(9, 1) + struct.pack("<d", 1.0)
    datas += [_key(3, 2) + varint(len(m)) + m,
              plain.SerializeToString() + _key(7, 0) + b"\x01"]
    # a covariance on the edge of positive definite: LAPACK decides, not the margin
    c = np.diag([1.0, 1, 1, 1, 1, 1e-12]) * 1e-4
    c[4, 5] = c[5, 4] = np.sqrt(1e-4 * 1e-16) * (1 - 1e-12)
    datas.append(pb.FuseStreamRequest(measurements=measurement_msgs(
        np.array([[1.0, 0, 0, 0, 0, 0, 0, 0]]), c[None], names=["cam"], bodies=["a"],
        times=[0.0])).SerializeToString())
    for data in datas:
        assert fuse_stream_from_wire(data) is None
    run_both(datas)


def test_refused_measurements_are_named_as_the_protobuf_path_names_them():
    ms = good(6)
    ms[0].time = float("nan")
    del ms[1].covariance[:]
    ms[1].weight = -1.0
    ms[2].body = ""
    ms[3].covariance[1] += 1.0
    ms[4].pose.orientation.w = 3.0
    ms[5].source = "cam3"
    data = pb.FuseStreamRequest(measurements=ms).SerializeToString()
    w = fuse_stream_from_wire(data)
    assert w is not None
    assert w.codes.tolist() == [1, 4, 6, 8, 5, 0]       # wire.h DQ_MEAS_*
    decoded: list = []
    run_both([data], decoded=decoded)
    assert decoded == [True]
    f, _, state = streams(0.0, True)
    out, n = f.stream_step_wire(state, data, 1, 0)
    details = [a.error.details for a in out if a.HasField("error")]
    assert n == 6 and details == [
        "requests[1].measurements[0].time: must be finite, got nan",
        "requests[1].measurements[1].weight: must be positive and finite (0 means 1), got -1.0",
        "requests[1].measurements[2].body: empty (every measurement names its body)",
        pytest.approx(details[3]),
        details[4],
        "requests[1].measurements[5].source: 'cam3' is not among options.sources (cam, arm)"]
    assert details[3].startswith("requests[1].measurements[3].covariance: not symmetric")
    assert details[4].startswith("requests[1].measurements[4].pose.orientation: quaternion norm")
