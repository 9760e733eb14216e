"""Arm safety that does not depend on whoever feeds the arm, the same for every arm: a stalled
heartbeat, an arm that stops following its set-points, a halt, faults that clear, one run at a
time; and plans sampled by the control loop itself. Against the real clients and our simulators
(URArm through ur_rtde against the simulated controller, PiperArm through python-can against
PiperSim), each with its control loop in a thread and in the arm's own process (the rigs of
test_executor.py). What the arm did is read at the simulator."""
from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from dqpose import dq, trajectory
from dqpose.drivers.base import ArmError, pose_delta, servo_step
from dqpose.drivers.executor import Executor, Result
from tests._polling import wait_until
from tests.drivers.test_arm_limits import LIMITS
from tests.drivers.test_executor import PiperExec, URExec, _plan, rig, run_parent  # noqa: F401 (fixture)


def _running(arm, **plan):
    """An executor running a plan (``_plan``'s arguments), some 20 set-points in; and the plan."""
    times, poses = _plan(arm, rate=1.0 / arm.period, **plan)
    ex = Executor(arm)
    ex.push(times, poses)
    ex.finish()
    assert wait_until(lambda: ex.sent >= 20)
    return ex, times, poses


def _runs_again(arm):
    """The arm takes a short plan and finishes it."""
    ex = Executor(arm)
    ex.push_plan(_trajectory(arm, length=0.01))
    assert (ex.wait(10), ex.message) == (Result.FINISHED, "")


def _speeds(poses) -> list[float]:
    return [float(np.linalg.norm(servo_step(b, a)[:3])) for a, b in zip(poses, poses[1:])]


def _braked_within_the_limits(arm, got):
    """From its fastest step on, the stream only slowed, within the acceleration limit, to rest."""
    speeds = _speeds(got)
    peak = int(np.argmax(speeds))
    assert all(b <= a + 1e-6 for a, b in zip(speeds[peak:], speeds[peak + 1:]))
    assert speeds[-1] < 0.1 * speeds[peak]
    steps = [servo_step(b, a)[:3] for a, b in zip(got, got[1:])]
    dv = [np.linalg.norm(b - a) / arm.period ** 2 for a, b in zip(steps, steps[1:])]
    assert max(dv) <= LIMITS.max_linear_acceleration * (1 + 1e-6)


def test_a_stalled_heartbeat_brings_the_arm_to_rest(rig, arm):
    # The owner (a server's event loop) stops beating mid-plan, with the whole plan handed over
    # and nothing cancelled: the arm must not run on to the end.
    times, poses = _plan(arm, rate=1.0 / arm.period, length=0.1, speed=0.15, accel=1.5)
    hb = 0.05
    ex = Executor(arm, heartbeat=hb)
    beating = threading.Event()
    beating.set()

    def owner():
        while beating.is_set() and not ex.done:
            ex.beat()
            time.sleep(hb / 5)
    threading.Thread(target=owner, daemon=True).start()
    ex.push(times, poses)
    ex.finish()
    assert wait_until(lambda: ex.sent >= len(times) // 4 or ex.done, timeout=10)
    beating.clear()
    at_last_beat = ex.sent
    assert ex.wait(10) == Result.STALLED, ex.message
    assert ex.message.startswith("heartbeat: none for ")
    assert f"(3 beats of {hb:g} s missed); the arm was brought to rest in" in ex.message
    assert wait_until(rig.stopped)
    got = [p for _, p in rig.arrivals()][:ex.sent]
    _braked_within_the_limits(arm, got)
    assert pose_delta(arm.tool_pose()[1], poses[-1])[0] > 0.02     # well short of the end
    # after the last beat: at most three heartbeats of the plan, then the braking
    v = 0.15
    braking = v / (0.5 * LIMITS.max_linear_acceleration * arm.period) + 2
    assert ex.sent - at_last_beat <= 3 * hb / arm.period + 1 + braking


def test_steady_heartbeats_let_a_plan_finish(rig, arm):
    times, poses = _plan(arm, rate=1.0 / arm.period, length=0.02)
    ex = Executor(arm, heartbeat=0.05)
    stop = threading.Event()

    def owner():
        while not stop.is_set():
            ex.beat()
            time.sleep(0.01)
    threading.Thread(target=owner, daemon=True).start()
    try:
        ex.push(times, poses)
        ex.finish()
        assert (ex.wait(10), ex.message) == (Result.FINISHED, "")
    finally:
        stop.set()


def test_an_arm_that_falls_behind_ends_the_run_tracking(rig, arm):
    ex, times, poses = _running(arm, length=0.08, speed=0.1)
    rig.slow(True)
    try:
        assert ex.wait(10) == Result.TRACKING, ex.message
        assert wait_until(rig.stopped)
    finally:
        rig.slow(False)
    m = ex.message
    assert m.startswith("tracking: the arm is ") and m.endswith("the arm was stopped")
    assert f"more than max_tracking = {arm.max_tracking:g} m" in m
    assert float(m.split()[4]) > arm.max_tracking
    # no catch-up: the arm stands short of the last set-point it was sent
    got = [p for _, p in rig.arrivals()][:ex.sent]
    assert pose_delta(arm.tool_pose()[1], got[-1])[0] > arm.max_tracking / 2
    assert len(got) < len(times)


def test_a_halt_brakes_the_arm_to_rest_within_its_limits(rig, arm):
    times, poses = _plan(arm, rate=1.0 / arm.period, length=0.1, speed=0.15, accel=1.5)
    ex = Executor(arm)
    ex.push(times, poses)
    ex.finish()
    assert wait_until(lambda: ex.sent >= len(times) // 3)
    ex.halt("the server is shutting down")
    assert ex.wait(10) == Result.STOPPED, ex.message
    assert ex.message.startswith("the server is shutting down; the arm was brought to rest in ")
    assert wait_until(rig.stopped)
    got = [p for _, p in rig.arrivals()][:ex.sent]
    _braked_within_the_limits(arm, got)
    n = int(ex.message.split(" in ")[1].split()[0])
    assert n >= 0.15 / (0.5 * LIMITS.max_linear_acceleration * arm.period) - 1   # braked, not cut
    assert pose_delta(arm.tool_pose()[1], poses[-1])[0] > 0.02


def test_a_halt_before_the_start_leaves_the_arm_unmoved(rig, arm):
    times, poses = _plan(arm, rate=1.0 / arm.period)
    ex = Executor(arm)
    ex.halt("shutting down")
    ex.push(times, poses)
    ex.finish()
    assert ex.wait(5) == Result.STOPPED, ex.message
    assert ex.message == "shutting down; the arm was not moved"
    assert rig.arrivals() == []


def _trajectory(arm, length=0.03, speed=0.1):
    start = arm.tool_pose()[1]
    q, t = dq.to_pose(start)
    end = dq.from_pose(q, t + length * np.array([1.0, 0.5, -0.5]) / math.sqrt(1.5))
    return trajectory.plan([trajectory.Waypoint(start), trajectory.Waypoint(end)],
                           trajectory.Limits(speed, 0.5, 1.0, 2.0))


class _Counting:
    """A trajectory that counts the samples asked of it (in this process)."""

    def __init__(self, traj):
        self.traj, self.duration, self.asked = traj, traj.duration, []

    def sample(self, times):
        self.asked.append(len(times))
        return self.traj.sample(times)


def test_a_whole_plan_is_sampled_by_the_loop_as_it_goes(rig, arm):
    traj = _trajectory(arm)
    counting = _Counting(traj)
    ex = Executor(arm, feedback_every=1)
    ex.push_plan(counting if not rig.process else traj)
    assert (ex.wait(10), ex.message) == (Result.FINISHED, "")
    fb = []
    while (f := ex.feedback(timeout=0)) is not None:
        fb.append(f)
    n = int(math.ceil(traj.duration / arm.period - 1e-9)) + 1
    t = np.array([f.time for f in fb[:n]])
    assert np.allclose(t, arm.period * np.arange(n))
    want = traj.sample(np.minimum(t, traj.duration)).pose
    got = [p for _, p in rig.arrivals()][:n]
    assert all(pose_delta(g, w)[0] < 1e-6 for g, w in zip(got, want))
    if not rig.process:     # in chunks, never whole (in an arm's process: there)
        assert max(counting.asked) <= 64 and sum(counting.asked[1:]) >= n


def test_a_whole_plan_that_does_not_start_at_the_arm_is_refused_before_sampling(rig, arm):
    here = arm.tool_pose()[1]
    q, t = dq.to_pose(here)
    away = dq.from_pose(q, t + [0.01, 0, 0])
    traj = trajectory.plan([trajectory.Waypoint(away),
                            trajectory.Waypoint(dq.from_pose(q, t + [0.3, 0, 0]))],
                           trajectory.Limits(0.001, 0.5, 1.0, 2.0))     # 5 minutes
    counting = _Counting(traj)
    ex = Executor(arm)
    with pytest.raises(ValueError, match=r"^poses\[0\]: the plan starts 0.01 m and 0 deg from "
                                         r"the arm's actual pose"):
        ex.push_plan(counting)
    # its start, nothing more (an arm's process samples its own copy: none here)
    assert counting.asked == ([] if rig.process else [1])
    assert ex.wait(0) is None and rig.arrivals() == []
    ex = Executor(arm)                          # the arm is free for the next
    ex.push_plan(_trajectory(arm, length=0.005))
    assert ex.wait(10) == Result.FINISHED, ex.message


def test_a_stale_data_fault_ends_its_run_and_clears(rig, arm):
    ex, times, poses = _running(arm, length=0.08, speed=0.1)
    rig.stall_feedback(arm.stale_after + 0.3)
    assert ex.wait(10) == Result.ERROR, ex.message
    assert "stale" in ex.message or "stopped sending data" in ex.message
    assert wait_until(lambda: not arm.status().ok)          # the arm's own watchdog, too
    # data flows again: the fault is gone, and the next run works
    assert wait_until(lambda: arm.status().ok, timeout=10), arm.status().error
    rig.reset()
    _runs_again(arm)


def _standing(arm, seconds: float = 2.0):
    """A plan that holds the arm where it stands (a run under way that moves nothing, so the
    next plan can start from the same pose)."""
    here = arm.tool_pose()[1]
    times = np.arange(0.0, seconds, arm.period)
    return times, np.repeat(here[None], len(times), axis=0)


def test_a_run_started_while_the_last_one_ends_waits_for_the_arm(rig, arm):
    # The next plan comes a moment after a cancel (a client that restarts at once): it starts
    # once the cancelled run has stopped the arm, or is refused as busy; never two at once.
    here = arm.tool_pose()[1]
    first = Executor(arm)
    first.push(*_standing(arm))
    first.finish()
    assert wait_until(lambda: first.sent >= 10)
    first.cancel()
    second = Executor(arm)
    second.push_plan(_trajectory(arm, length=0.005))
    assert first.wait(5) == Result.STOPPED, first.message
    assert (second.wait(10), second.message) == (Result.FINISHED, "")
    # the first run's set-points (and a PiPER's stop, a hold where it stands) all came before
    # the second run moved the arm
    got = [p for _, p in rig.arrivals()]
    moved = next(i for i, p in enumerate(got) if pose_delta(p, here)[0] > 1e-5)
    assert all(pose_delta(p, here)[0] > 1e-6 for p in got[moved:])


def test_a_busy_arm_is_refused_quickly_and_says_so(rig, arm):
    first = Executor(arm)
    first.push(*_standing(arm))         # no finish(): it runs until cancelled
    try:
        second = Executor(arm, busy_timeout=0.05)
        with pytest.raises(ArmError, match="^busy: another plan is running on this arm"):
            second.push_plan(_trajectory(arm, length=0.005))
        assert not first.done
    finally:
        first.cancel()
        assert first.wait(5) == Result.STOPPED, first.message


# ur_rtde 1.6.5 reconnects its control side by itself, in its own thread, when the controller
# drops the connection; a servoL written at that moment can crash the process (SIGSEGV, seen here
# about once in ten kills). In the arm's own process (serve's default) that ends the arm's process,
# not the caller's (which opens it again on its next use: test_armproc_respawn.py): the arm's own
# rigs only, so a crash cannot take the test run down with it.
UR_RTDE_RECONNECT_CRASH = "ur_rtde's own reconnect may crash the process that runs servoL"


def _answers(arm) -> bool:
    """The arm's status is ok (an arm process that cannot be opened again yet: not)."""
    try:
        return arm.status().ok
    except ArmError:
        return False


def test_a_restarted_controller_fails_its_run_and_is_reconnected(rig, arm):
    if not (isinstance(rig, URExec) and rig.process):
        pytest.skip("a UR controller restart (the PiPER's: test_piper_resends_its_mode...), "
                    f"with the arm in its own process ({UR_RTDE_RECONNECT_CRASH})")
    ex, times, poses = _running(arm, length=0.08, speed=0.1)
    rig.sim.restart()
    assert (ex.wait(10), ex.message[:40]) == (Result.ERROR, ex.message[:40])
    # the crash: the arm's process is opened again on its next use, once the controller is back
    crashed = ex.message.startswith("the arm's process ended (killed by SIGSEGV)")
    if not crashed:
        assert ex.message.startswith(f"connection to the controller at {rig.sim.host} lost")
    assert wait_until(lambda: _answers(arm), timeout=20), arm.status().error
    assert crashed or arm.status().extra["reconnects"] >= 1
    rig.reset()
    _runs_again(arm)


def test_a_killed_controller_is_reported_lost():
    # ur_rtde's own answer to a controller gone mid-stream is "Timeout connecting to UR
    # dashboard server", from its attempt to reconnect
    pytest.importorskip("rtde_control")
    from dqpose import drivers
    from dqpose.drivers.sim import ur as ursim
    with ursim.URSimProcess(args=("--max-linear-speed", "5")) as sim:
        with drivers.open_arm(f"ur:{sim.host}", process=True, limits=LIMITS, watchdog=0.2,
                              stale_after=0.5) as arm:
            ex, times, poses = _running(arm, length=0.08, speed=0.1)
            sim.kill()
            assert ex.wait(10) == Result.ERROR, ex.message
            if ex.message.startswith("the arm's process ended"):
                arm.process.join(5)
                if (arm.process.exitcode or 0) < 0:      # killed by a signal: the crash
                    pytest.xfail(f"{UR_RTDE_RECONNECT_CRASH}: exit code {arm.process.exitcode}")
            assert ex.message.startswith(f"connection to the controller at {sim.host} lost")
            assert not arm.status().ok and "lost" in arm.status().error


def test_piper_lost_command_frames_stop_the_run_instead_of_a_catch_up(rig, arm):
    # 300 ms of command frames lost mid-plan: the set-points run on without the arm; when the
    # frames come back it would race (at its own top speed) to the set-point far ahead.
    if not isinstance(rig, PiperExec):
        pytest.skip("CAN frames: the PiPER's bus")
    times, poses = _plan(arm, rate=1.0 / arm.period, length=0.1, speed=0.15, accel=1.5)
    ex = Executor(arm)
    ex.push(times, poses)
    ex.finish()
    assert wait_until(lambda: ex.sent >= len(times) // 4)
    at_drop = rig.sim.pose
    rig.sim.drop(seconds=0.3)
    assert ex.wait(10) == Result.TRACKING, ex.message
    assert rig.sim.dropped
    time.sleep(0.4)                      # the frames flow again
    assert wait_until(rig.stopped)
    # it went on to the last set-point that arrived, and no farther
    assert pose_delta(rig.sim.pose, at_drop)[0] < arm.max_tracking
    assert pose_delta(rig.sim.pose, poses[-1])[0] > 0.05


def test_piper_resends_its_mode_until_the_arm_follows(rig, arm):
    # A PiPER that restarts (standby) must be put back in CAN command mode, and the one 0x151
    # frame that does it may be lost
    if not isinstance(rig, PiperExec):
        pytest.skip("the PiPER's motion mode (0x151)")
    from dqpose.drivers.piper import MOTION_CTRL_2
    rig.sim.drop(ids=MOTION_CTRL_2, count=1)
    rig.sim.restart()
    try:
        assert wait_until(lambda: arm.status().extra.get("ctrl_mode") == 0)
        times, poses = _plan(arm, rate=1.0 / arm.period, length=0.02)
        ex = Executor(arm)
        ex.push(times, poses)
        ex.finish()
        assert (ex.wait(10), ex.message) == (Result.FINISHED, "")
        assert rig.sim.dropped[MOTION_CTRL_2] == 1
        assert rig.sim.mode is not None and rig.sim.mode.ctrl_mode == 0x01
    finally:
        rig.sim.undrop()


# A parent that starts each next run 0-5 ms after cancelling the last (as a client that retries
# at once does), then exits: every ring in shared memory must be gone by then.
_RETRY = """
import sys, time
from dqpose import drivers
from dqpose.drivers.base import ArmError
from dqpose.drivers.executor import Executor, Result
from tests.drivers.test_arm_limits import LIMITS
from tests.drivers.test_arm_safety import _standing
arm = drivers.open_arm("ur:" + sys.argv[1], process=True, limits=LIMITS, watchdog=0.2,
                       stale_after=0.5)
outcomes = []
ex = None
for delay in (0, 0, 1, 2, 3, 5):
    times, poses = _standing(arm)
    if ex is not None:
        ex.cancel()
        time.sleep(0.001 * delay)
    ex = Executor(arm)
    try:
        ex.push(times, poses)
        ex.finish()
        while ex.sent < 5 and not ex.done:
            time.sleep(0.001)
        outcomes.append("started")
    except (ArmError, ValueError) as e:
        outcomes.append(str(e).split(":")[0])
        ex = None
if ex is not None:
    ex.cancel()
    ex.wait(5)
arm.close()
print(" ".join(outcomes), flush=True)
"""


def test_runs_started_right_after_a_cancel_leak_no_shared_memory():
    pytest.importorskip("rtde_control")
    from dqpose.drivers.sim import ur as ursim
    with ursim.URSimProcess(args=("--max-linear-speed", "5")) as sim:
        run = run_parent(_RETRY, sim.host, timeout=120)
    assert run.returncode == 0, run.stderr
    outcomes = run.stdout.split()
    assert outcomes == ["started"] * 6          # each waited for the cancelled one to end
    assert "leaked shared_memory" not in run.stderr, run.stderr


def test_an_opened_arm_has_its_first_state_or_says_why_not():
    import uuid

    import can

    from dqpose import drivers
    from dqpose.drivers.sim.piper import HOME, PiperSim
    channel = f"first-{uuid.uuid4().hex[:8]}"
    bus = can.Bus(interface="virtual", channel=channel)
    try:
        with PiperSim(bus):
            with drivers.open_arm(f"piper:virtual:{channel}") as arm:
                stamp, pose = arm.tool_pose()           # at once, no waiting
                assert pose_delta(pose, HOME)[0] < 1e-6
                assert arm.state().ok
    finally:
        bus.shutdown()
    with pytest.raises(ArmError, match=r"^PiPER: no end-pose feedback received yet \(waited "
                                       r"[\d.]+ s\) on python-can virtual channel 'nobody'; "
                                       r"is the arm powered and on this bus\?"):
        drivers.open_arm("piper:virtual:nobody?connect_timeout=0.2")


def test_the_state_reports_motion_and_rest(rig, arm):
    # what GetArm reads: the pose, the velocities (a PiPER's from its pose reports), at rest
    assert wait_until(lambda: arm.state().at_rest)     # (a reset's teleport is a report ago)
    ex, times, poses = _running(arm, length=0.06, speed=0.1)
    seen = []
    while not ex.done:
        st = arm.state()
        if st.pose is not None:
            seen.append((np.linalg.norm(st.linear_velocity), st.at_rest, st.faults))
        time.sleep(0.01)
    assert ex.wait(10) == Result.FINISHED, ex.message
    moving = [v for v, rest, _ in seen if not rest]
    assert moving and 0.05 < np.median(moving) < 0.2      # cruising at 0.1 m/s
    assert all(faults == () for _, _, faults in seen)
    assert wait_until(lambda: arm.state().at_rest)
    st = arm.state()
    assert pose_delta(st.pose, poses[-1])[0] < 1e-4 and st.ok
