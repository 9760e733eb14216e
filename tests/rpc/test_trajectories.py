"""The Trajectories service on a real server on 127.0.0.1: Plan and Smooth give what the domain
gives in process, bad requests are named by field with the right status, and Execute drives the
simulated UR through the real ur_rtde client: to the end, stopped by a client that leaves,
refused when the plan does not start where the arm is."""
from __future__ import annotations

import math
import time

import grpc
import numpy as np
import pytest

from dqpose import dq, smoothing, trajectory
from dqpose.rpc.client import Client, InvalidArgument, RpcError
from dqpose.rpc.server import ServerConfig
from tests._polling import wait_until
from tests.rpc._grpc_server import ServerThread

LIMITS = trajectory.Limits(max_linear_velocity=0.2, max_angular_velocity=1.0,
                           max_linear_acceleration=1.0, max_angular_acceleration=2.0,
                           max_linear_jerk=10.0, max_angular_jerk=20.0)


def _rz(deg: float) -> np.ndarray:
    h = math.radians(deg) / 2
    return np.array([math.cos(h), 0.0, 0.0, math.sin(h)])


def _waypoints():
    poses = dq.from_pose(np.array([_rz(0), _rz(30), _rz(60), _rz(45)]),
                         np.array([[0.4, 0.0, 0.3], [0.5, 0.1, 0.3], [0.5, 0.2, 0.4],
                                   [0.4, 0.2, 0.35]]))
    return [trajectory.Waypoint(poses[0]), trajectory.Waypoint(poses[1], blend_radius=0.02),
            trajectory.Waypoint(poses[2], blend_radius=0.03), trajectory.Waypoint(poses[3])]


@pytest.fixture(scope="module")
def server():
    with ServerThread() as s:
        yield s


@pytest.fixture
def client(server):
    with Client(server.target) as c:
        yield c


@pytest.mark.parametrize("mode", trajectory.INTERPOLATIONS)
def test_plan_streams_what_the_domain_plans(client, mode):
    wps = _waypoints()
    local = trajectory.plan(wps, LIMITS, mode)
    want = local.at_rate(125.0)
    got = client.plan(wps, LIMITS, 125.0, mode)
    # the wire carries waypoints as (q, t): back to dual quaternions costs a rounding or two
    assert got.duration == pytest.approx(local.duration, rel=1e-12)
    assert [s.binding for s in got.segments] == [s.binding for s in local.segments]
    assert all(type(s) is trajectory.Segment for s in got.segments)     # the domain's type
    assert len(got.time) == len(want.time)
    np.testing.assert_allclose(got.time, want.time, atol=1e-12, rtol=0)
    np.testing.assert_allclose(got.pose, want.pose * np.sign(got.pose[:, :1] * want.pose[:, :1]),
                               atol=1e-12, rtol=0)
    np.testing.assert_allclose(got.linear_velocity, want.linear_velocity, atol=1e-10, rtol=0)
    np.testing.assert_allclose(got.angular_velocity, want.angular_velocity, atol=1e-10, rtol=0)
    assert got.time[0] == 0 and got.time[-1] == got.duration
    for k, end in ((0, wps[0]), (-1, wps[-1])):
        lin, ang = _delta(got.pose[k], end.pose)
        assert lin < 1e-12 and ang < 1e-9


def test_plan_while_moving_off_the_path(client):
    """Replanning while moving: a start velocity across the first segment reaches the server's
    planner and the stream starts at waypoint 0 with that velocity."""
    v0 = np.array([0.0, -0.1, 0.05, 0.0, 0.3, 0.0])
    got = client.plan(_waypoints(), LIMITS, 125.0, start_velocity=v0)
    np.testing.assert_allclose(np.r_[got.linear_velocity[0], got.angular_velocity[0]], v0,
                               atol=1e-10)
    assert len(got.segments) == 3
    local = trajectory.plan(_waypoints(), LIMITS, start_velocity=v0)
    assert got.duration == pytest.approx(local.duration, rel=1e-12)


def _delta(a, b):
    qa, ta = dq.to_pose(a)
    qb, tb = dq.to_pose(b)
    return float(np.linalg.norm(ta - tb)), 2 * math.acos(min(1.0, abs(float(qa @ qb))))


def test_smooth_gives_what_the_domain_gives(client):
    rng = np.random.default_rng(3)
    t = np.arange(200) / 100.0
    q = np.array([_rz(20 * s) for s in t])
    p = np.stack([0.4 + 0.05 * t, 0.02 * np.sin(t), 0.3 + 0 * t], axis=1)
    noisy = dq.from_pose(q, p + rng.normal(0, 1e-3, p.shape))
    want_t, want = smoothing.smooth(t, noisy, LIMITS, smoothing=1.0)
    got_t, got = client.smooth(t, noisy, LIMITS, 1.0)
    np.testing.assert_allclose(got_t, want_t, atol=1e-12, rtol=0)
    np.testing.assert_allclose(got * np.sign(got[:, :1] * want[:, :1]), want, atol=1e-9)


def _limits(**change):
    values = {f: getattr(LIMITS, f) for f in LIMITS.__dataclass_fields__}
    values.update(change)
    return values


@pytest.mark.parametrize("edit, code, text", [
    (lambda r: setattr(r.limits, "max_linear_velocity", 0.0), "INVALID_ARGUMENT",
     "limits.max_linear_velocity: must be finite and > 0"),
    (lambda r: setattr(r.limits, "max_angular_acceleration", math.nan), "INVALID_ARGUMENT",
     "limits.max_angular_acceleration"),
    (lambda r: r.ClearField("limits"), "INVALID_ARGUMENT", "limits: required"),
    (lambda r: setattr(r.waypoints[2].pose.orientation, "w", 3.0), "INVALID_ARGUMENT",
     "waypoints[2].pose.orientation: quaternion norm"),
    (lambda r: setattr(r, "rate_hz", 0.0), "INVALID_ARGUMENT", "rate_hz: must be within"),
    (lambda r: setattr(r.waypoints[1], "time", 0.01), "FAILED_PRECONDITION", "waypoints[1]"),
])
def test_plan_names_the_bad_field(server, edit, code, text):
    from dqpose.rpc._proto.dqpose.v1 import trajectories_pb2 as tpb
    from dqpose.rpc._proto.dqpose.v1 import trajectories_pb2_grpc as tgrpc
    from dqpose.rpc.trajectories_convert import plan_msg
    request = plan_msg(_waypoints(), LIMITS, 125.0)
    edit(request)
    with grpc.insecure_channel(server.target) as ch:
        with pytest.raises(grpc.RpcError) as e:
            list(tgrpc.TrajectoriesStub(ch).Plan(request, timeout=10))
    assert e.value.code().name == code
    assert text in e.value.details()
    assert isinstance(request, tpb.PlanRequest)


def test_client_raises_the_servers_error(client):
    with pytest.raises(InvalidArgument, match=r"^waypoints\[1\]"):
        bad = _waypoints()
        bad[1] = trajectory.Waypoint(np.array([2.0, 0, 0, 0, 0, 0, 0, 0]))
        client.plan(bad, LIMITS, 125.0)


# ---- Execute on the simulated UR, through ur_rtde ----------------------------------------------

@pytest.fixture(scope="module")
def ur():
    pytest.importorskip("rtde_control")
    from dqpose import drivers
    from dqpose.drivers.executor import Executor
    from dqpose.drivers.sim.ur import URSimProcess
    sim = URSimProcess()
    # generous watchdogs: the simulator, the server and its clients share a loaded machine (a
    # 0.1 s heartbeat, 0.3 s of stall allowed, stopped a run in CI once; the watchdog's own
    # timing is tests/drivers/test_arm_safety.py's)
    arm = drivers.open_arm(f"ur:{sim.host}", stale_after=0.5, heartbeat=0.25)
    server = ServerThread(ServerConfig(port=0, arms={"ur": arm}, executor=Executor))
    try:
        yield sim, arm, server
    finally:
        server.stop()
        arm.close()
        sim.close()


def _from_arm(arm, dx=0.05, turn=20.0):
    start = arm.tool_pose()[1]
    q, t = dq.to_pose(start)
    goal_q = dq.to_pose(dq.mul(dq.from_pose(_rz(turn), [0, 0, 0]), dq.from_pose(q, [0, 0, 0])))[0]
    return [start, dq.from_pose(goal_q, t + [dx, 0.02, 0.0])]


def _ready(sim, arm):
    arm.stop()
    sim.set_pose([0.4, -0.1, 0.3, 2.2, 2.2, 0.0])
    time.sleep(0.05)


def test_execute_runs_a_plan_to_the_end(ur):
    sim, arm, server = ur
    _ready(sim, arm)
    wps = _from_arm(arm)
    with Client(server.target) as c:
        feedback = list(c.execute("ur", wps, LIMITS))
    assert feedback[-1].state == "FINISHED", feedback[-1].message
    assert all(f.state == "WORKING" for f in feedback[:-1])
    times = [f.time for f in feedback]
    assert times == sorted(times) and len(feedback) > 5
    lin, ang = _delta(arm.tool_pose()[1], wps[-1])
    assert lin < 1e-4 and ang < 1e-3
    # every commanded pose lies on the plan at its time
    plan = trajectory.plan([trajectory.Waypoint(w) for w in wps], LIMITS)
    for f in feedback[::5]:
        lin, ang = _delta(f.commanded, plan.sample([min(f.time, plan.duration)]).pose[0])
        assert lin < 1e-9 and ang < 1e-9


def test_a_client_that_leaves_stops_the_arm(ur):
    sim, arm, server = ur
    _ready(sim, arm)
    slow = trajectory.Limits(**_limits(max_linear_velocity=0.05))
    wps = _from_arm(arm, dx=0.2)
    with Client(server.target) as c:
        it = c.execute("ur", wps, slow)
        first = next(it)
        assert first.state == "WORKING"
        it.close()                       # cancels the call
    assert wait_until(lambda: not sim.state()["servoing"], timeout=2.0)
    lin, _ = _delta(arm.tool_pose()[1], wps[-1])
    assert lin > 0.05                    # stopped on the way, not at the goal


def test_execute_refuses_what_it_cannot_do(ur):
    sim, arm, server = ur
    _ready(sim, arm)
    wps = _from_arm(arm)
    far = [dq.mul(dq.from_pose([1, 0, 0, 0], [0.1, 0, 0]), wps[0]), wps[1]]
    with Client(server.target) as c:
        with pytest.raises(RpcError) as e:
            list(c.execute("ur", far, LIMITS))
        assert e.value.code.name == "FAILED_PRECONDITION"
        assert "plan.waypoints[0].pose" in e.value.details
        with pytest.raises(InvalidArgument, match=r"arm: unknown arm 'piper'.*ur"):
            list(c.execute("piper", wps, LIMITS))
    assert not sim.state()["servoing"]


# ---- where the arm is: GetArm, ListArms, Execute from_current ----------------------------------

def test_get_arm_says_where_the_arm_is_and_what_it_may_do(ur):
    from dqpose.drivers.rotvec import pose_from_rotvec
    sim, arm, server = ur
    _ready(sim, arm)
    with Client(server.target) as c:
        got = c.get_arm("ur")
        listed = c.list_arms()
        with pytest.raises(InvalidArgument, match=r"^arm: unknown arm 'kuka' \(this server's "
                                                  r"arms: ur\)$"):
            c.get_arm("kuka")
    lin, ang = _delta(got.pose, pose_from_rotvec(sim.state()["pose"]))
    assert lin < 1e-9 and ang < 1e-9
    assert got.arm == "ur" and not got.busy and got.faults == ()
    assert np.linalg.norm(got.linear_velocity) < 1e-9
    assert np.linalg.norm(got.angular_velocity) < 1e-9
    assert (got.limits.max_linear_velocity, got.limits.max_angular_velocity,
            got.limits.max_linear_acceleration, got.limits.max_angular_acceleration) == (
        arm.limits.max_linear_velocity, arm.limits.max_angular_velocity,
        arm.limits.max_linear_acceleration, arm.limits.max_angular_acceleration)
    assert got.limits.max_linear_jerk == 0
    assert [a.arm for a in listed] == ["ur"]
    lin, _ = _delta(listed[0].pose, got.pose)
    assert lin < 1e-9


def test_execute_from_where_the_arm_is(ur):
    sim, arm, server = ur
    _ready(sim, arm)
    start = arm.tool_pose()[1]
    _, goal = _from_arm(arm)
    with Client(server.target) as c:
        feedback = list(c.execute("ur", [goal], LIMITS, from_current=True))
        assert feedback[-1].state == "FINISHED", feedback[-1].message
        # the plan the arm followed is the one from where it was
        plan = trajectory.plan([trajectory.Waypoint(start), trajectory.Waypoint(goal)], LIMITS)
        for f in feedback[:-1]:
            lin, ang = _delta(f.commanded, plan.sample([f.time]).pose[0])
            assert lin < 1e-9 and ang < 1e-9
        lin, ang = _delta(arm.tool_pose()[1], goal)
        assert lin < 1e-4 and ang < 1e-3
        state = c.get_arm("ur")
        assert state.state == "FINISHED" and not state.busy
        # errors name the request's own waypoints, not the plan's with the arm's pose in front
        late = [trajectory.Waypoint(start), trajectory.Waypoint(goal, time=0.01)]
        with pytest.raises(RpcError) as e:
            list(c.execute("ur", late, LIMITS, from_current=True))
        assert e.value.code.name == "FAILED_PRECONDITION"
        assert e.value.details.startswith("plan.waypoints[1]"), e.value.details


def test_execute_from_current_needs_the_arm_at_rest(ur):
    import threading
    sim, arm, server = ur
    _ready(sim, arm)
    start = arm.tool_pose()[1]
    q, t = dq.to_pose(start)
    away = dq.from_pose(q, t + [0.1, 0.0, 0.0])
    def move():
        try:
            arm.move(away, 0.02, 0.5)
        except Exception:      # stopped below, as meant
            pass

    mover = threading.Thread(target=move, daemon=True)
    mover.start()        # a moveL of the arm's own, ~5 s: not a plan of the server's
    try:
        # the arm's own reading, which the server judges: the simulator's state runs ahead of it
        assert wait_until(lambda: sim.state()["moving"] and not arm.state().at_rest, timeout=5)
        with Client(server.target) as c, pytest.raises(RpcError) as e:
            list(c.execute("ur", [start], LIMITS, from_current=True))
        assert e.value.code.name == "FAILED_PRECONDITION"
        assert e.value.details.startswith("from_current: arm 'ur' is moving (")
        assert "it must be at rest" in e.value.details
    finally:
        arm.stop()
        mover.join(10)
