"""The executor against both real simulators: URArm through the real ur_rtde client against the
simulated controller in its own process, PiperArm against PiperSim on a python-can bus (the rigs
of test_arm_limits.py, with the same Limits); each arm opened here (the control loop in a thread)
and in a process of its own (``open_arm(..., process=True)``: the loop in that process, fed
through shared memory). What the arm did is read at the simulator: the set-points it received,
when they arrived, whether it stands still."""
from __future__ import annotations

import gc
import math
import threading
import time
import weakref

import numpy as np
import pytest

from dqpose import dq
from dqpose.drivers.base import pose_delta, servo_step
from dqpose.drivers.executor import Executor, Feedback, Result
from dqpose.interpolate import interpolate
from dqpose.profile import Trapezoid
from tests._polling import Slowdown, wait_until
from tests.drivers.test_arm_limits import LIMITS, PiperRig, URRig, _same


class URExec(URRig):
    def __init__(self, process: bool = False):
        # the test machine is shared: a 0.1 s hiccup is no fault
        super().__init__(process, stale_after=0.5)

    def arrivals(self) -> list[tuple[float, np.ndarray]]:
        """(CLOCK_MONOTONIC at the simulator, pose) of each servo set-point since ``reset``."""
        from dqpose.drivers.rotvec import pose_from_rotvec
        return [(e["mono"], pose_from_rotvec(e["args"][:6]))
                for e in self.sim.log(self._mark, cmd=self._ursim.SERVOL)["entries"]]

    def stop_arrived(self) -> float:
        """When the servo stop arrived (monotonic), inf if none did."""
        stops = self.sim.log(self._mark, cmd=self._ursim.SERVO_STOP)["entries"]
        return stops[0]["mono"] if stops else math.inf

    def setpoints_after_stop(self) -> int:
        """Servo set-points the controller read after the first servo stop (in the order of the
        stream: a set-point and the stop right behind it can share one kernel stamp)."""
        cmds = [e["cmd"] for e in self.sim.log(self._mark, keys=["cmd"])["entries"]]
        stop = cmds.index(self._ursim.SERVO_STOP)
        return cmds[stop:].count(self._ursim.SERVOL)

    def protective_stop(self, on: bool):
        self.sim.protective_stop(on)
        if not on:
            assert wait_until(lambda: not self.arm.status().protective_stop)
            self.arm.recover()

    def slow(self, on: bool):
        """The arm falls behind (held back, slowed): its model's speed limit 0.02 m/s."""
        self.sim.set_speed(linear=0.02 if on else 5.0)

    def stall_feedback(self, seconds: float):
        self.sim.pause_stream(seconds)


class PiperExec(PiperRig):
    def reset(self):
        super().reset()         # nothing of the last test still on the bus
        self._arrival_mark = len(self.sim.arrivals)

    def arrivals(self) -> list[tuple[float, np.ndarray]]:
        return list(zip(self.sim.arrivals[self._arrival_mark:], self.received()))

    def stop_arrived(self) -> float:
        return math.inf   # a PiPER stop is a set-point on the measured pose: see stopped()

    def protective_stop(self, on: bool):
        if on:
            self.sim.collide()
        else:
            self.sim.clear_faults()
            assert wait_until(lambda: self.arm.status().ok)

    def slow(self, on: bool):
        self.sim.max_speed = 0.02 if on else 0.5

    def stall_feedback(self, seconds: float):
        self.sim.pause_feedback(True)
        threading.Timer(seconds, self.sim.pause_feedback, args=(False,)).start()


@pytest.fixture(scope="module", params=["ur", "piper", "ur-process", "piper-process"])
def rig(request):
    process = request.param.endswith("-process")
    r = URExec(process) if request.param.startswith("ur") else PiperExec(process)
    yield r
    r.close()


def _plan(arm, rate: float, length: float = 0.03, speed: float = 0.1, accel: float = 1.0,
          direction=(1.0, 0.5, -0.5)):
    """A trapezoidal straight move from where the arm stands, turning 2 rad per metre about
    base z (within LIMITS' angular rates), sampled at ``rate`` Hz (the last sample on the end)."""
    turn = 2.0 * length
    start = arm.tool_pose()[1]
    q, t = dq.to_pose(start)
    u = np.asarray(direction) / np.linalg.norm(direction)
    rot = dq.from_pose([math.cos(turn / 2), 0, 0, math.sin(turn / 2)], [0, 0, 0])
    end = dq.from_pose(dq.to_pose(dq.mul(rot, dq.from_pose(q, [0, 0, 0])))[0], t + length * u)
    prof = Trapezoid(length, speed, accel)
    times = np.append(np.arange(0.0, prof.duration, 1.0 / rate), prof.duration)
    return times, interpolate([0.0, 1.0], np.stack([start, end]), prof.fraction(times),
                              "tool_linear")


def _drain(ex) -> list[Feedback]:
    out = []
    while (f := ex.feedback(timeout=0)) is not None:
        out.append(f)
    return out


def test_a_plan_pushed_in_chunks_runs_to_the_end(rig, arm):
    times, poses = _plan(arm, rate=1000.0)      # not the arm's rate: resampled
    ex = Executor(arm)
    for i in range(0, len(times), 40):
        ex.push(times[i:i + 40], poses[i:i + 40])
    ex.finish()
    assert (ex.wait(10), ex.message) == (Result.FINISHED, "")
    fb = _drain(ex)
    assert [f.result for f in fb] == [Result.OK] * (len(fb) - 1) + [Result.FINISHED]
    d, a = pose_delta(fb[-1].actual, poses[-1])
    assert d <= ex.settle_tolerance[0] and a <= ex.settle_tolerance[1] and rig.stopped()
    # one set-point per period on the plan's clock, each the plan at that time
    t = np.array([f.time for f in fb[:-1]])
    n = int(math.ceil(times[-1] / arm.period - 1e-9)) + 1
    assert np.allclose(t[:n], arm.period * np.arange(n))
    want = interpolate(times, poses, np.minimum(t[:n], times[-1]), "tool_linear")
    got = [a[1] for a in rig.arrivals()]
    assert len(got) >= n
    assert all(_same(g, w) for g, w in zip(got[:n], want))
    assert all(_same(g, poses[-1]) for g in got[n - 1:])       # then held until settled


def test_samples_at_the_arm_rate_are_sent_unchanged(rig, arm):
    times, poses = _plan(arm, rate=1.0 / arm.period, length=0.01)
    ex = Executor(arm, feedback_every=5)
    ex.push(times, poses)
    ex.finish()
    assert ex.wait(10) == Result.FINISHED
    got = [a[1] for a in rig.arrivals()]
    assert all(_same(g, p) for g, p in zip(got, poses)) and len(got) >= len(poses)
    fb = _drain(ex)
    assert len(fb) == ex.sent // 5 + 1


def test_cancel_stops_within_one_period(rig, arm):
    times, poses = _plan(arm, rate=1.0 / arm.period, length=0.08, speed=0.1)
    seen = []
    ex = Executor(arm, callback=seen.append)
    ex.push(times, poses)                                      # no finish(): cancel ends it
    assert wait_until(lambda: len(seen) >= 30)
    slow = Slowdown().start()
    cancelled = time.monotonic()
    ex.cancel()
    assert ex.wait(5) == Result.STOPPED
    slowdown = slow.stop()
    assert seen[-1].result == Result.STOPPED and "stopped" in seen[-1].message
    assert wait_until(rig.stopped)
    after = [t for t, _ in rig.arrivals() if t > cancelled]
    if isinstance(rig, URExec):
        # the test's clock is read before cancel() reaches the loop: a set-point may go out in
        # between, and one more already on its way past the loop's own check; the stop comes
        # next, and nothing after it
        assert len(after) <= 2
        assert rig.setpoints_after_stop() == 0
        # one period and a little slack, stretched by how much slower than an idle core the
        # machine ran meanwhile
        assert rig.stop_arrived() - cancelled < (arm.period + 0.01) * slowdown
    else:
        # as above, a set-point between the clock read and the loop's check, one already past
        # it, then the stop's hold on the measured pose
        assert len(after) <= 3
    assert all(t - cancelled < (arm.period + 0.01) * slowdown for t in after)
    assert pose_delta(arm.tool_pose()[1], poses[-1])[0] > 0.01  # stopped well short of the end


def _all_arrived(rig, ex) -> list:
    """The poses the simulator received, once it has every set-point the executor sent and the
    arm is still (on a loaded machine the last set-points may still be on their way when the
    arm already stands; a set-point that never arrives fails the wait)."""
    assert wait_until(lambda: len(rig.arrivals()) >= ex.sent and rig.stopped(), timeout=10)
    return [p for _, p in rig.arrivals()]


def test_a_dry_buffer_brakes_within_the_limits_and_stalls(rig, arm):
    times, poses = _plan(arm, rate=1.0 / arm.period, length=0.04, speed=0.15, accel=1.5)
    half = len(times) // 2                                     # cruising by then
    ex = Executor(arm)
    ex.push(times[:half], poses[:half])
    assert ex.wait(10) == Result.STALLED
    assert "ran dry" in ex.message
    got = _all_arrived(rig, ex)
    assert ex.sent > half + 3                                  # braked over several periods
    got = got[:ex.sent]                                        # (a PiPER stop is one more)
    assert all(_same(g, p) for g, p in zip(got, poses[:half]))
    # the braking passed the arm's Limits (else LIMITED) and never reversed: the speed only falls
    steps = [servo_step(b, a) for a, b in zip(got[half - 1:], got[half:])]
    speeds = [np.linalg.norm(s[:3]) for s in steps]
    assert all(b <= a + 1e-6 for a, b in zip(speeds, speeds[1:]))
    v = np.linalg.norm(servo_step(poses[half - 1], poses[half - 2])[:3]) / arm.period
    braking = v * v / (2 * 0.5 * LIMITS.max_linear_acceleration)
    d = pose_delta(got[-1], poses[half - 1])[0]
    assert 0 < d <= braking + v * arm.period


def test_a_setpoint_over_the_limits_ends_limited_with_the_arm_stopped(rig, arm):
    # cruising at 1.5 x max_linear_velocity
    times, poses = _plan(arm, rate=1.0 / arm.period, length=0.05,
                         speed=1.5 * LIMITS.max_linear_velocity, accel=1.0)
    ex = Executor(arm)
    ex.push(times, poses)
    ex.finish()
    assert ex.wait(10) == Result.LIMITED
    assert "limits.max_linear_velocity" in ex.message and ex.message.endswith("the arm was stopped")
    got = _all_arrived(rig, ex)
    assert ex.sent > 0
    assert all(_same(g, p) for g, p in zip(got[:ex.sent], poses))  # the plan's, up to the refusal
    bad = poses[ex.sent]
    assert np.linalg.norm(servo_step(bad, poses[ex.sent - 1])[:3]) / arm.period > \
        LIMITS.max_linear_velocity
    assert not any(_same(g, bad) for g in got)


def test_a_protective_stop_aborts(rig, arm):
    times, poses = _plan(arm, rate=1.0 / arm.period, length=0.08)
    ex = Executor(arm)
    ex.push(times, poses)
    ex.finish()
    assert wait_until(lambda: ex.sent >= 20)
    rig.protective_stop(True)
    try:
        assert ex.wait(5) == Result.PROTECTIVE_STOP
        assert ex.message
        n = len(rig.arrivals())
        time.sleep(10 * arm.period)
        assert len(rig.arrivals()) == n                        # nothing more was sent
    finally:
        rig.protective_stop(False)


def test_a_plan_that_does_not_start_at_the_arm_is_refused(rig, arm):
    times, poses = _plan(arm, rate=1.0 / arm.period)
    q, t = dq.to_pose(poses[0])
    far = dq.from_pose(q, t + [0.003, 0, 0])     # within max_tracking, above a step's reach
    ex = Executor(arm)
    with pytest.raises(ValueError, match=r"^poses\[0\]: the plan starts 0.003 m and 0 deg from "
                                         r"the arm's actual pose; it must start within .* m and "
                                         r".* deg of it \(start_tolerance\); the arm was not "
                                         r"moved"):
        ex.push([0.0, 0.1], np.stack([far, poses[1]]))
    assert ex.wait(0) is None and ex.sent == 0
    time.sleep(5 * arm.period)
    assert rig.arrivals() == []
    # a looser tolerance accepts it, and then the arm's Limits refuse the jump
    ex = Executor(arm, start_tolerance=(0.01, 0.1))
    ex.push([0.0], far[None])
    ex.finish()
    assert ex.wait(5) == Result.LIMITED
    assert not any(_same(p, far) for _, p in rig.arrivals())


def _may_realtime() -> bool:
    import os
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except (AttributeError, OSError):
        return False
    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    return True


def test_bad_input_is_refused_by_name(arm):
    here = arm.tool_pose()[1]
    ex = Executor(arm, realtime=1)
    with pytest.raises(ValueError, match=r"^times\[2\]: 0.1 is not after the previous time 0.2"):
        ex.push([0.0, 0.2, 0.1], np.stack([here] * 3))
    with pytest.raises(ValueError, match=r"^poses: expected shape \(2, 8\)"):
        ex.push([0.0, 0.1], np.stack([here] * 3))
    bad = np.stack([here] * 2)
    bad[1, 0] = np.nan
    with pytest.raises(ValueError, match=r"^poses\[1\]: contains NaN"):
        ex.push([0.0, 0.1], bad)
    with pytest.raises(ValueError, match=r"^poses\[0\]: quaternion norm 2 is not unit"):
        ex.push([0.0], 2 * here[None])
    with pytest.raises(ValueError, match="^finish: no samples were pushed"):
        ex.finish()
    ex.push([0.0, 0.1], np.stack([here] * 2))
    with pytest.raises(ValueError, match=r"^times\[0\]: 0.1 is not after the last pushed time 0.1"):
        ex.push([0.1], here[None])
    ex.finish()
    with pytest.raises(ValueError, match="^push: the plan was already finished"):
        ex.push([0.2], here[None])
    assert ex.wait(5) == Result.FINISHED
    # the control thread asked for real-time scheduling, and got it where it is permitted
    assert ex.realtime == _may_realtime()
    for kw, msg in ((dict(interpolation="cubic"), "^interpolation: unknown 'cubic'"),
                    (dict(feedback_every=0), "^feedback_every: must be a whole number"),
                    (dict(stall_timeout=-1), "^stall_timeout: must be a positive"),
                    (dict(start_tolerance=(0.1,)), r"^start_tolerance: expected \(metres"),
                    (dict(realtime=100), r"^realtime: must be a priority within 1..99 or None")):
        with pytest.raises(ValueError, match=msg):
            Executor(arm, **kw)
    with pytest.raises(ValueError, match="^arm: expected a drivers.base.Arm"):
        Executor(object())


def test_an_executor_is_freed_once_its_run_ended_without_the_garbage_collector(rig, arm):
    # the run reports to an Outcome, never to its executor: nothing (the loop's thread, the
    # reader of an arm process's feedback) keeps the executor alive, and no cycle does
    times, poses = _plan(arm, rate=1.0 / arm.period, length=0.01)
    gc.disable()
    try:
        ex = Executor(arm)
        ex.push(times, poses)
        ex.finish()
        assert ex.wait(10) == Result.FINISHED, ex.message
        gone = weakref.ref(ex)
        del ex
        assert gone() is None
    finally:
        gc.enable()


def test_no_samples_in_time_stalls_without_moving(rig, arm):
    here = arm.tool_pose()[1]
    ex = Executor(arm, prefill=0.5, stall_timeout=0.05)
    ex.push([0.0], here[None])
    assert ex.wait(5) == Result.STALLED and "the arm was not moved" in ex.message
    assert rig.arrivals() == []


# The parent of an arm's process, killed halfway through a plan it had pushed whole.
_PARENT = """
import os, sys, time
from dqpose import drivers
from dqpose.drivers.executor import Executor
from tests.drivers.test_arm_limits import LIMITS
from tests.drivers.test_executor import _plan
arm = drivers.open_arm("ur:" + sys.argv[1], process=True, limits=LIMITS, watchdog=0.2,
                       stale_after=0.5)
times, poses = _plan(arm, rate=1.0 / arm.period, length=0.08, speed=0.15, accel=1.5)
ex = Executor(arm)
ex.push(times, poses)                   # all of it, and no finish(): the parent dies first
while ex.sent < len(times) // 2:
    time.sleep(0.002)
print(arm.pid, len(times), flush=True)
os.kill(os.getpid(), 9)
"""


def run_parent(script: str, host: str, timeout: float = 60):
    """``script`` in a Python process of its own, which imports these tests' modules; its
    argument the controller's host."""
    import os
    import subprocess
    import sys
    here = os.path.dirname(os.path.abspath(__file__))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [here, os.path.dirname(here), os.path.dirname(os.path.dirname(here))]))
    return subprocess.run([sys.executable, "-c", script, host], env=env, capture_output=True,
                          text=True, timeout=timeout)


def test_a_killed_parent_brakes_the_arm_to_a_stop_and_its_process_ends():
    pytest.importorskip("rtde_control")
    import os

    from dqpose.drivers.rotvec import pose_from_rotvec
    from dqpose.drivers.sim import ur as ursim
    with ursim.URSimProcess(args=("--max-linear-speed", "5")) as sim:
        run = run_parent(_PARENT, sim.host)
        assert run.returncode == -9, run.stderr
        pid, planned = map(int, run.stdout.split())

        def ended():
            try:
                os.kill(pid, 0)
            except ProcessLookupError:
                return True
            with open(f"/proc/{pid}/stat") as f:      # a zombie no one reaps has ended too
                return f.read().split(")")[-1].split()[0] == "Z"
        assert wait_until(ended, timeout=10)
        log = sim.log()["entries"]
        got = [pose_from_rotvec(e["args"][:6]) for e in log if e["cmd"] == ursim.SERVOL]
        stops = [i for i, e in enumerate(log) if e["cmd"] == ursim.SERVO_STOP]
        assert stops and all(e["cmd"] != ursim.SERVOL for e in log[stops[0]:])
        assert planned // 2 <= len(got) < planned   # the plan was not run to its end
        assert not sim.state()["servoing"]
        # braked within the Limits: after the kill the speed only falls, to rest
        speeds = [np.linalg.norm(servo_step(b, a)[:3]) for a, b in zip(got, got[1:])]
        peak = int(np.argmax(speeds))
        assert all(b <= a + 1e-6 for a, b in zip(speeds[peak:], speeds[peak + 1:]))
        assert speeds[-1] < 0.1 * speeds[peak]
        steps = [servo_step(b, a) for a, b in zip(got, got[1:])]
        dv = [np.linalg.norm(b[:3] - a[:3]) / 0.002 ** 2 for a, b in zip(steps, steps[1:])]
        assert max(dv) <= LIMITS.max_linear_acceleration * (1 + 1e-6)


@pytest.mark.parametrize("machine, ok", [("x86_64", True), ("AMD64", True), ("aarch64", False),
                                         ("arm64", False), ("riscv64", False), ("", False)])
def test_the_arm_process_is_refused_where_stores_may_be_reordered(machine, ok):
    # The ring publishes a slot by the count written after it; only a TSO processor keeps that
    # order without fences, so elsewhere the loop must stay in a thread.
    from dqpose.drivers.armproc import check_store_order
    from dqpose.drivers.base import ArmError
    if ok:
        check_store_order(machine)
    else:
        with pytest.raises(ArmError, match="process: .*store order.*in a thread"):
            check_store_order(machine)


def test_process_problem_names_what_keeps_an_arm_in_a_thread():
    from dqpose import drivers
    from dqpose.drivers.armproc import check_store_order
    check_store_order()             # (these machines: x86-64)
    assert drivers.process_problem("ur:127.0.0.1") is None
    assert drivers.process_problem("piper:udp_multicast:239.74.163.2") is None
    assert "virtual bus" in drivers.process_problem("piper:virtual:can0")
    with pytest.raises(ValueError, match="unknown backend"):
        drivers.process_problem("kuka:1.2.3.4")
