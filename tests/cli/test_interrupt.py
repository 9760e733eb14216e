"""One Ctrl-C ends every long-running command, as a user at a terminal sees it: SIGINT to the
command's whole process group, once; the command exits promptly (within ``PROMPT`` s of an idle
core, stretched by how much slower CPU-bound work ran meanwhile: see _interrupt.Slowdown), with
130 (or 0 for the server and the simulators, which stop gracefully on it), no traceback and no
complaint of ur_rtde's, and the arm it drove was told to stop and received no motion command
after that. What kept the commands 2 s longer is checked on its own, load or not: ur_rtde's
disconnect (0.5 s an interface, as long again in its destructors, all after the connection has
ended), seen as the arm's process living on once the simulator had lost its RTDE clients.
The UR simulators the commands start are watched through their test hooks."""
from __future__ import annotations

import os
import time

import pytest

pytest.importorskip("rtde_control")

from dqpose.drivers.sim.ur import (
    MOVEL,
    SERVO_STOP,
    SERVOL,
    SPEED_STOP,
    STOP_SCRIPT,
    STOPJ,
    STOPL,
)
from tests.cli._interrupt import (
    EXIT_TIMEOUT,
    Command,
    SimWatch,
    alive,
    arm_process,
    assert_stopped_after,
    children,
    sim_host,
)

MOTION = (SERVOL, MOVEL)
STOPS = (SERVO_STOP, SPEED_STOP, STOPL, STOPJ, STOP_SCRIPT)
#: s the arm's process may be seen alive after its simulator lost its RTDE clients: none when
#: the process's end closes them; a disconnect on the way out lingers 1 s or more
LINGER = 0.5


def _clean(cmd: Command) -> None:
    """No traceback, and no complaint of ur_rtde's threads (a controller that went away while
    the connections were still open)."""
    out = cmd.stdout + cmd.stderr
    assert "Traceback" not in out, cmd.stderr
    assert "RTDEReceiveInterface" not in out and "RTDEControlInterface" not in out, out[-3000:]


def _arm_stopped_and_gone(cmd: Command, watch: SimWatch, code: int, expected: int) -> None:
    """The command exited with ``expected``, cleanly and promptly; its arm was told to stop and
    got no motion command after that; its arm's process did not wait on ur_rtde's disconnect."""
    assert code == expected, cmd.stderr
    _clean(cmd)
    assert_stopped_after(watch.entries, cmd.interrupted_at, MOTION, STOPS)
    linger = watch.linger(cmd.interrupted_at)
    assert linger < LINGER, (f"the arm's process lived on {linger:.3f} s after its simulator "
                             f"had lost its RTDE clients (ur_rtde's disconnect)")
    cmd.assert_prompt()


def _interrupt_while_servoing(cmd: Command, servo_points: int = 200):
    """Waits until the command's simulator has received ``servo_points`` servoL set-points from
    its arm process, interrupts once and waits for the exit; returns the exit code and the
    watch."""
    try:
        pid, host = sim_host(cmd)
        watch = SimWatch(host)
        cmd.wait_for(lambda: watch.count(SERVOL) >= servo_points, "the arm servoing")
        watch.hold(arm_process(cmd))
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
    _arm_stopped_and_gone(cmd, watch, code, 130)
    assert f"dqpose demo {mode}: interrupted" in cmd.stderr


def test_ctrl_c_ends_handeye_capture_with_the_arm_stopped(tmp_path):
    folder = tmp_path / "calib"
    cmd = Command("handeye", "capture", str(folder), "--views", "15")
    try:
        pid, host = sim_host(cmd)
        watch = SimWatch(host)
        watch.hold(cmd.proc.pid)        # the arm is the command's own
        cmd.wait_for(lambda: watch.count(MOVEL) >= 3, "the arm moving between views")
        cmd.interrupt()
        code = cmd.wait()
        watch.wait_gone()               # the simulator ends with the command
    finally:
        cmd.kill()
    _arm_stopped_and_gone(cmd, watch, code, 130)
    # what was taken is kept, and the rerun is said
    assert (folder / "poses.json").is_file()
    assert "--resume" in cmd.stderr and "--force" in cmd.stderr, cmd.stderr


def test_ctrl_c_ends_sim_ur():
    cmd = Command("sim", "ur", "--host", "127.0.0.251")
    code = cmd.interrupted_when(lambda: "ursim" in cmd.stdout, "the simulator ready")
    assert code == 0, cmd.stderr
    _clean(cmd)
    cmd.assert_prompt()


def test_ctrl_c_ends_serve_with_its_simulators(tmp_path):
    cmd = Command("serve", "--sims", "--port", "0")
    try:
        cmd.wait_for(lambda: '"event": "serving"' in cmd.stderr, "the server serving")
        sims = [pid for pid, _ in children(cmd.proc.pid, "dqpose.drivers.sim.ur")
                + children(cmd.proc.pid, "dqpose.drivers.sim.piper")]
        cmd.interrupt()
        code = cmd.wait()
    finally:
        cmd.kill()
    assert code == 0, cmd.stderr
    _clean(cmd)
    # no health to drain at a terminal, and calls in flight get a short grace
    assert '{"event": "shutting_down", "drain_s": 0.0, "grace_s": 0.25}' in cmd.stderr, \
        cmd.stderr
    cmd.assert_prompt()
    deadline = time.monotonic() + EXIT_TIMEOUT
    while any(alive(p) for p in sims) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(alive(p) for p in sims), "a simulator outlived the server"


def test_ctrl_c_ends_serve_with_an_arm_of_its_simulators():
    """``serve --sims --arm ur=ur:sim``: the fleet's UR, driven in its own process, is stopped
    and its simulator ends with the server."""
    cmd = Command("serve", "--sims", "--port", "0", "--arm", "ur=ur:sim")
    try:
        pid, host = sim_host(cmd)
        watch = SimWatch(host)
        cmd.wait_for(lambda: '"event": "serving"' in cmd.stderr, "the server serving")
        watch.hold(arm_process(cmd))
        cmd.interrupt()
        code = cmd.wait()
        watch.wait_gone()
        assert not alive(pid)
    finally:
        cmd.kill()
    _arm_stopped_and_gone(cmd, watch, code, 0)


def test_a_second_ctrl_c_ends_serve_at_once():
    """A server in a slow shutdown (SIGTERM with a drain of 60 s): the first Ctrl-C hands SIGINT
    back to Python, the next ends the server at once (130, not 0 after the drain), its arm
    stopped and its simulators ended all the same. Ctrl-C is pressed until it exits (two
    signals close together may reach the server as one)."""
    import signal
    cmd = Command("serve", "--sims", "--port", "0", "--drain", "60", "--arm", "ur=ur:sim")
    try:
        pid, host = sim_host(cmd)
        watch = SimWatch(host)
        cmd.wait_for(lambda: '"event": "serving"' in cmd.stderr, "the server serving")
        sims = [p for p, _ in children(cmd.proc.pid, "dqpose.drivers.sim.ur")
                + children(cmd.proc.pid, "dqpose.drivers.sim.piper")]
        os.kill(cmd.proc.pid, signal.SIGTERM)           # to the server, as `kill` sends it
        cmd.wait_for(lambda: '"event": "shutting_down"' in cmd.stderr, "the shutdown")
        for _ in range(20):
            cmd.interrupt()
            cmd._waiter.join(1.0)
            if not cmd._waiter.is_alive():
                break
        code = cmd.wait()
        watch.wait_gone()
    finally:
        cmd.kill()
    assert code == 130, cmd.stderr
    _clean(cmd)
    assert '"event": "stopped"' not in cmd.stderr       # the drain was not waited for
    assert watch.count(STOP_SCRIPT) >= 1                # the arm's close ended its script
    assert not any(alive(p) for p in sims), "a simulator outlived the server"


def test_ctrl_c_ends_serve_while_an_arm_executes(tmp_path):
    """A server with an arm (a simulator of the test's own, so it can be asked afterwards) and a
    client's Execute under way: one Ctrl-C ends the server, the run is cut and the arm stands."""
    import threading

    import numpy as np

    from dqpose import dq, trajectory
    from dqpose.drivers.rotvec import pose_from_rotvec
    from dqpose.drivers.sim.ur import URSimProcess
    from dqpose.rpc.client import Client

    home = np.array([0.40, -0.10, 0.30, np.pi, 0.0, 0.0])
    with URSimProcess() as sim:
        sim.set_pose(home)
        watch = SimWatch(sim.host)
        cmd = Command("serve", "--port", "0", "--arm", f"ur=ur:{sim.host}", "--arm-loop",
                      "thread")
        watch.hold(cmd.proc.pid)        # the arm's loop runs in the server
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
        _arm_stopped_and_gone(cmd, watch, code, 0)
        state = sim.state()
        assert not state["moving"] and not state["servoing"], state
        assert states and states[-1] != "FINISHED", states      # cut, not run to the end


def _address(log: str) -> str:
    import re
    m = re.search(r'"event": "serving", "address": "([^"]+)"', log)
    assert m, log
    return m.group(1)
