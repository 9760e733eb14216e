"""The unmodified ur_rtde 1.6.5 client against our simulated UR controller (drivers.sim.ur).

One simulator process and one pair of interfaces serve the whole module: ur_rtde's
``disconnect()`` sleeps half a second and its constructor holds the GIL, so the simulator runs in
its own process. Tests run in file order and leave the arm at rest for the next one.
"""
from __future__ import annotations

import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from tests._polling import wait_until

rtde_control = pytest.importorskip("rtde_control")
rtde_receive = pytest.importorskip("rtde_receive")

from dqpose.drivers.sim import ur  # noqa: E402

HOME = [0.4, -0.1, 0.3, 2.2, 2.2, 0.0]



@pytest.fixture(scope="module")
def rtde(sim):
    recv = rtde_receive.RTDEReceiveInterface(sim.host)
    ctrl = rtde_control.RTDEControlInterface(sim.host)
    yield recv, ctrl
    ctrl.disconnect()
    recv.disconnect()


def _at_rest(sim, pose=HOME):
    sim.set_pose(pose)


def test_interfaces_connect_and_read_the_simulated_pose(sim, rtde):
    recv, ctrl = rtde
    assert recv.isConnected() and ctrl.isConnected()
    assert ctrl.isProgramRunning()                      # the uploaded script is "playing"
    assert sim.state()["scripts"] == 1
    assert recv.getRobotMode() == 7 and recv.getSafetyMode() == 1
    target = [0.31, 0.12, 0.45, 0.1, -0.2, 1.3]
    sim.set_pose(target)
    assert wait_until(lambda: np.allclose(recv.getActualTCPPose(), target, atol=1e-12))
    t0 = recv.getTimestamp()
    assert wait_until(lambda: recv.getTimestamp() > t0)      # data keeps streaming


def test_servoL_at_500_hz_follows_the_path_with_little_lag(sim, rtde):
    recv, ctrl = rtde
    _at_rest(sim)
    start = sim.log()["next"]
    tick0 = sim.state()["tick"]
    n = 500                                             # one second at 500 Hz
    path = np.tile(np.array(HOME), (n, 1))
    s = 0.5 - 0.5 * np.cos(np.pi * np.arange(1, n + 1) / n)
    path[:, 0] += 0.08 * s
    path[:, 2] -= 0.04 * s
    for p in path:
        t = ctrl.initPeriod()
        assert ctrl.servoL(p.tolist(), 0.0, 0.0, 0.002, 0.1, 300)
        ctrl.waitPeriod(t)
    time.sleep(0.05)
    entries = [e for e in sim.log(start)["entries"] if e["cmd"] == ur.SERVOL]
    hist = sim.history(tick0)
    # every set-point arrived intact, in order
    got = np.array([e["args"][:6] for e in entries])
    assert len(got) == n and np.array_equal(got, path)
    assert all(e["args"][8] == 0.002 and e["args"][10] == 300 for e in entries)
    lags = ur.servo_lag_cycles(entries, hist)
    assert lags.min() >= 1 and lags.max() <= 3, f"lag (cycles) {np.bincount(lags + 1)}"
    # the arm moved along the commanded line, never off it, and ended at its end
    moving = hist[(hist[:, 0] > entries[0]["tick"])]
    a, b = path[0, :3], path[-1, :3]
    u = (b - a) / np.linalg.norm(b - a)
    off = np.linalg.norm(np.cross(moving[:, 2:5] - a, u), axis=1)
    assert off.max() < 1e-12
    assert np.allclose(recv.getActualTCPPose(), path[-1], atol=1e-12)


def test_servoStop_decelerates_to_rest(sim, rtde):
    recv, ctrl = rtde
    _at_rest(sim)
    p = np.array(HOME)
    for _ in range(100):                                # reach 0.1 m/s along y
        p[1] += 0.1 * 0.002
        t = ctrl.initPeriod()
        ctrl.servoL(p.tolist(), 0.0, 0.0, 0.002, 0.1, 300)
        ctrl.waitPeriod(t)
    # A set-point far ahead keeps the arm moving at the speed limit for 0.3 s, so it is still
    # moving when servoStop lands even if this process is descheduled for a while (CI machines).
    p[1] += 0.3
    ctrl.servoL(p.tolist(), 0.0, 0.0, 0.002, 0.1, 300)
    time.sleep(0.03)
    tick0 = sim.state()["tick"]
    assert ctrl.servoStop(2.0)                          # blocks until the arm is at rest
    st = sim.state()
    assert not st["moving"] and not st["servoing"]
    speed = np.linalg.norm(np.diff(sim.history(tick0)[:, 2:5], axis=0), axis=1) / 0.002
    decel = -np.diff(speed[speed > 1e-9])
    assert speed.max() > 0.05 and np.all(decel >= -1e-9)
    assert np.allclose(decel[1:-1], 2.0 * 0.002, rtol=1e-6)   # 2 m/s^2, as requested
    p_end = recv.getActualTCPPose()
    time.sleep(0.05)
    assert recv.getActualTCPPose() == p_end


def test_servo_speed_is_limited(sim, rtde):
    recv, ctrl = rtde
    _at_rest(sim)
    tick0 = sim.state()["tick"]
    jump = list(HOME)
    jump[0] += 0.1                                      # 0.1 m at once
    jump[5] += 0.3                                      # and 0.3 rad
    assert ctrl.servoL(jump, 0.0, 0.0, 0.002, 0.1, 300)
    assert wait_until(lambda: np.allclose(recv.getActualTCPPose(), jump, atol=1e-12))
    assert ctrl.servoStop()
    hist = sim.history(tick0)
    step = np.linalg.norm(np.diff(hist[:, 2:5], axis=0), axis=1)
    assert step.max() == pytest.approx(5.0 * 0.002, rel=1e-9)     # --max-linear-speed 5
    assert np.count_nonzero(step > 1e-12) == 10                    # 0.1 m at 10 mm per cycle


def test_moveL_blocks_until_the_move_ends(sim, rtde):
    recv, ctrl = rtde
    _at_rest(sim)
    start = sim.log()["next"]
    tick0 = sim.state()["tick"]
    target = list(HOME)
    target[0] += 0.06
    target[1] -= 0.02
    target[5] += 0.2
    assert ctrl.moveL(target, 0.2, 1.0)
    st = sim.state()
    assert st["busy"] is None and not st["moving"]
    assert np.allclose(recv.getActualTCPPose(), target, atol=1e-12)
    hist = sim.history(tick0)
    arrived = hist[np.all(np.abs(hist[:, 2:8] - target) < 1e-12, axis=1), 0].min()
    log = sim.log(start)["entries"]
    move = next(e for e in log if e["cmd"] == ur.MOVEL)
    assert move["args"][:8] == pytest.approx(target + [0.2, 1.0])
    # the client cleared the command (its next step after moveL returned) only after arrival
    clear = next(e for e in log if e["cmd"] == 0 and e["tick"] > move["tick"])
    assert clear["tick"] >= arrived
    # trapezoid: accelerate at 1 m/s^2, cruise at 0.2 m/s, decelerate
    seg = hist[(hist[:, 0] > move["tick"]) & (hist[:, 0] <= arrived)]
    speed = np.linalg.norm(np.diff(seg[:, 2:5], axis=0), axis=1) / 0.002
    assert speed.max() == pytest.approx(0.2, rel=1e-6)
    accel = np.diff(speed) / 0.002
    assert np.abs(accel).max() <= 1.0 + 1e-6


def test_async_moveL_reports_progress_and_stopL_ends_it(sim, rtde):
    recv, ctrl = rtde
    _at_rest(sim)
    op = ctrl.getAsyncOperationProgressEx().operationId()
    target = list(HOME)
    target[2] += 0.1
    assert ctrl.moveL(target, 0.1, 1.0, True)           # returns at once
    status = ctrl.getAsyncOperationProgressEx()
    assert status.isAsyncOperationRunning() and status.operationId() == (op + 1) % 128
    assert wait_until(lambda: sim.state()["moving"])
    ctrl.stopL(5.0)
    assert not sim.state()["moving"]
    assert not ctrl.getAsyncOperationProgressEx().isAsyncOperationRunning()
    assert HOME[2] < recv.getActualTCPPose()[2] < target[2]
    assert ctrl.moveL(target, 0.25, 2.0, True)
    assert wait_until(lambda: not ctrl.getAsyncOperationProgressEx().isAsyncOperationRunning())
    assert np.allclose(recv.getActualTCPPose(), target, atol=1e-12)


def test_second_control_interface_is_refused(sim, rtde):
    with pytest.raises(RuntimeError, match="already in use"):
        rtde_control.RTDEControlInterface(sim.host)
    assert rtde[1].isConnected()


def test_dashboard_answers_like_a_robot(sim):
    with socket.create_connection((sim.host, ur.DASHBOARD_PORT), timeout=2) as s:
        f = s.makefile("rw")
        assert "Dashboard Server" in f.readline()
        for cmd, pattern in [("PolyscopeVersion", r"\d+\.\d+\.\d+\.\d+"),
                             ("get serial number", r"^\d+$"), ("robotmode", "RUNNING"),
                             ("safetystatus", "NORMAL"), ("nonsense", "could not understand")]:
            f.write(cmd + "\n")
            f.flush()
            assert __import__("re").search(pattern, f.readline().strip()), cmd


def test_protective_stop_is_seen_by_the_client(sim, rtde):
    recv, ctrl = rtde
    sim.protective_stop(True)
    assert wait_until(lambda: recv.isProtectiveStopped())
    assert not ctrl.moveL(HOME, 0.1, 0.5)               # refused, as on a robot
    sim.protective_stop(False)
    assert wait_until(lambda: not recv.isProtectiveStopped())
    assert ctrl.reuploadScript()                        # the program must be started again
    assert wait_until(lambda: ctrl.isProgramRunning())


def test_stopScript_ends_the_program(sim, rtde):
    recv, ctrl = rtde
    assert ctrl.isProgramRunning()
    ctrl.stopScript()
    assert not ctrl.isProgramRunning()
    assert sim.state()["runtime_state"] == ur.STOPPED
    assert not ctrl.servoL(HOME, 0.0, 0.0, 0.002, 0.1, 300)   # nothing runs the commands now


def test_cli_starts_the_simulator():
    host = next(h for h in (f"127.0.0.{i}" for i in range(250, 20, -1)) if ur.address_free(h))
    proc = subprocess.Popen([sys.executable, "-m", "dqpose.cli", "sim", "ur", "--host", host,
                             "--version", "3.15.7.106331"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert f"on {host}" in line and "125 Hz" in line        # CB3 version: 125 Hz
        recv = rtde_receive.RTDEReceiveInterface(host)
        assert np.allclose(recv.getActualTCPPose(), HOME)
        recv.disconnect()
    finally:
        proc.terminate()
        proc.communicate(timeout=5)
    assert proc.returncode == 0
