"""07 — Execute a plan on a UR arm through the server (here the simulated controller).

Starts the simulated UR controller and a dqpose server that owns the arm (what `dqpose serve
--arm ur=ur:HOST` does), then asks the server to run a plan on it: the server's executor feeds
the arm at its own 500 Hz from a buffer, never paced by the network, and streams back the
commanded and actual poses. A second plan is abandoned half way: the client leaves, the arm
stops. A plan that does not start where the arm is gets refused, never jumped to.

    .venv/bin/python examples/07_execute_on_ur_arm.py
"""
import numpy as np

from dqpose import dq, drivers, trajectory
from dqpose.cli.common import local_server
from dqpose.drivers.executor import Executor
from dqpose.drivers.sim.ur import URSimProcess
from dqpose.rpc.client import Client, RpcError

limits = trajectory.Limits(max_linear_velocity=0.1, max_angular_velocity=0.5,
                           max_linear_acceleration=0.5, max_angular_acceleration=1.0,
                           max_linear_jerk=5.0, max_angular_jerk=10.0)

# stale_after: the simulator shares this machine, so a 0.1 s pause in its data is not a lost arm
with URSimProcess() as sim, drivers.open_arm(f"ur:{sim.host}", stale_after=0.5) as arm, \
        local_server(arms={"ur": arm}, executor=Executor) as target, Client(target) as client:
    start = arm.tool_pose()[1]
    q, t = dq.to_pose(start)
    goal = dq.from_pose(q, t + [0.08, -0.04, 0.02])

    feedback = list(client.execute("ur", [start, goal], limits))
    end = arm.tool_pose()[1]
    off = np.linalg.norm(dq.to_pose(end)[1] - dq.to_pose(goal)[1])
    print(f"{feedback[-1].state} after {feedback[-1].time:.3f} s of plan, "
          f"{len(feedback)} feedback messages; the arm ended {off * 1e3:.3f} mm from the goal")
    assert feedback[-1].state == "FINISHED" and off < 1e-3

    run = client.execute("ur", [end, start], limits)      # back again, but leave half way
    for fb in run:
        if fb.time > 0.5:
            break
    run.close()                                            # cancels the call: the arm stops
    moved = np.linalg.norm(dq.to_pose(arm.tool_pose()[1])[1] - dq.to_pose(start)[1])
    print(f"left the second plan at 0.5 s: the arm stopped {moved * 1e3:.1f} mm short of its end")
    assert moved > 0.01

    try:
        list(client.execute("ur", [start, end], limits))   # the arm is not at `start` any more
    except RpcError as e:
        print(f"refused: {e.code.name}: {e.details[:100]}...")
        assert e.code.name == "FAILED_PRECONDITION"
