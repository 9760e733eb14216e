"""05 — Stream a smooth tool path into a UR arm (here the simulated controller).

Starts the simulated UR controller (it speaks RTDE, so the real `ur_rtde` client drives it),
plans a 1.5 s move along a straight tool line with a smooth time law, and servos it at the
controller rate through `URArm`, which checks every set-point against speed, acceleration and
workspace limits. Against a real arm, drop the simulator and pass the robot's address.

    .venv/bin/python examples/05_servo_ur_arm.py
"""
import numpy as np

from dqpose import dq
from dqpose.drivers.base import LimitError
from dqpose.drivers.sim.ur import URSimProcess
from dqpose.drivers.ur import URArm
from dqpose.interpolate import interpolate
from dqpose.profile import smoothstep

with URSimProcess() as sim, URArm(sim.host) as arm:
    print(f"connected to {sim.host}, controller period {arm.period * 1e3:.0f} ms")
    start = arm.tool_pose()[1]
    turn = dq.from_pose([np.cos(np.radians(10)), 0, 0, np.sin(np.radians(10))], [0, 0, 0])
    q, t = dq.to_pose(dq.mul(turn, start))
    goal = dq.from_pose(q, dq.to_pose(start)[1] + [0.10, -0.05, 0.02])   # 11 cm, 20 deg

    T = 1.5
    k = np.arange(int(round(T / arm.period)) + 1) * arm.period
    s = smoothstep(k / T)                # starts and ends at rest, bounded acceleration
    path = interpolate([0.0, 1.0], np.array([start, goal]), s, "tool_linear")

    for pose in path[1:]:
        arm.servo(pose)                   # one set-point per controller period
    arm.stop()
    end = arm.tool_pose()[1]
    off = np.linalg.norm(dq.to_pose(end)[1] - dq.to_pose(goal)[1])
    print(f"streamed {len(path) - 1} set-points; the arm ended {off * 1e3:.3f} mm from the goal")
    assert off < 1e-3

    try:                                  # a jump is refused and the arm is stopped
        arm.servo(dq.from_pose(q, dq.to_pose(goal)[1] + [0.2, 0, 0]))
    except LimitError as e:
        print("refused:", e)
