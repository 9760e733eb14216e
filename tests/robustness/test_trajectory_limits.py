"""Plan and Smooth against the probe's requests: never INTERNAL for finite input, every refusal
naming the field it is about with readable numbers, and the samples a plan streams within the
server's limit."""
from __future__ import annotations

import grpc
import numpy as np
import pytest

from dqpose import dq, lie, trajectory
from dqpose.rpc import geometry, trajectories_convert
from dqpose.rpc._proto.dqpose.v1 import geometry_pb2 as geo
from dqpose.rpc._proto.dqpose.v1 import trajectories_pb2 as pb
from dqpose.rpc._proto.dqpose.v1 import trajectories_pb2_grpc as pb_grpc
from tests.robustness._served import code_of, served


@pytest.fixture(scope="module")
def server():
    with served() as s:
        yield s


LIMITS = trajectory.Limits(0.2, 1.0, 1.0, 2.0)
A, B = dq.from_pose([1.0, 0, 0, 0], [0, 0, 0]), dq.from_pose([1.0, 0, 0, 0], [0.1, 0.05, 0])
_T = np.linspace(0.0, 2.0, 40)
_PATH = lie.se3_exp(np.column_stack([np.outer(0.1 * np.sin(_T), np.ones(3)),
                                     np.outer(0.1 * np.cos(_T), np.ones(3))]))
#: a legal plan: three waypoints, the middle one blended, a start velocity
PLAN = trajectories_convert.plan_msg(
    [trajectory.Waypoint(_PATH[0]), trajectory.Waypoint(_PATH[20], 0.0, 0.01),
     trajectory.Waypoint(_PATH[39])],
    trajectory.Limits(0.2, 1.0, 1.0, 2.0, 10.0, 20.0), 100.0, start_velocity=np.zeros(6))


def plan(server, request):
    return code_of(lambda: list(pb_grpc.TrajectoriesStub(server.channel).Plan(request, timeout=60)))


def smooth(server, request):
    return code_of(lambda: pb_grpc.TrajectoriesStub(server.channel).Smooth(request, timeout=120))


def plan_request(waypoints=(A, B), **limits):
    request = trajectories_convert.plan_msg(list(waypoints), LIMITS, 100.0)
    for name, value in limits.items():
        setattr(request.limits, name, value)
    return request


def smooth_request(smoothing=1.0, **limits):
    t = np.linspace(0, 2, 50)
    P = lie.se3_exp(np.column_stack([np.outer(0.1 * np.sin(t), np.ones(3)),
                                     np.outer(0.1 * np.cos(t), np.ones(3))]))
    request = pb.SmoothRequest(poses=geometry.stamped_msgs(t, P),
                               limits=trajectories_convert.limits_msg(LIMITS), smoothing=smoothing)
    for name, value in limits.items():
        setattr(request.limits, name, value)
    return request


@pytest.mark.parametrize("name", ["max_linear_velocity", "max_linear_acceleration",
                                  "max_angular_velocity", "max_linear_jerk"])
def test_a_limit_of_5e_324_is_refused_naming_it(server, name):
    for call, request in ((plan, plan_request(**{name: 5e-324})),
                          (smooth, smooth_request(**{name: 5e-324}))):
        code, details = call(server, request)
        assert code == grpc.StatusCode.INVALID_ARGUMENT, (code, details)
        assert details.startswith(f"limits.{name}: 4.94066e-324 is outside [1e-09, 1e+09]"), \
            details


@pytest.mark.parametrize("smoothing", [1e300, 1e4])
def test_a_smoothing_too_large_is_refused_naming_it(server, smoothing):
    code, details = smooth(server, smooth_request(smoothing=smoothing))
    assert code == grpc.StatusCode.INVALID_ARGUMENT, (code, details)
    assert details.startswith(f"smoothing: {smoothing:g} is over 1000"), details


def test_a_waypoint_a_long_way_off_is_named_with_readable_numbers(server):
    far = dq.from_pose([1.0, 0, 0, 0], [1e30, 0, 0])
    code, details = plan(server, plan_request((A, far)))
    assert code == grpc.StatusCode.RESOURCE_EXHAUSTED, (code, details)
    assert details.startswith("waypoints[1]: the plan lasts 5e+30 s, 5e+30 s of it to this "
                              "waypoint (at limits.max_linear_velocity); at rate_hz 100 that is "
                              "5e+32 samples"), details
    assert "max_plan_samples" in details and "--max-plan-samples" in details


@pytest.mark.parametrize("which, value", [("start_angular_velocity", float("nan")),
                                          ("start_angular_velocity", 1e300),
                                          ("start_linear_velocity", 1e300)])
def test_a_bad_start_velocity_names_its_own_field(server, which, value):
    request = plan_request()
    getattr(request, which).CopyFrom(geo.Vector3(x=value))
    code, details = plan(server, request)
    assert code in (grpc.StatusCode.INVALID_ARGUMENT, grpc.StatusCode.FAILED_PRECONDITION)
    assert details.startswith(f"{which}: "), details


def test_a_vanishing_start_velocity_is_rest(server):
    # off the first segment (a redirect), so small that its norm underflowed to 0: a division
    # by zero, INTERNAL
    request = pb.PlanRequest()
    request.CopyFrom(PLAN)
    request.start_linear_velocity.y = 2.2250738585072014e-308
    code, details = plan(server, request)
    assert code == grpc.StatusCode.OK, (code, details)
