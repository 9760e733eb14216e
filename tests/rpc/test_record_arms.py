"""The arms' calls recorded by a real server (``dqpose serve --record``'s recorder) on the
simulated UR through ur_rtde: an Execute's request, its feedback as sent (commanded and actual,
state), the plan's path and the limits; a WatchArm's states. Read back by mcap's own readers with
every CRC checked, each message decoded with the schema the file embeds."""
from __future__ import annotations

import json

import numpy as np
import pytest

from dqpose import dq, trajectory
from dqpose.record import topics, views
from dqpose.rpc.client import Client
from tests._polling import wait_until
from tests.record.test_recorder import messages
from tests.robustness._arms import SLOW, URRig, offset, serve

pytest.importorskip("foxglove", reason="the [record] extra")


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """One Execute and one WatchArm through a recording server: (the file, the feedback and
    states the client got, the rig, the goal)."""
    from dqpose.record.recorder import Recorder

    rig = URRig()
    recorder = Recorder(tmp_path_factory.mktemp("rec"))
    try:
        rig.reset()
        goal = offset(rig.home, dy=0.02)
        with serve([rig], recorder=recorder) as server, Client(server.target) as c:
            feedback = list(c.execute("ur", [rig.home, goal], SLOW))
            it = c.watch_arm("ur", rate_hz=20.0)
            states = [next(it) for _ in range(3)]
            it.close()
            # the cancel reached the server before it stops (which would end the watch itself)
            (traj,) = [s for s in server.running.servicers
                       if s.NAME == "dqpose.v1.Trajectories"]
            assert wait_until(lambda: traj.arms.watchers == 0, timeout=10)
        recorder.close()
        yield recorder.files[0], feedback, states, rig, goal
    finally:
        rig.close()


def _by_topic(path) -> dict:
    out: dict = {}
    for topic, name, enc, schema, data, ns in messages(path):
        out.setdefault(topic, []).append((name, enc, schema, data, ns))
    return out


def _decode(entries):
    name, _, schema, _, _ = entries[0]
    from dqpose.record.schemas import message_class
    cls = message_class(schema, name)
    return [cls.FromString(d) for _, _, _, d, _ in entries]


def _position(p) -> np.ndarray:
    return np.array([p.position.x, p.position.y, p.position.z])


def test_execute_is_recorded_with_its_feedback_as_sent(recorded):
    path, feedback, _, rig, goal = recorded
    got = _by_topic(path)
    rpc = "dqpose.v1.Trajectories/Execute"
    (request,) = _decode(got[topics.requests_topic(rpc)])
    assert request.arm == "ur" and len(request.plan.waypoints) == 2
    answers = _decode(got[topics.answers_topic(rpc)])
    assert len(answers) == len(feedback) > 5
    assert [a.time for a in answers] == [f.time for f in feedback]
    assert views._state_name(answers[-1], answers[-1].state) == feedback[-1].state == "FINISHED"
    # the Foxglove views: commanded and actual poses as sent, the tracking error as a scalar
    commanded = _decode(got[topics.arm_topic("ur", "commanded")])
    actual = _decode(got[topics.arm_topic("ur", "actual")])
    # the actual poses of the watch that followed come after the run's
    watched = len(got[topics.answers_topic("dqpose.v1.Trajectories/WatchArm")])
    assert len(commanded) == len(feedback) and len(actual) == len(feedback) + watched
    for c, a, f in zip(commanded, actual, feedback):
        assert c.frame_id == views.WORLD
        # the client's poses went through a dual quaternion and back: to rounding
        assert np.allclose(_position(c.pose), dq.to_pose(f.commanded)[1], rtol=0, atol=1e-12)
        assert np.allclose(_position(a.pose), dq.to_pose(f.actual)[1], rtol=0, atol=1e-12)
    scalars = [json.loads(d) for *_, d, _ in got[topics.arm_topic("ur", "feedback")]]
    assert [s["state"] for s in scalars] == [f.state for f in feedback]
    for s, f in zip(scalars, feedback):
        err = np.linalg.norm(dq.to_pose(f.actual)[1] - dq.to_pose(f.commanded)[1])
        assert s["error_position"] == pytest.approx(err, abs=1e-12)
    tools = [t for tf in _decode(got[topics.TF_TOPIC]) for t in tf.transforms]
    assert {(t.parent_frame_id, t.child_frame_id) for t in tools} == {(views.WORLD, "ur/tool")}


def test_the_plan_and_the_limits_are_recorded_beside_it(recorded):
    path, _, _, rig, goal = recorded
    got = _by_topic(path)
    (plan,) = _decode(got[topics.plan_topic("ur")])
    assert np.allclose(_position(plan.poses[0]), dq.to_pose(rig.home)[1], atol=1e-12)
    assert np.allclose(_position(plan.poses[-1]), dq.to_pose(goal)[1], atol=1e-12)
    (limits,) = [json.loads(d) for *_, d, _ in got[topics.arm_topic("ur", "limits")]]
    name, enc, schema, _, _ = got[topics.arm_topic("ur", "limits")][0]
    assert (name, enc) == ("dqpose.record.ArmLimits", "jsonschema")
    assert json.loads(schema)["properties"]["max_linear_velocity"] == {"type": "number"}
    assert limits["max_linear_velocity"] == rig.arm.limits.max_linear_velocity
    assert limits["max_angular_acceleration"] == rig.arm.limits.max_angular_acceleration
    for f in trajectory.LIMIT_FIELDS:
        assert limits[f"plan_{f}"] == getattr(SLOW, f)


def test_watch_arm_is_recorded_with_its_views(recorded):
    path, _, states, _, goal = recorded
    got = _by_topic(path)
    rpc = "dqpose.v1.Trajectories/WatchArm"
    (request,) = _decode(got[topics.requests_topic(rpc)])
    assert (request.arm, request.rate_hz) == ("ur", 20.0)
    answers = _decode(got[topics.answers_topic(rpc)])
    assert len(answers) >= len(states)
    for a, s in zip(answers, states):
        assert a.arm == "ur"
        assert np.allclose(_position(a.pose), dq.to_pose(s.pose)[1], rtol=0, atol=1e-12)
    scalars = [json.loads(d) for *_, d, _ in got[topics.arm_topic("ur", "state")]]
    assert scalars[0]["state"] == "FINISHED" and scalars[0]["busy"] is False
    assert scalars[0]["max_linear_velocity"] == states[0].limits.max_linear_velocity
    calls = [json.loads(d) for *_, d, _ in got[topics.CALLS_TOPIC]]
    ends = {c["call"]: c["code"] for c in calls if c["event"] == "end"}
    begins = {c["rpc"]: c["call"] for c in calls if c["event"] == "begin"}
    assert ends[begins["dqpose.v1.Trajectories/Execute"]] == "OK"
    assert ends[begins[rpc]] == "CANCELLED"
