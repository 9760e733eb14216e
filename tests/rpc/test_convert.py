"""service.rpc.convert: protobuf messages <-> arrays, and errors renamed to proto field paths."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service import dq
from service.rpc.convert import (METHOD_ENUMS, METHOD_NAMES, FieldError, arrays_to_stamped,
                                 blend_request_wire, dq_to_pose, dqs_to_poses, pose_msgs,
                                 poses_to_dqs, stamped_to_arrays)
from service.rpc._proto.dqpose.v1 import blending_pb2 as pb
from service.rpc._proto.dqpose.v1 import geometry_pb2 as geo


def _pose(q, t) -> geo.Pose:
    return geo.Pose(position=geo.Vector3(x=t[0], y=t[1], z=t[2]),
                    orientation=geo.Quaternion(w=q[0], x=q[1], y=q[2], z=q[3]))


def test_poses_round_trip_through_messages(make_dqs):
    dqs = make_dqs(7, scale=2.0)
    back = poses_to_dqs(dqs_to_poses(dqs), "poses")
    # q and -q are one pose; compare with the sign of the scalar part aligned
    s = np.sign(np.sum(back[:, :4] * dqs[:, :4], axis=1))[:, None]
    np.testing.assert_allclose(back, s * dqs, atol=1e-15)
    one = dq_to_pose(dqs[2])
    np.testing.assert_allclose(poses_to_dqs([one], "poses")[0] * s[2], dqs[2], atol=1e-15)


def test_stamped_round_trip(make_dqs):
    dqs = make_dqs(5)
    times = np.array([0.0, 0.1, 0.25, 1.0, 2.5])
    t2, d2 = stamped_to_arrays(arrays_to_stamped(times, dqs))
    np.testing.assert_array_equal(t2, times)
    s = np.sign(np.sum(d2[:, :4] * dqs[:, :4], axis=1))[:, None]
    np.testing.assert_allclose(d2, s * dqs, atol=1e-15)


@pytest.mark.parametrize("q,t,message", [
    ((0, 0, 0, 0), (0, 0, 0), r"^poses\[1\]\.orientation: zero quaternion"),
    ((1.1, 0, 0, 0), (0, 0, 0), r"^poses\[1\]\.orientation: quaternion norm 1.1 is not unit"),
    ((np.nan, 0, 0, 0), (0, 0, 0), r"^poses\[1\]\.orientation: contains NaN or infinity"),
    ((1, 0, 0, 0), (0, np.inf, 0), r"^poses\[1\]\.position: contains NaN or infinity"),
])
def test_bad_poses_name_the_field(q, t, message):
    poses = [_pose((1, 0, 0, 0), (0, 0, 0)), _pose(q, t)]
    with pytest.raises(FieldError, match=message):
        poses_to_dqs(poses, "poses")


def test_keyframe_errors_name_the_pose_inside_the_stamped_message():
    stamped = [geo.StampedPose(time=0.0, pose=_pose((1, 0, 0, 0), (0, 0, 0))),
               geo.StampedPose(time=1.0, pose=_pose((0, 0, 0, 0), (0, 0, 0)))]
    with pytest.raises(FieldError, match=r"^keyframes\[1\]\.pose\.orientation: zero quaternion"):
        stamped_to_arrays(stamped)


def test_an_empty_message_is_the_identity_only_if_the_quaternion_is_set():
    # proto3 defaults every field to 0: a Pose with no orientation is a zero quaternion, which
    # must be refused rather than silently read as some rotation
    with pytest.raises(FieldError, match="zero quaternion"):
        poses_to_dqs([geo.Pose()], "poses")
    ident = poses_to_dqs([geo.Pose(orientation=geo.Quaternion(w=1))], "poses")
    np.testing.assert_array_equal(ident[0], dq.identity())


# ---- the client's request encoder: wire bytes from arrays, without message objects

_doubles = st.one_of(st.just(0.0), st.just(-0.0), st.floats(allow_nan=True, allow_infinity=True))


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


def test_blend_request_wire_refuses_out_of_range_iterations():
    q, t = np.array([[1.0, 0, 0, 0]]), np.zeros((1, 3))
    for bad in (-1, 2**32, 2.5):
        with pytest.raises(ValueError, match="max_iterations: must be a whole number"):
            blend_request_wire(q, t, max_iterations=bad)


def test_the_method_table_is_the_proto_enum():
    # by name and by value: the C fast path passes a request's Method value to the core as is
    proto = {name: value for name, value in pb.Method.items() if name != "METHOD_UNSPECIFIED"}
    assert proto == {f"METHOD_{name.upper()}": m.code for name, m in dq.METHODS.items()}
    assert METHOD_NAMES == {pb.METHOD_UNSPECIFIED: "dib", **{m.code: n for n, m in dq.METHODS.items()}}
    assert METHOD_ENUMS == {n: m.code for n, m in dq.METHODS.items()}
