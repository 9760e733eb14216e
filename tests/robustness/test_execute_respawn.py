"""A server whose arm's process died (a crash of the client library that writes the set-points:
ur_rtde's own reconnect can take that process down) keeps serving the arm: the call that was
running ends ERROR saying how the process ended, and the next Execute or GetArm opens the arm
again, without a server restart. SIGKILL stands in for the crash. The real server on 127.0.0.1
with the shipped Client, the simulated UR through ur_rtde and the simulated PiPER through
python-can, each arm in a process of its own (as ``dqpose serve`` opens them)."""
from __future__ import annotations

import os
import signal
from multiprocessing.connection import wait

import pytest

from tests.robustness._arms import (  # noqa: F401 (rig: a fixture)
    SLOW,
    distance,
    offset,
    rig,
    run_out,
    served_rigs,
)


@pytest.fixture(scope="module")
def rigs():
    # each test kills an arm's process: it is opened again at once (not once per 5 s)
    with served_rigs(reopen_every=0.0) as made:
        yield made


def _kill(arm) -> int:
    """SIGKILL the arm's process, as a crash ends it, and wait until it has exited; its pid."""
    old = arm.process
    os.kill(old.pid, signal.SIGKILL)
    assert wait([old.sentinel], timeout=10)
    return old.pid


def _reports(state, r) -> None:
    """GetArm's answer is the arm's: where it stands, no fault, its own limits."""
    assert state.faults == (), state.faults
    assert state.pose is not None and distance(state.pose, r.pose()) < 1e-3
    assert state.limits.max_linear_velocity == r.arm.limits.max_linear_velocity


def test_an_execute_whose_arm_process_dies_ends_unavailable_and_the_arm_serves_on(rig):
    r, c, _ = rig
    it = c.execute(r.name, [r.home, offset(r.home, dx=0.06)], SLOW)
    assert next(it).state == "WORKING"
    pid = _kill(r.arm)
    got, err = run_out(it)
    assert err is not None and err.code.name == "UNAVAILABLE", got[-1:]
    assert [f.state for f in got[:-1]] == ["WORKING"] * (len(got) - 1)
    assert got[-1].state == "ERROR" and err.details == f"ERROR: {got[-1].message}"
    assert got[-1].message.startswith("the arm's process ended (killed by SIGKILL) before the "
                                      "run did"), got[-1].message
    # the next GetArm opens the arm again and reports it, then an Execute runs to its end (slow
    # plans here: a simulator starved on a loaded machine trails them by less than max_tracking)
    state = c.get_arm(r.name)
    _reports(state, r)
    assert state.state == "ERROR" and not state.busy and r.arm.pid != pid
    got, err = run_out(c.execute(r.name, [offset(state.pose, dz=0.005)], SLOW, from_current=True))
    assert err is None and got[-1].state == "FINISHED", got[-1:]


def test_an_arm_whose_process_died_at_rest_takes_the_next_execute(rig):
    r, c, _ = rig
    pid = _kill(r.arm)
    # the next Execute opens the arm again and runs to its end; GetArm reports the arm
    got, err = run_out(c.execute(r.name, [r.home, offset(r.home, dz=0.005)], SLOW))
    assert err is None and got[-1].state == "FINISHED", (got[-1:], err)
    assert r.arm.pid != pid
    state = c.get_arm(r.name)
    _reports(state, r)
    assert state.state == "FINISHED"
