"""An arm whose process died (a crash: ur_rtde's own reconnect can take the process that writes
servoL down with it) is opened again in a new process on its next use; the run it was running
ends ERROR saying how the process ended. SIGKILL stands in for the crash. Against the real
clients and our simulators (URArm through ur_rtde, PiperArm through python-can), each arm in a
process of its own (the rigs of test_executor.py)."""
from __future__ import annotations

import json
import logging
import os
import signal
import time
from multiprocessing.connection import wait

import pytest

from dqpose.drivers.base import ArmError
from dqpose.drivers.executor import Executor, Result
from tests._polling import wait_until
from tests.drivers.test_arm_safety import _runs_again, _trajectory
from tests.drivers.test_executor import PiperExec, URExec, _plan, run_parent


@pytest.fixture(scope="module", params=["ur-process", "piper-process"])
def rig(request):
    r = URExec(True) if request.param.startswith("ur") else PiperExec(True)
    r.arm.reopen_every = 0.0        # each test kills the arm's process: reopen it at once
    yield r
    r.close()


def _kill(arm):
    """SIGKILL the arm's process, as a crash ends it, and wait until it has exited; the
    process."""
    old = arm.process
    os.kill(old.pid, signal.SIGKILL)
    assert wait([old.sentinel], timeout=10)
    return old


def _still(rig) -> bool:
    """The simulated arm has reached the last set-point it was given."""
    if isinstance(rig, URExec):
        return not rig.sim.state()["moving"]
    return rig.stopped()


def test_a_run_whose_arm_process_dies_ends_error_once_and_the_arm_is_reopened(rig, arm):
    times, poses = _plan(arm, rate=1.0 / arm.period, length=0.08, speed=0.1)
    records = []
    ex = Executor(arm, callback=records.append)
    ex.push(times, poses)
    ex.finish()
    assert wait_until(lambda: ex.sent >= 20)
    fixed = (arm.limits, arm.name, arm.period, arm.options)
    old = _kill(arm)
    assert ex.wait(10) == Result.ERROR, ex.message
    assert ex.message == ("the arm's process ended (killed by SIGKILL) before the run did; it is "
                          "opened again on the arm's next use")
    # one last record, the last one, carrying where the run had got to
    assert [r.result for r in records].count(Result.ERROR) == 1
    assert records[-1].result == Result.ERROR and records[-1].message == ex.message
    assert records[-1].time > 0 and records[-1].actual is not None
    # nothing commands the arm now: it stands at the last set-point it was given
    assert wait_until(lambda: _still(rig), timeout=5)
    st = arm.state()                    # the next use opens it again
    assert st.ok and st.pose is not None, st.faults
    assert arm.pid != old.pid and arm.process.is_alive()
    assert (arm.limits, arm.name, arm.period, arm.options) == fixed
    rig.reset()
    _runs_again(arm)


@pytest.mark.parametrize("use", ["run", "state", "call"])
def test_an_arm_process_killed_at_rest_is_reopened_by_its_next_use(rig, arm, use, caplog):
    caplog.set_level(logging.WARNING, logger="dqpose.drivers")
    old = _kill(arm)
    if use == "run":
        _runs_again(arm)
    elif use == "state":
        st = arm.state()
        assert st.ok and st.pose is not None, st.faults
    else:
        stamp, pose = arm.tool_pose()
        assert pose.shape == (8,)
    assert arm.pid != old.pid
    _runs_again(arm)
    # one line in the log for the one reopen
    logged = [json.loads(r.getMessage()) for r in caplog.records if r.name == "dqpose.drivers"]
    assert logged == [{"event": "arm_reopened", "arm": arm.spec, "ended": "killed by SIGKILL",
                       "pid": arm.pid}]


def test_a_run_that_opens_the_arm_again_starts_with_a_fresh_heartbeat(rig, arm):
    # The owner beats from the thread that hands the plan over, as a script does: the time the
    # hand-over spends opening the arm again (most of a second for a UR) is no missed beat.
    plan = _trajectory(arm, length=0.01)
    _kill(arm)
    ex = Executor(arm, heartbeat=0.1)
    ex.push_plan(plan)                  # opens the arm again
    while not ex.done:
        ex.beat()
        time.sleep(0.01)
    assert (ex.result, ex.message) == (Result.FINISHED, "")


def _controller_away(rig, away: bool) -> None:
    """The controller stops answering (UR: it refuses connections, as while it reboots; PiPER:
    it sends no feedback), or is back."""
    if isinstance(rig, URExec):
        rig.sim.restart(down=3600.0 if away else 0.0)
    else:
        rig.sim.pause_feedback(away)


def test_reopening_is_bounded_says_why_it_failed_and_is_tried_again(rig, arm):
    old = _kill(arm)
    assert arm.state().ok               # reopened at once (reopen_every 0)
    arm.reopen_every = 3600.0
    killed_pid = None
    try:
        killed = _kill(arm)
        killed_pid = killed.pid
        st = arm.state()                # within the bound: not opened, and says when it will be
        assert not st.ok and st.pose is None
        assert st.error.startswith(f"arm: the process of {arm.spec!r} ended (killed by SIGKILL); "
                                   f"it is opened again at most once every 3600 s, next in "), \
            st.error
        with pytest.raises(ArmError, match="at most once every 3600 s"):
            arm.tool_pose()
        assert arm.process is killed    # nothing was started
        # the bound passed, the controller away: the reopen fails and says why
        arm.reopen_every = 0.0
        _controller_away(rig, True)
        with pytest.raises(ArmError) as e:
            arm.tool_pose()
        text = str(e.value)
        assert text.startswith(f"arm: the process of {arm.spec!r} ended (killed by SIGKILL); "
                               f"opening it again failed: "), text
        why = text.split("opening it again failed: ", 1)[1]
        assert why and "did not open within" not in why, why     # the backend's own reason
        arm.reopen_every = 3600.0       # a failed reopen counts: the next is after the bound
        with pytest.raises(ArmError, match="next in .*; the last attempt failed: "):
            arm.tool_pose()
        # the controller back and the bound passed: a later use opens it
        _controller_away(rig, False)
        arm.reopen_every = 0.0
        assert wait_until(lambda: arm.state().ok, timeout=30), arm.state().faults
        assert arm.pid not in (old.pid, killed_pid)
    finally:
        arm.reopen_every = 0.0
        if rig.arm.pid == killed_pid:   # failed before the controller was back
            _controller_away(rig, False)
    rig.reset()
    _runs_again(arm)


# A parent that kills its arm's process during a run, then at rest, runs again each time, and
# exits: the dead processes' rings, pipes and threads must all be gone by then.
_KILLS = """
import os, signal, sys, threading
from multiprocessing.connection import wait
from dqpose import drivers
from dqpose.drivers.executor import Executor, Result
from tests.drivers.test_arm_limits import LIMITS
from tests.drivers.test_arm_safety import _standing
arm = drivers.open_arm("ur:" + sys.argv[1], process=True, limits=LIMITS, watchdog=0.2,
                       stale_after=0.5, reopen_every=0)
def kill():
    old = arm.process
    os.kill(old.pid, signal.SIGKILL)
    wait([old.sentinel], 10)
counts = []
for during in (True, False, True, False):
    ex = None
    if during:
        ex = Executor(arm)
        ex.push(*_standing(arm))
        while ex.sent < 5:
            pass
    kill()
    if ex is not None:
        assert ex.wait(10) == Result.ERROR, ex.message
    ex = Executor(arm)                  # a plan that holds the arm still: what load cannot fail
    ex.push(*_standing(arm, 0.2))
    ex.finish()
    assert (ex.wait(10), ex.message) == (Result.FINISHED, ""), (ex.result, ex.message)
    counts.append((len(os.listdir("/proc/self/fd")), threading.active_count()))
arm.close()
print(counts, flush=True)
"""


def test_dead_arm_processes_leave_no_shared_memory_pipes_or_threads():
    pytest.importorskip("rtde_control")
    from dqpose.drivers.sim import ur as ursim
    with ursim.URSimProcess(args=("--max-linear-speed", "5")) as sim:
        run = run_parent(_KILLS, sim.host, timeout=180)
    assert run.returncode == 0, run.stderr
    counts = eval(run.stdout)
    assert len(counts) == 4 and len(set(counts)) == 1, counts     # as many after four as one
    assert "leaked shared_memory" not in run.stderr, run.stderr


def test_an_arm_that_comes_back_with_another_period_is_refused():
    # the controller at the address is now a CB3 (125 Hz, not the e-series' 500): plans made for
    # this arm's period, limits and name would not be its own
    pytest.importorskip("rtde_control")
    from dqpose import drivers
    from dqpose.drivers.sim import ur as ursim
    from tests.drivers.test_arm_limits import LIMITS
    sim = ursim.URSimProcess()
    arm = drivers.open_arm(f"ur:{sim.host}", process=True, limits=LIMITS, reopen_every=0)
    try:
        assert arm.period == 0.002
        killed = _kill(arm)
        sim.close()
        sim = ursim.URSimProcess(sim.host, args=("--version", "3.15.7.106331"))
        with pytest.raises(ArmError) as e:
            arm.tool_pose()
        assert str(e.value) == (f"arm: the process of {arm.spec!r} ended (killed by SIGKILL); "
                                f"opening it again failed: it opened with period 0.008 (was "
                                f"0.002); an arm in use keeps these")
        assert arm.period == 0.002 and arm.process is killed
        assert "opening it again failed: it opened with period 0.008" in arm.state().error
    finally:
        arm.close()
        sim.close()


def test_a_sigterm_to_the_arm_process_leaves_the_run_to_its_owner(rig, arm):
    # systemd's stop sends SIGTERM to every process of the service at once: the arm's process
    # must not die before the server, which owns the run, has brought the arm to a stop
    times, poses = _plan(arm, rate=1.0 / arm.period, length=0.04, speed=0.1)
    ex = Executor(arm)
    ex.push(times, poses)
    ex.finish()
    assert wait_until(lambda: ex.sent >= 20)
    pid = arm.pid
    os.kill(pid, signal.SIGTERM)
    assert ex.wait(10) == Result.FINISHED, ex.message
    assert arm.pid == pid and arm.process.is_alive()
