"""What an Execute costs the server (R1): its waypoints are counted before anything is made of
them, and a plan's duration costs nothing on the server (the arm's control loop samples the
plan as it goes: a 20-minute plan at 500 Hz is 600,000 set-points nobody materialises), neither
when it runs nor when it is refused. The real server on 127.0.0.1, the shipped Client, the
simulated UR through ur_rtde (the arm in the server's process, so that its memory is measured
with the server's)."""
from __future__ import annotations

import tracemalloc

import pytest

from dqpose import limits, trajectory
from dqpose.rpc.client import Client, RpcError
from tests.robustness._arms import URRig, offset, serve

MAX_WAYPOINTS = 100
#: a crawl: 0.06 m at 50 um/s is a 20-minute plan
CRAWL = trajectory.Limits(max_linear_velocity=5e-5, max_angular_velocity=0.1,
                          max_linear_acceleration=0.5, max_angular_acceleration=1.0)
#: what an Execute may allocate on the server, whatever its duration (the 20-minute plan's
#: set-points alone would be 38 MB of poses)
BUDGET = 8 * 1024 * 1024


@pytest.fixture(scope="module")
def ur():
    r = URRig(process=False)
    try:
        with serve([r], limits=limits.Limits(max_execute_waypoints=MAX_WAYPOINTS)) as server:
            yield r, server
    finally:
        r.close()


def test_too_many_waypoints_are_refused_naming_the_limit(ur):
    r, server = ur
    r.reset()
    wps = [offset(r.home, dz=0.0005 * k) for k in range(MAX_WAYPOINTS + 1)]
    with Client(server.target) as c, pytest.raises(RpcError) as e:
        list(c.execute("ur", wps, CRAWL))
    assert e.value.code.name == "RESOURCE_EXHAUSTED"
    assert e.value.details == (f"plan.waypoints: {MAX_WAYPOINTS + 1} waypoints, over the "
                               f"server's limit max_execute_waypoints = {MAX_WAYPOINTS} waypoints "
                               f"(dqpose serve --max-execute-waypoints)")
    assert r.setpoints() == 0


@pytest.mark.parametrize("starts_at_arm", [True, False], ids=["runs", "refused"])
def test_a_long_plan_costs_the_server_nothing_that_grows_with_it(ur, starts_at_arm):
    r, server = ur
    r.reset()
    start = r.home if starts_at_arm else offset(r.home, dz=0.01)
    tracemalloc.start()
    try:
        with Client(server.target) as c:
            it = c.execute("ur", [start, offset(start, dx=0.06)], CRAWL)
            if starts_at_arm:
                first = next(it)
                it.close()
            else:
                with pytest.raises(RpcError) as e:
                    next(it)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    if starts_at_arm:
        assert first.state == "WORKING"
    else:
        assert e.value.code.name == "FAILED_PRECONDITION"
        assert e.value.details.startswith("plan.waypoints[0].pose")
    assert peak < BUDGET, f"{peak / 2**20:.1f} MiB allocated for a 20-minute plan"
