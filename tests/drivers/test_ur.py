"""URArm (drivers.ur) through the real ur_rtde client against the simulated controller."""
from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest

pytest.importorskip("rtde_control")

from dqpose import dq
from dqpose.drivers.base import ArmError, LimitError, Limits
from dqpose.drivers.rotvec import pose_from_rotvec, rotvec_from_pose
from dqpose.drivers.sim import ur as ursim
from dqpose.drivers.ur import URArm
from tests._polling import Slowdown, wait_until

HOME = np.array([0.4, -0.1, 0.3, 2.2, 2.2, 0.0])
DETECT = 0.5        # seconds the issue allows for noticing a protective stop or a lost controller



@pytest.fixture(scope="module")
def arm(sim):
    # A long watchdog here: a loaded CI machine may pause the test loop for tens of ms; the
    # watchdog test shortens it.
    a = URArm(sim.host, watchdog=0.2)
    yield a
    a.close()


@pytest.fixture
def home(sim, arm):
    sim.set_pose(HOME)
    assert wait_until(lambda: np.allclose(rotvec_from_pose(arm.tool_pose()[1]), HOME, atol=1e-12))
    arm._stream.forget()            # the arm was teleported; measure the next step from there
    return HOME.copy()


def _latency(pred, timeout=2.0):
    """Seconds until ``pred`` holds, and how much slower than an idle core work ran meanwhile
    (:class:`_polling.Slowdown`): a deadline of the driver's own work stretches by that much on a
    loaded machine, its fixed waits (``stale_after``) do not."""
    slow = Slowdown().start()
    t0 = time.monotonic()
    try:
        assert wait_until(pred, timeout), "not detected"
        return time.monotonic() - t0, slow.stop()
    finally:
        slow.stop()


def _same_pose(a, b, atol=1e-12):
    return np.abs(a - b).max() <= atol or np.abs(a + b).max() <= atol


def _ramp(p0, direction, n, distance):
    """Set-points from rest to rest along a line (cosine profile)."""
    s = 0.5 - 0.5 * np.cos(np.pi * np.arange(1, n + 1) / n)
    out = np.tile(p0, (n, 1))
    out[:, :3] += distance * s[:, None] * np.asarray(direction, float)
    return out


def test_connects_and_reports(arm):
    st = arm.status()
    assert st.ok, st
    assert arm.period == 0.002 and st.extra["frequency"] == 500.0   # e-series


def test_rtde_commands_are_not_held_by_nagle(sim, arm):
    # ur_rtde 1.6.5 loses its TCP_NODELAY when boost reopens the socket at connect; without
    # it a servoStop waits up to a data cycle for the controller's acknowledgement.
    from dqpose.drivers.ur_connection import _rtde_connections
    socks = _rtde_connections(sim.host)
    try:
        assert len(socks) >= 2, "the receive and control connections"
        assert arm.nodelay_sockets >= 2
        assert all(s.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY) for s in socks)
    finally:
        for s in socks:
            s.close()


def test_restoring_nodelay_leaves_no_descriptors_behind(sim, arm):
    # it looks at every descriptor of the process; one kept per look doubled them per arm
    import os

    from dqpose.drivers.ur_connection import restore_nodelay as _restore_nodelay
    before = sorted(os.listdir("/proc/self/fd"))
    assert _restore_nodelay(sim.host) >= 2
    assert _restore_nodelay(sim.host) >= 2
    assert sorted(os.listdir("/proc/self/fd")) == before


def test_tool_pose_is_the_simulated_pose(sim, arm):
    p6 = [0.35, 0.05, 0.5, -0.4, 0.3, 2.9]
    sim.set_pose(p6)
    assert wait_until(lambda: _same_pose(arm.tool_pose()[1], pose_from_rotvec(p6)))


def test_servo_follows_the_path(sim, arm, home):
    start, tick0 = sim.log()["next"], sim.state()["tick"]
    path = _ramp(home, [1.0, 0.5, -0.5], 500, 0.05)     # 1 s at 500 Hz, peak 0.095 m/s
    for p in path:
        arm.servo(pose_from_rotvec(p))
    time.sleep(0.02)                                    # let the arm catch up before stopping
    arm.stop()
    entries = [e for e in sim.log(start)["entries"] if e["cmd"] == ursim.SERVOL]
    assert np.allclose([e["args"][:6] for e in entries], path, atol=1e-12)
    lags = ursim.servo_lag_cycles(entries, sim.history(tick0))
    assert lags.min() >= 1 and lags.max() <= 3, f"lag (cycles) {np.bincount(lags + 1)}"
    assert _same_pose(arm.tool_pose()[1], pose_from_rotvec(path[-1]))


def test_move_blocks_until_the_target(sim, arm, home):
    target = home.copy()
    target[:3] += [-0.05, 0.03, 0.02]
    target[3:] = rotvec_from_pose(dq.mul(pose_from_rotvec(home), dq.exp([0, 0, 0.1, 0, 0, 0])))[3:]
    arm.move(pose_from_rotvec(target), 0.2, 1.0)
    st = sim.state()
    assert st["busy"] is None and not st["moving"]
    assert _same_pose(arm.tool_pose()[1], pose_from_rotvec(target))


def test_stop_ends_a_move(sim, arm, home):
    target = home.copy()
    target[1] += 0.1
    threading.Timer(0.2, arm.stop).start()
    with pytest.raises(ArmError, match="stopped before reaching the target"):
        arm.move(pose_from_rotvec(target), 0.1, 1.0)
    assert wait_until(lambda: not sim.state()["moving"])
    y = rotvec_from_pose(arm.tool_pose()[1])[1]
    assert home[1] + 0.005 < y < target[1] - 0.05
    assert arm.status().ok


def test_jumps_and_limits_are_refused_and_the_arm_stopped(sim, arm, home):
    # the policy is tested against both arms in test_arm_limits.py; here, what ur_rtde sees
    start = sim.log()["next"]
    path = _ramp(home, [0, 1.0, 0], 100, 0.01)
    for p in path[:50]:
        arm.servo(pose_from_rotvec(p))
    jump = path[49].copy()
    jump[1] += 0.01                                     # 10 mm in one 2 ms period: 5 m/s
    with pytest.raises(LimitError, match="above limits.max_linear_velocity = 0.25 m/s"):
        arm.servo(pose_from_rotvec(jump))
    cmds = [e["cmd"] for e in sim.log(start)["entries"]]
    assert cmds.count(ursim.SERVOL) == 50 and ursim.SERVO_STOP in cmds[50:]
    assert not sim.state()["servoing"] and not sim.state()["moving"]
    assert rotvec_from_pose(arm.tool_pose()[1])[1] < jump[1] - 0.005   # never went there
    at = rotvec_from_pose(arm.tool_pose()[1])
    # from rest, a full-speed step is an acceleration of v / period = 125 m/s^2
    step = at.copy()
    step[0] += 0.25 * arm.period
    with pytest.raises(LimitError,
                       match="m/s\\^2, above limits.max_linear_acceleration = 2 m/s\\^2"):
        arm.servo(pose_from_rotvec(step))
    turned = dq.mul(pose_from_rotvec(at), dq.exp([0.0, 0.0, 0.5 * 1.5 * arm.period, 0, 0, 0]))
    with pytest.raises(LimitError, match="limits.max_angular_velocity = 1 rad/s"):
        arm.servo(turned)                               # 1.5 rad/s > 1 rad/s
    far = at.copy()
    far[2] = 1.5
    with pytest.raises(LimitError, match="outside limits.workspace"):
        arm.move(pose_from_rotvec(far), 0.1, 0.5)
    with pytest.raises(ValueError, match="^speed: must be within"):
        arm.move(pose_from_rotvec(at), 2.0, 0.5)
    with pytest.raises(ValueError, match="^pose: expected a dual quaternion of shape"):
        arm.servo(np.zeros(6))
    with pytest.raises(ValueError, match="^pose"):
        arm.servo(2 * pose_from_rotvec(at))             # not unit
    turn = at.copy()
    turn[0] += 0.01
    turn[3:] = rotvec_from_pose(dq.mul(pose_from_rotvec(at), dq.exp([0, 0, 0.5, 0, 0, 0])))[3:]
    with pytest.raises(ValueError, match="^speed: 0.2 m/s over 0.0100 m turns the tool"):
        arm.move(pose_from_rotvec(turn), 0.2, 0.5)      # moveL would turn the tool too fast
    assert sim.log(start)["entries"][-1]["cmd"] != ursim.SERVOL
    assert arm.status().ok                              # refusals are not faults


def test_watchdog_stops_a_stalled_stream(sim, arm, home):
    arm.watchdog = 10 * arm.period
    try:
        start, stops = sim.log()["next"], arm.watchdog_stops
        for p in _ramp(home, [0, 0, 1.0], 200, 0.02)[:100]:   # stop at full speed (0.16 m/s)
            arm.servo(pose_from_rotvec(p))
        assert wait_until(lambda: arm.watchdog_stops == stops + 1)
        assert wait_until(lambda: not sim.state()["moving"])
        cmds = [e["cmd"] for e in sim.log(start)["entries"]]
        assert cmds[-2:] == [ursim.SERVO_STOP, 0]      # servoStop, then the client's clear
        assert not sim.state()["servoing"]
    finally:
        arm.watchdog = 100 * arm.period


def test_protective_stop_is_reported_and_recovered(sim, arm, home):
    sim.protective_stop(True)
    latency, slower = _latency(lambda: arm.status().protective_stop)
    assert latency < DETECT * slower
    st = arm.status()
    assert not st.ok and st.error == "protective stop"
    with pytest.raises(ArmError, match="protective stop"):
        arm.servo(pose_from_rotvec(home))
    with pytest.raises(ArmError, match="cannot recover: protective stop"):
        arm.recover()
    sim.protective_stop(False)
    assert wait_until(lambda: not arm.status().protective_stop)
    arm.recover()
    assert arm.status().ok
    arm.servo(pose_from_rotvec(home))                   # commands work again
    arm.stop()


@pytest.fixture
def doomed_sim():
    with ursim.URSimProcess() as s:
        yield s


def test_lost_controller_is_detected(doomed_sim):
    sim = doomed_sim
    # 0.3 s, not the 0.1 s default: on a loaded machine a gap of 0.1 s in the resumed stream is
    # itself a (true) fault, which failed the move below before the controller was killed
    arm = URArm(sim.host, stale_after=0.3)
    try:
        assert arm.status().ok
        # a controller that stops sending while its sockets stay open: the pose goes stale
        sim.call("pause_stream", seconds=0.6)
        stale_pose = arm._recv.getActualTCPPose()
        latency, slower = _latency(lambda: not arm.status().connected)
        assert latency < 0.3 + (DETECT - 0.3) * slower      # stale_after, then the monitor
        assert "stopped sending data" in arm.status().error
        assert arm._recv.getActualTCPPose() == stale_pose    # ur_rtde alone would not notice
        with pytest.raises(ArmError, match="stopped sending data"):
            arm.tool_pose()
        assert wait_until(lambda: arm.status().connected)      # the stream resumed
        arm.recover()
    finally:
        arm.close()
    # a controller that dies in the middle of a move (ur_rtde's own blocking moveL would wait
    # for it for minutes), on a new connection: after the pause above ur_rtde's control
    # interface may still be reconnecting by itself ("Reconnecting..."), which failed the move
    # before the kill
    arm = URArm(sim.host, stale_after=0.3)
    try:
        killed = []
        # the time noted before the kill: the move may fail before sim.kill() has returned
        timer = threading.Timer(0.2, lambda: (killed.append(time.monotonic()), sim.kill()))
        target = HOME.copy()
        target[0] += 0.1
        slow = Slowdown().start()
        timer.start()
        with pytest.raises(ArmError, match="lost|stopped sending"):
            arm.move(pose_from_rotvec(target), 0.05, 0.5)     # 2 s
        noticed = time.monotonic() - killed[0]
        assert noticed < DETECT * slow.stop()
        assert not arm.status().connected
        with pytest.raises(ArmError, match="lost|stopped sending"):
            arm.servo(pose_from_rotvec(target))
    finally:
        arm.close()


def test_a_close_without_disconnect_stops_and_leaves_the_connections_to_the_process(doomed_sim):
    """``disconnect=False``, for an arm closed only as its process ends: close() sends the stop
    and ends the control script, and leaves ur_rtde's connections open (no disconnect: 0.5 s an
    interface, and as long in each destructor) for the process's end, which closes them. The
    ordinary close ends them itself."""
    import os
    import subprocess
    import sys
    sim = doomed_sim
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    # ended as the class says such a process ends (os._exit: a teardown with ur_rtde's threads
    # still running crashes now and then)
    code = ("import os, sys; from dqpose.drivers.ur import URArm; "
            "from dqpose.drivers.ur_connection import kept_to_exit; "
            "a = URArm(sys.argv[1], disconnect=False); "
            "a.close(); print('closed', flush=True); sys.stdin.readline(); "
            "assert kept_to_exit(); os._exit(0)")
    proc = subprocess.Popen([sys.executable, "-c", code, sim.host], cwd=root, text=True,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        assert proc.stdout.readline() == "closed\n", proc.stderr.read()
        assert sim.state()["rtde_clients"] == 2              # both connections still open
        sent = [e["cmd"] for e in sim.log(keys=["cmd"])["entries"] if e["cmd"]]
        assert sent[-2:] == [ursim.SERVO_STOP, ursim.STOP_SCRIPT], sent
        out, err = proc.communicate("\n", timeout=60)        # the process ends
        assert proc.returncode == 0 and "RTDE" not in out + err, err
        assert wait_until(lambda: sim.state()["rtde_clients"] == 0)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    arm = URArm(sim.host)
    assert arm.disconnect_on_close and sim.state()["rtde_clients"] == 2
    arm.close()
    assert sim.state()["rtde_clients"] == 0


def test_unreachable_host_fails_fast():
    host = next(h for h in (f"127.0.0.{i}" for i in range(250, 20, -1)) if ursim.address_free(h))
    t0 = time.monotonic()
    with pytest.raises(ArmError, match=f"^host: cannot reach a UR controller at {host}:30004"):
        URArm(host, connect_timeout=0.5)
    # a host whose ports accept connections but never answer (not a UR controller)
    listeners = []
    try:
        for port in (30004, 29999, 30003):
            s = socket.socket()
            s.bind((host, port))
            s.listen(4)
            listeners.append(s)
        with pytest.raises(ArmError, match=f"^host: {host}:30004 does not answer as a UR"):
            URArm(host, connect_timeout=0.5)
    finally:
        for s in listeners:
            s.close()
    assert time.monotonic() - t0 < 10        # a guard against a hang, not a benchmark


def test_bad_arguments():
    with pytest.raises(ValueError, match="^host:"):
        URArm("")
    with pytest.raises(ValueError, match="^frequency:"):
        URArm("127.0.0.1", frequency=1000)
    with pytest.raises(ValueError, match="^stale_after:"):
        URArm("127.0.0.1", stale_after=0)
    with pytest.raises(ValueError, match="^limits.max_linear_velocity:"):
        Limits(max_linear_velocity=-1)
    with pytest.raises(ValueError, match="^limits.workspace_min:"):
        Limits(workspace_min=(0, 0, 2), workspace_max=(1, 1, 1))


def test_measure_is_the_tool_pose_with_its_time_and_covariance(arm, home):
    before = time.time()
    m = arm.measure()
    after = time.time()
    assert m.source == "ur"
    # time.time(), the clock every driver stamps with, of when the data arrived (never older
    # than stale_after: that would be a fault)
    assert before - arm.stale_after <= m.time <= after
    assert np.allclose(rotvec_from_pose(m.pose), home, atol=1e-12)
    rs, ts = URArm.pose_sigma
    assert np.allclose(m.covariance, np.diag([rs * rs] * 3 + [ts * ts] * 3))
    arm.pose_sigma = (1e-3, 2e-3)        # e.g. the absolute accuracy of an uncalibrated arm
    try:
        assert np.allclose(np.diag(arm.measure().covariance), [1e-6] * 3 + [4e-6] * 3)
        C = np.diag(np.arange(1.0, 7.0))
        assert np.array_equal(arm.measure(C).covariance, C)
        with pytest.raises(ValueError, match="covariance: expected a finite 6x6"):
            arm.measure(np.eye(3))
        arm.pose_sigma = (0.0, 1e-3)
        with pytest.raises(ValueError, match="rotation_sigma: must be a positive"):
            arm.measure()
    finally:
        del arm.pose_sigma
