"""dqpose.rpc.geometry and the vocabularies: poses and stamped poses <-> messages, errors renamed to
proto field paths, the enum tables against the domain's names and the proto, counts refused the
same everywhere."""
from __future__ import annotations

import numpy as np
import pytest

from dqpose import dq, handeye, trajectory
from dqpose.errors import FieldError
from dqpose.rpc._proto.dqpose.v1 import blending_pb2 as pb
from dqpose.rpc._proto.dqpose.v1 import geometry_pb2 as geo
from dqpose.rpc._proto.dqpose.v1 import handeye_pb2 as hpb
from dqpose.rpc.blending import INTERPOLATE_INTERPOLATION
from dqpose.rpc.blending_convert import METHOD_ENUMS, METHOD_NAMES
from dqpose.rpc.checks import check_count, over_count
from dqpose.rpc.geometry import (
    INTERPOLATION_ENUMS,
    arrays_to_stamped,
    dq_to_pose,
    dqs_to_poses,
    interpolation_named,
    poses_to_dqs,
    stamped_to_arrays,
)
from dqpose.rpc.handeye_convert import SETUP_ENUMS, SETUP_NAMES
from dqpose.rpc.trajectories_convert import PLAN_INTERPOLATION, plan_from_msg, plan_msg


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


def test_the_method_table_is_the_proto_enum():
    # by name and by value: the C fast path passes a request's Method value to the core as is
    proto = {name: value for name, value in pb.Method.items() if name != "METHOD_UNSPECIFIED"}
    assert proto == {f"METHOD_{name.upper()}": m.code for name, m in dq.METHODS.items()}
    assert METHOD_NAMES == {pb.METHOD_UNSPECIFIED: "dib",
                            **{m.code: n for n, m in dq.METHODS.items()}}
    assert METHOD_ENUMS == {n: m.code for n, m in dq.METHODS.items()}


def test_the_interpolation_and_setup_tables_are_the_domains_names_and_the_proto_enums():
    # one vocabulary: the domain's names, each a value of the proto's enum, and every value
    assert list(INTERPOLATION_ENUMS) == list(trajectory.INTERPOLATIONS)
    assert set(INTERPOLATION_ENUMS.values()) == set(geo.Interpolation.values()) - {0}
    assert list(SETUP_ENUMS) == list(handeye.SETUPS)
    assert set(SETUP_NAMES) == set(hpb.Setup.values()) - {hpb.SETUP_UNSPECIFIED}
    for name, code in INTERPOLATION_ENUMS.items():
        assert geo.Interpolation.Name(code) == f"INTERPOLATION_{name.upper()}"
        assert interpolation_named(code, "unused") == name
    with pytest.raises(FieldError, match=r"^plan\.interpolation: unknown Interpolation value 9$"):
        interpolation_named(9, "screw", "plan.interpolation")


def test_each_rpc_has_its_own_default_for_unspecified_interpolation():
    # the proto's comments: SCREW for Interpolate, TOOL_LINEAR for Plan (and Execute's plan)
    assert interpolation_named(geo.INTERPOLATION_UNSPECIFIED, INTERPOLATE_INTERPOLATION) == "screw"
    req = plan_msg([np.r_[1.0, np.zeros(7)], np.r_[1.0, np.zeros(6), 0.1]],
                   trajectory.Limits(1.0, 1.0, 1.0, 1.0), 100.0)
    req.interpolation = geo.INTERPOLATION_UNSPECIFIED
    assert plan_from_msg(req).interpolation == PLAN_INTERPOLATION == "tool_linear"


def test_a_count_over_the_limit_reads_the_same_wherever_it_is_refused():
    assert over_count("poses", 10, 10, "poses") is None
    assert over_count("poses", 11, 10, "poses") == \
        "poses: 11 poses exceed the server limit of 10 per request"
    assert over_count("pairs", 41, 40) == "pairs: 41 exceed the server limit of 40 per request"
    with pytest.raises(FieldError, match=r"^times: empty request: no times$"):
        check_count("times", 0, 10, "times", empty=True)
    check_count("times", 0, 10, "times")
    with pytest.raises(FieldError, match=r"^times: 11 times exceed the server limit of 10 per"):
        check_count("times", 11, 10, "times")
