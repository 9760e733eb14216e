"""service/csrc/wire.c (through service.messages.decode_blend_request): the C decoder of
BlendRequest bytes must agree with the protobuf parser on every message, and refuse (None) what
the parser refuses."""
from __future__ import annotations

import struct

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from service.messages import decode_blend_request
from service._proto.dqpose.v1 import blending_pb2 as pb
from service._proto.dqpose.v1 import geometry_pb2 as geo
from google.protobuf.message import DecodeError

# Zeros matter: proto3 leaves zero fields off the wire, which is what a fixed-layout reader
# would get wrong.
floats = st.one_of(st.just(0.0), st.just(-0.0), st.floats(allow_nan=True, allow_infinity=True),
                   st.floats(-2, 2))


@st.composite
def requests(draw):
    n = draw(st.integers(0, 6))
    poses = []
    for _ in range(n):
        p = geo.Pose()
        if draw(st.booleans()):
            p.position.x, p.position.y, p.position.z = (draw(floats) for _ in range(3))
        if draw(st.booleans()):
            o = p.orientation
            o.w, o.x, o.y, o.z = (draw(floats) for _ in range(4))
        poses.append(p)
    return pb.BlendRequest(
        poses=poses, weights=draw(st.lists(floats, max_size=6)),
        method=draw(st.sampled_from([0, 1, 2, 3, 6, 7, -1, 2**31 - 1])),
        tolerance=draw(floats), max_iterations=draw(st.integers(0, 2**32 - 1)))


def parsed(req: pb.BlendRequest):
    flat = np.array([(p.orientation.w, p.orientation.x, p.orientation.y, p.orientation.z,
                      p.position.x, p.position.y, p.position.z) for p in req.poses]).reshape(-1, 7)
    return flat, np.array(req.weights), req.method, req.tolerance, req.max_iterations


def assert_same(got, want):
    assert got is not None
    np.testing.assert_array_equal(got[0], want[0])   # NaN == NaN, and -0.0 kept bit for bit
    np.testing.assert_array_equal(np.signbit(got[0]), np.signbit(want[0]))
    np.testing.assert_array_equal(got[1], want[1])
    assert got[2] == want[2] and got[4] == want[4]
    assert got[3] == want[3] or (np.isnan(got[3]) and np.isnan(want[3]))


@given(requests())
def test_agrees_with_protobuf(req):
    data = req.SerializeToString()
    assert_same(decode_blend_request(data), parsed(pb.BlendRequest.FromString(data)))


def _key(field, wt):
    return bytes([field << 3 | wt])


def test_unpacked_weights_merged_poses_and_unknown_fields():
    a = pb.BlendRequest(poses=[geo.Pose(position=geo.Vector3(x=1.0))]).SerializeToString()
    # weights as unpacked fixed64 entries, a second Pose message for index 0 is a new pose, a
    # position field repeated inside one Pose merges, and unknown fields of every wire type
    pose = (_key(1, 2) + bytes([9]) + _key(1, 1) + struct.pack("<d", 2.0)
            + _key(1, 2) + bytes([9]) + _key(2, 1) + struct.pack("<d", 3.0))
    extra = (_key(2, 1) + struct.pack("<d", 0.5) + _key(2, 1) + struct.pack("<d", 0.25)
             + _key(1, 2) + bytes([len(pose)]) + pose
             + _key(9, 0) + b"\x96\x01" + _key(10, 5) + b"\0\0\0\0" + _key(11, 2) + b"\x02hi"
             + _key(12, 1) + b"\0" * 8)
    data = a + extra
    assert_same(decode_blend_request(data), parsed(pb.BlendRequest.FromString(data)))
    got = decode_blend_request(data)
    np.testing.assert_array_equal(got[0][1, 4:], [2.0, 3.0, 0.0])
    np.testing.assert_array_equal(got[1], [0.5, 0.25])


@settings(max_examples=300)
@given(requests(), st.data())
def test_damaged_bytes_are_refused_or_read_as_protobuf_reads_them(req, data):
    raw = bytearray(req.SerializeToString())
    if raw:
        for _ in range(data.draw(st.integers(1, 3))):
            i = data.draw(st.integers(0, len(raw) - 1))
            raw[i] = data.draw(st.integers(0, 255))
        raw = raw[:data.draw(st.integers(0, len(raw)))]
    raw = bytes(raw)
    try:
        want = parsed(pb.BlendRequest.FromString(raw))
    except DecodeError:
        assert decode_blend_request(raw) is None
        return
    got = decode_blend_request(raw)
    if got is not None:  # None is always safe: the server then uses protobuf's parser
        assert_same(got, want)
