"""One Ctrl-C ends every long-running command, as a user at a terminal sees it: SIGINT to the
command's whole process group, once; the command exits (within a generous timeout: nothing here
is timed), with 130 (or 0 for the server and the simulators, which stop gracefully on it) and
no traceback, and the arm it drove was told to stop and received no motion command after that.
The UR simulators the commands start are watched through their test hooks."""
from __future__ import annotations

import os
import time

import pytest

pytest.importorskip("rtde_control")

from _interrupt import (EXIT_TIMEOUT, Command, SimWatch, alive, assert_stopped_after,  # noqa: E402
                        children, sim_host)

from drivers.sim.ursim import (MOVEL, SERVO_STOP, SERVOL, SPEED_STOP, STOP_SCRIPT,  # noqa: E402
                               STOPJ, STOPL)

MOTION = (SERVOL, MOVEL)
STOPS = (SERVO_STOP, SPEED_STOP, STOPL, STOPJ, STOP_SCRIPT)


def _no_traceback(cmd: Command) -> None:
    assert "Traceback" not in cmd.stderr and "Traceback" not in cmd.stdout, cmd.stderr


def _interrupt_while_servoing(cmd: Command, servo_points: int = 200):
    """Waits until the command's simulator has received ``servo_points`` servoL set-points,
    interrupts once and waits for the exit; returns the exit code and the watch."""
    try:
        pid, host = sim_host(cmd)
        watch = SimWatch(host)
        cmd.wait_for(lambda: watch.count(SERVOL) >= servo_points, "the arm servoing")
        cmd.interrupt()
        code = cmd.wait()
        watch.wait_gone()          # the simulator ends with the command, not before it
        assert not alive(pid)
        return code, watch
    finally:
        cmd.kill()


@pytest.mark.parametrize("mode, plot", [("fusion", "--plot"),
                                        ("trajectory", "--trajectory-plot")])
def test_ctrl_c_ends_a_demo_with_the_arm_stopped(tmp_path, mode, plot):
    cmd = Command("demo", mode, plot, str(tmp_path / "demo.png"))
    code, watch = _interrupt_while_servoing(cmd)
    assert code == 130, cmd.stderr
    _no_traceback(cmd)
    assert_stopped_after(watch.entries, cmd.interrupted_at, MOTION, STOPS)
    assert f"dqpose demo {mode}: interrupted" in cmd.stderr


def test_ctrl_c_ends_handeye_capture_with_the_arm_stopped(tmp_path):
    folder = tmp_path / "calib"
    cmd = Command("handeye", "capture", str(folder), "--views", "15")
    try:
        pid, host = sim_host(cmd)
        watch = SimWatch(host)
        cmd.wait_for(lambda: watch.count(MOVEL) >= 3, "the arm moving between views")
        cmd.interrupt()
        code = cmd.wait()
        watch.wait_gone()
    finally:
        cmd.kill()
    assert code == 130, cmd.stderr
    _no_traceback(cmd)
    assert_stopped_after(watch.entries, cmd.interrupted_at, MOTION, STOPS)
    # what was taken is kept, and the rerun is said
    assert (folder / "poses.json").is_file()
    assert "--resume" in cmd.stderr and "--force" in cmd.stderr, cmd.stderr


def test_ctrl_c_ends_sim_ur():
    cmd = Command("sim", "ur", "--host", "127.0.0.251")
    try:
        cmd.wait_for(lambda: "ursim" in cmd.stdout, "the simulator ready")
        cmd.interrupt()
        code = cmd.wait()
    finally:
        cmd.kill()
    assert code == 0, cmd.stderr
    _no_traceback(cmd)


def test_ctrl_c_ends_serve_with_its_simulators(tmp_path):
    cmd = Command("serve", "--sims", "--port", "0")
    try:
        cmd.wait_for(lambda: '"event": "serving"' in cmd.stderr, "the server serving")
        sims = [pid for pid, _ in children(cmd.proc.pid, "drivers.sim.ursim")
                + children(cmd.proc.pid, "drivers.sim.piper")]
        cmd.interrupt()
        code = cmd.wait()
    finally:
        cmd.kill()
    assert code == 0, cmd.stderr
    _no_traceback(cmd)
    deadline = time.monotonic() + EXIT_TIMEOUT
    while any(alive(p) for p in sims) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(alive(p) for p in sims), "a simulator outlived the server"


def test_ctrl_c_ends_serve_while_an_arm_executes(tmp_path):
    """A server with an arm (a simulator of the test's own, so it can be asked afterwards) and a
    client's Execute under way: one Ctrl-C ends the server, the run is cut and the arm stands."""
    import threading

    import numpy as np

    from drivers.rotvec import pose_from_rotvec
    from drivers.sim.ursim import URSimProcess
    from service import dq, trajectory
    from service.rpc.client import Client

    home = np.array([0.40, -0.10, 0.30, np.pi, 0.0, 0.0])
    with URSimProcess() as sim:
        sim.set_pose(home)
        watch = SimWatch(sim.host)
        cmd = Command("serve", "--port", "0", "--arm", f"ur=ur:{sim.host}", "--arm-loop",
                      "thread")
        try:
            cmd.wait_for(lambda: '"event": "serving"' in cmd.stderr, "the server serving")
            target = _address(cmd.stderr)
            start = pose_from_rotvec(home)
            q, t = dq.to_pose(start)
            far = dq.from_pose(q, t + [0.2, 0.0, 0.0])
            limits = trajectory.Limits(0.02, 0.5, 0.5, 1.0)      # 10 s out, then back
            wps = [trajectory.Waypoint(start), trajectory.Waypoint(far),
                   trajectory.Waypoint(start)]
            states: list = []

            def execute():
                try:
                    with Client(target) as c:
                        for fb in c.execute("ur", wps, limits):
                            states.append(fb.state)
                except Exception as e:         # the server went away under the stream
                    states.append(repr(e))
            runner = threading.Thread(target=execute, daemon=True)
            runner.start()
            cmd.wait_for(lambda: watch.count(SERVOL) >= 200, "the arm servoing")
            cmd.interrupt()
            code = cmd.wait()
            runner.join(EXIT_TIMEOUT)
        finally:
            cmd.kill()
        assert code == 0, cmd.stderr
        assert_stopped_after(watch.entries, cmd.interrupted_at, MOTION, STOPS)
        state = sim.state()
        assert not state["moving"] and not state["servoing"], state
        assert states and states[-1] != "FINISHED", states      # cut, not run to the end
        _no_traceback(cmd)


def _address(log: str) -> str:
    import re
    m = re.search(r'"event": "serving", "address": "([^"]+)"', log)
    assert m, log
    return m.group(1)
