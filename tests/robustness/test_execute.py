"""Execute when things go wrong, from a client's side: the real server on 127.0.0.1 with the
shipped Client, a simulated UR driven through the real ur_rtde and a simulated PiPER through
python-can, each arm in a process of its own (as ``dqpose serve`` opens them). Every arm behaves
the same:

- limits above the arm's are refused before it moves (L1);
- the call's status follows how the run ended, after a last record that says so (L1, A1);
- a controller that stops sending data fails the call it happens in, and the next Execute works
  once data flows again (A1);
- an Execute right after a cancel waits for the braking arm instead of failing (A2);
- a server whose event loop hangs stops its arms by itself (D1b).
"""
from __future__ import annotations

import dataclasses
import time

import pytest

from dqpose.rpc.client import Client, RpcError
from tests.robustness._arms import (  # noqa: F401 (rigs: rig's fixture)
    LIMITS,
    SLOW,
    STALE_AFTER,
    URRig,
    block,
    distance,
    offset,
    rig,
    rigs,
    run_out,
    serve,
    wait_until,
)


def test_limits_above_the_arms_are_refused_before_it_moves(rig):
    r, c, _ = rig
    fast = dataclasses.replace(LIMITS, max_linear_velocity=0.5)
    with pytest.raises(RpcError) as e:
        list(c.execute(r.name, [r.home, offset(r.home, dx=0.05)], fast))
    assert e.value.code.name == "FAILED_PRECONDITION"
    assert e.value.details == (
        f"plan.limits.max_linear_velocity: 0.5 m/s is above the limits.max_linear_velocity of arm "
        f"{r.name!r}, 0.25 m/s; plan within the arm's limits (GetArm lists them)")
    assert r.setpoints() == 0 and not r.moving()


def test_a_protective_stop_ends_the_call_aborted_after_a_record_that_says_so(rig):
    r, c, _ = rig
    it = c.execute(r.name, [r.home, offset(r.home, dx=0.06)], SLOW)
    assert next(it).state == "WORKING"
    r.fault()
    got, err = run_out(it)
    assert err is not None and err.code.name == "ABORTED", got[-1:]
    assert got[-1].state == "PROTECTIVE_STOP" and err.feedback is got[-1]
    assert err.details == f"PROTECTIVE_STOP: {got[-1].message}" and got[-1].message
    assert all(f.state == "WORKING" for f in got[:-1])


def test_lost_data_fails_that_call_unavailable_and_the_next_one_works(rig):
    r, c, _ = rig
    it = c.execute(r.name, [r.home, offset(r.home, dx=0.06)], SLOW)
    assert next(it).state == "WORKING"
    # 4 x stale_after: a loaded machine can starve the arm's loop for a whole 1 s loss (the
    # PiPER's run then FINISHED, never having looked while the data was stale)
    r.lose_data(4 * STALE_AFTER)
    got, err = run_out(it)
    assert err is not None and err.code.name == "UNAVAILABLE", got[-1:]
    assert got[-1].state == "ERROR" and err.details == f"ERROR: {got[-1].message}"
    # at once, while the data is still stale: no plan from a pose that is not the arm's
    assert _settled(r, quiet=0.1)       # the stop's own last command in
    sent = r.setpoints()
    _, err = run_out(c.execute(r.name, [offset(r.home, dz=0.01)], LIMITS, from_current=True))
    assert err is not None and err.code.name == "FAILED_PRECONDITION", err
    assert err.details.startswith(f"from_current: arm {r.name!r} "), err.details
    assert r.setpoints() == sent
    # GetArm says so while it lasts, and the fault clears once data flows again: no restart
    assert wait_until(lambda: c.get_arm(r.name).faults, timeout=5)
    assert wait_until(lambda: c.get_arm(r.name).faults == () and not r.moving(), timeout=5)
    assert c.health() == "SERVING"
    here = c.get_arm(r.name).pose
    got, err = run_out(c.execute(r.name, [offset(here, dz=0.01)], LIMITS, from_current=True))
    assert err is None and got[-1].state == "FINISHED"
    assert c.get_arm(r.name).state == "FINISHED"


def test_an_execute_right_after_a_cancel_waits_for_the_arm(rig):
    r, c, _ = rig
    for i in range(6):
        it = c.execute(r.name, [offset(r.home, dy=0.03 if i % 2 else -0.03)], SLOW,
                       from_current=True)
        assert next(it).state == "WORKING"
        it.close()              # cancels; the arm brakes
        # at once: the server waits for the arm to be free and at rest, then starts from there
        got, err = run_out(c.execute(r.name, [offset(r.home, dz=0.005)], LIMITS,
                                  from_current=True))
        assert err is None, err
        assert got[-1].state == "FINISHED"


@pytest.mark.parametrize("cancel", [True, False], ids=["client-cancels", "client-waits"])
def test_a_hung_server_loop_stops_the_arm_by_itself(rig, cancel):
    """The heartbeat is beaten from the server's event loop: held, the arm's control loop
    brings the arm to a stop (STALLED) while the loop is still held, and nothing moves it after,
    even a cancel that could not get through meanwhile."""
    r, c, server = rig
    goal = offset(r.home, dx=0.1)               # ~5 s at SLOW
    it = c.execute(r.name, [r.home, goal], SLOW)
    assert next(it).state == "WORKING"
    release = block(server)
    try:
        if cancel:
            it.close()
        stopped = _settled(r)
        sent, where = r.setpoints(), r.pose()
    finally:
        release.set()
    assert stopped, "the arm kept moving while the server's loop was held"
    assert distance(where, goal) > 0.05         # stopped early, not at the plan's end
    if not cancel:
        got, err = run_out(it)
        assert err is not None and err.code.name == "ABORTED"
        assert got[-1].state == "STALLED" and "heartbeat" in got[-1].message
    assert wait_until(lambda: not c.get_arm(r.name).busy, timeout=5)
    assert c.get_arm(r.name).state == "STALLED"
    assert r.setpoints() == sent and distance(r.pose(), where) < 1e-6


def _settled(r, quiet: float = 0.2, timeout: float = 3.0) -> bool:
    """Whether the arm came to rest and its controller received nothing for ``quiet`` s (the
    stop's own last command included) within ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not wait_until(lambda: not r.moving(), timeout=deadline - time.monotonic(), poll=0.01):
            return False
        n = r.setpoints()
        time.sleep(quiet)
        if r.setpoints() == n and not r.moving():
            return True
    return False


def test_a_tracking_error_stops_the_arm_aborted():
    """An arm that cannot keep up (this simulated UR moves at most 0.05 m/s) is stopped once
    the actual pose is further behind than the arm spec's max_tracking."""
    r = URRig(sim_args=("--max-linear-speed", "0.05"), max_tracking=0.002)
    try:
        r.reset()
        with serve([r]) as server, Client(server.target) as c:
            got, err = run_out(c.execute(r.name, [r.home, offset(r.home, dx=0.15)], LIMITS))
            assert err is not None and err.code.name == "ABORTED", got[-1:]
            assert got[-1].state == "TRACKING_ERROR" and "max_tracking" in got[-1].message
            assert c.get_arm(r.name).state == "TRACKING_ERROR"
        assert distance(r.pose(), offset(r.home, dx=0.15)) > 0.05 and not r.moving()
    finally:
        r.close()


def test_a_plan_that_leaves_the_workspace_ends_limited_aborted():
    r = URRig(limits=_workspace_below_x(0.43))
    try:
        r.reset()
        with serve([r]) as server, Client(server.target) as c:
            got, err = run_out(c.execute(r.name, [r.home, offset(r.home, dx=0.05)], LIMITS))
            assert err is not None and err.code.name == "ABORTED", got[-1:]
            # the box's edge, or on a starved machine a late set-point's speed: a limit either way
            assert got[-1].state == "LIMITED" and "limits." in got[-1].message, got[-1].message
    finally:
        r.close()


def _workspace_below_x(x: float):
    from dqpose.drivers.base import Limits
    return Limits(workspace_max=(x, 1.0, 1.2))


def test_an_execute_right_after_a_cancel_is_never_internal(rig):
    """The same without from_current, with the plan a client had ready: the arm brakes to a
    stop near where the plan starts, so it runs, or is refused as not starting there; never
    INTERNAL ("a plan is already running")."""
    r, c, _ = rig
    for i in range(20):
        assert wait_until(lambda: not r.moving(), timeout=5)
        here = r.arm.tool_pose()[1]
        it = c.execute(r.name, [here, offset(here, dy=0.05 if i % 2 else -0.05)], SLOW)
        first = next(it)
        assert first.state == "WORKING", first.message
        it.close()
        got, err = run_out(c.execute(r.name, [here, offset(here, dz=0.005)], LIMITS))
        if err is None:
            assert got[-1].state == "FINISHED"
        elif err.code.name == "ABORTED":
            # a starved machine: the control loop came late for a set-point, which the arm
            # refuses as over its limits and stops (a safety stop, not INTERNAL)
            assert got[-1].state == "LIMITED" and "late for the set-point" in got[-1].message, (
                got[-1].message)
        else:
            assert err.code.name == "FAILED_PRECONDITION", err
            assert err.details.startswith("plan.waypoints[0].pose"), err.details
