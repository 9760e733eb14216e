"""`dqpose plan` and `dqpose smooth`: JSON (the grpcurl request bodies) and CSV files, on a real
server on 127.0.0.1 and --local; both answer what the domain computes, --plot writes a PNG, bad
files and limits are named; and `dqpose demo trajectory` runs on the simulated UR."""
from __future__ import annotations

import io
import json
import math

import numpy as np
import pytest

from dqpose import dq, smoothing, trajectory
from tests.cli._cli import run, server  # noqa: F401 (server: a fixture)

LIMIT_FLAGS = ["--max-linear-velocity", "0.2", "--max-angular-velocity", "1",
               "--max-linear-acceleration", "1", "--max-angular-acceleration", "2",
               "--max-linear-jerk", "10", "--max-angular-jerk", "20"]
LIMITS = trajectory.Limits(0.2, 1.0, 1.0, 2.0, 10.0, 20.0)


def _rz(deg):
    h = math.radians(deg) / 2
    return [math.cos(h), 0.0, 0.0, math.sin(h)]


ROWS = [([0.4, 0.0, 0.3], _rz(0), 0.0), ([0.5, 0.0, 0.3], _rz(20), 0.02),
        ([0.5, 0.1, 0.35], _rz(40), 0.0)]


def _csv(path):
    with open(path, "w") as f:
        f.write("x,y,z,qw,qx,qy,qz,blend_radius\n")
        for t, q, r in ROWS:
            f.write(",".join(repr(float(v)) for v in t + q + [r]) + "\n")


def _read_samples(text):
    a = np.loadtxt(io.StringIO(text), delimiter=",", skiprows=1)
    return a[:, 0], dq.from_pose(a[:, 4:8], a[:, 1:4]), a[:, 8:]


def _local_plan():
    wps = [trajectory.Waypoint(dq.from_pose(q, t), blend_radius=r) for t, q, r in ROWS]
    return trajectory.plan(wps, LIMITS)


@pytest.mark.parametrize("where", ["local", "server"])
def test_plan_csv_prints_the_samples_the_domain_plans(tmp_path, capsys, server, where):
    path = tmp_path / "path.csv"
    _csv(path)
    png = tmp_path / "plan.png"
    extra = ["--local"] if where == "local" else ["--server", server.target]
    code, out, err = run(capsys, "plan", str(path), "--rate", "250", "--plot", str(png),
                         *LIMIT_FLAGS, *extra)
    assert code == 0, err
    want = _local_plan().at_rate(250)
    t, poses, vel = _read_samples(out)
    np.testing.assert_allclose(t, want.time, atol=1e-9)
    np.testing.assert_allclose(poses * np.sign(poses[:, :1] * want.pose[:, :1]), want.pose,
                               atol=1e-9)
    np.testing.assert_allclose(vel[:, :3], want.linear_velocity, atol=1e-9)
    assert "segment 1" in err and "bound by max_" in err
    assert png.stat().st_size > 10_000


def test_plan_json_request_body(tmp_path, capsys):
    doc = {"waypoints": [{"pose": {"position": dict(zip("xyz", t)),
                                   "orientation": dict(zip("wxyz", q))}, "blend_radius": r}
                         for t, q, r in ROWS],
           "limits": {"max_linear_velocity": 0.2, "max_angular_velocity": 1.0,
                      "max_linear_acceleration": 1.0, "max_angular_acceleration": 2.0,
                      "max_linear_jerk": 10, "max_angular_jerk": 20},
           "rate_hz": 100, "interpolation": "INTERPOLATION_TOOL_LINEAR"}
    path = tmp_path / "plan.json"
    path.write_text(json.dumps(doc))
    out_json = tmp_path / "out.json"
    code, out, err = run(capsys, "plan", "--local", str(path), "-o", str(out_json))
    assert code == 0, err
    samples = json.loads(out_json.read_text())["samples"]
    want = _local_plan().at_rate(100)
    assert len(samples) == len(want.time)
    assert samples[-1]["time"] == pytest.approx(want.time[-1])


@pytest.mark.parametrize("flags, text", [
    (["--max-linear-velocity", "0"], "limits.max_linear_velocity: must be finite and > 0"),
    (["--max-angular-velocity", "nan"], "limits.max_angular_velocity"),
])
def test_plan_names_bad_limits(tmp_path, capsys, flags, text):
    path = tmp_path / "path.csv"
    _csv(path)
    code, out, err = run(capsys, "plan", "--local", str(path), *LIMIT_FLAGS, *flags)
    assert code == 2 and text in err and not out


def test_plan_needs_the_limits(tmp_path, capsys):
    path = tmp_path / "path.csv"
    _csv(path)
    code, out, err = run(capsys, "plan", "--local", str(path))
    assert code == 2 and "--max-linear-velocity: required" in err


def test_smooth_csv_local_and_server_agree_with_the_domain(tmp_path, capsys, server):
    rng = np.random.default_rng(5)
    t = np.arange(150) / 100.0
    q = np.array([_rz(10 * s) for s in t])
    p = np.stack([0.4 + 0.05 * t, 0.01 * np.sin(2 * t), 0.3 + 0 * t], axis=1)
    p = p + rng.normal(0, 1e-3, p.shape)
    path = tmp_path / "rec.csv"
    with open(path, "w") as f:
        f.write("t,x,y,z,qw,qx,qy,qz\n")
        for k in range(len(t)):
            f.write(",".join(repr(float(v)) for v in [t[k], *p[k], *q[k]]) + "\n")
    want_t, want = smoothing.smooth(t, dq.from_pose(q, p), LIMITS)
    for extra in (["--local"], ["--server", server.target]):
        code, out, err = run(capsys, "smooth", str(path), *LIMIT_FLAGS, *extra)
        assert code == 0, err
        got_t, got, _ = _read_samples(out)
        np.testing.assert_allclose(got_t, want_t, atol=1e-9)
        np.testing.assert_allclose(dq.to_pose(got)[1], dq.to_pose(want)[1], atol=1e-9)


def test_demo_trajectory_runs_on_the_simulated_ur(tmp_path, capsys):
    pytest.importorskip("rtde_control")
    from dqpose.cli import demo_trajectory
    # the server's event loop beats 0.5 s here, not the UR's 0.1 s: a loaded machine starved it
    # for 0.3 s (STALLED; the hang safety itself is tests/robustness/test_execute.py's)
    r = demo_trajectory.run(heartbeat=0.5)
    demo_trajectory.report(r)
    out = capsys.readouterr().out
    assert f": {r.state}" in out and "period jitter" in out, out
    if r.state != "FINISHED":
        # a machine too busy for the simulated controller (it shares the CPUs with the arm's
        # process and the server): the run ends short of the plan and the report says why,
        # from the set-points that came late
        assert demo_trajectory.missed_cycles(r.periods, r.period) > 0, out
        assert "why: " in out and "a busy machine" in out, out
        return
    assert "why: " not in out, out
    # the arm follows the plan: within a few millimetres of the set-points (servoL lookahead)
    assert 0 < np.median(r.tracking_mm) < 5.0
    # every set-point of the plan reached the controller
    assert len(r.periods) + 1 >= len(r.plan.time)


def test_a_run_ended_short_says_why_when_set_points_came_late():
    """The report of a run the executor stopped: its state and message, and a reason when the
    controller missed cycles (a busy machine); none for a run without missed cycles, and none
    for a finished one."""
    import io

    from dqpose.cli import demo_trajectory
    from dqpose.trajectory import Segment

    seg = (Segment(0.0, 0.01, "max_linear_velocity"),)
    on_time = np.full(4, 0.002)
    late = np.array([0.002, 0.008, 0.002, 0.002])         # 3 cycles without a set-point

    def report(state, periods):
        out = io.StringIO()
        demo_trajectory.report(demo_trajectory.Result(
            state, "tracking: the arm is 0.0052 m from its set-points" if state != "FINISHED"
            else "", 0.01, seg, None, np.array([1.0]), np.array([0.1]), periods, 0.002), out)
        return out.getvalue()
    text = report("TRACKING", late)
    assert ": TRACKING (tracking: the arm is" in text and "missed cycles 3" in text, text
    assert "why: 3 controller cycles got no set-point in time (a busy machine" in text, text
    assert "why: " not in report("TRACKING", on_time)
    assert "why: " not in report("FINISHED", late)
    # the demo's last line, its verdict, says the same
    def verdict(state, periods):
        return demo_trajectory.conclusion(demo_trajectory.Result(
            state, "", 0.01, seg, None, np.array([1.0]), np.array([0.1]), periods, 0.002))
    assert verdict("FINISHED", late) == ("verdict: the planned path (0.01 s, within its limits) "
                                         "ran to its end on the simulated UR, the arm within "
                                         "1.00 mm of its set-points")
    assert verdict("TRACKING", late).endswith("(TRACKING); 'why:' above says what kept it from it")
    assert verdict("TRACKING", on_time).endswith("(TRACKING); its message above says why")


def test_demo_trajectory_records_the_plan_and_its_execution(tmp_path, capsys):
    pytest.importorskip("rtde_control")
    pytest.importorskip("foxglove", reason="the [record] extra")
    from dqpose.cli import main
    from dqpose.record import topics
    from dqpose.record.reader import read
    from dqpose.view.timeline import timeline
    from tests.record.test_recorder import messages

    path = str(tmp_path / "demo.mcap")
    # 1 when a loaded machine starves the simulated UR and the run ends early
    code = main(["demo", "trajectory", "--trajectory-plot", str(tmp_path / "t.png"),
                 "--record", path])
    assert f"recording: {path}" in capsys.readouterr().out
    # mcap's own readers, every CRC checked
    got = {topic for topic, *_ in messages(path)}
    assert {topics.plan_topic("Plan"), topics.plan_topic("ur"), topics.arm_topic("ur", "limits"),
            topics.arm_topic("ur", "commanded"), topics.arm_topic("ur", "actual"),
            topics.arm_topic("ur", "feedback")} <= got
    rec = read(path)
    (execute,) = [c for c in rec.calls.values() if c.rpc.endswith("/Execute")]
    assert (execute.code == "OK") == (code == 0), (execute.code, code)
    assert sum(e.kind == "answer" and e.call == execute.id for e in rec.events) > 1
    tl = timeline(rec)
    plan = [p for name, _, p in tl.plans if name == "ur"][-1]
    np.testing.assert_allclose(tl.arms["ur"].t[0], plan[0], atol=1e-3)
    if code == 0:   # what dqpose view draws: the arm's actual path ends where the plan does
        np.testing.assert_allclose(tl.arms["ur"].t[-1], plan[-1], atol=1e-3)
    assert main(["demo", "trajectory", "--record", path]) == 2     # exists already
