"""06 — Plan a motion through waypoints under linear and angular limits, in process.

Three waypoints with a 2 cm blend at the middle corner and a quarter turn of the tool on the
way; TOOL_LINEAR keeps the tool point on the straight segments. The limits are checked on the
samples themselves (finite differences at 1 kHz), the way an observer of the arm would see them,
and the planner says which limit decided each segment.

    .venv/bin/python examples/06_plan_a_trajectory.py
"""
import numpy as np

from dqpose import dq, trajectory

limits = trajectory.Limits(max_linear_velocity=0.25, max_angular_velocity=1.0,
                           max_linear_acceleration=1.0, max_angular_acceleration=2.0,
                           max_linear_jerk=10.0, max_angular_jerk=20.0)
down = np.array([0.0, 1.0, 0.0, 0.0])                       # tool z pointing down
turn = np.array([np.cos(np.pi / 8), 0.0, 0.0, np.sin(np.pi / 8)])
waypoints = [
    trajectory.Waypoint(dq.from_pose(down, [0.40, 0.00, 0.30])),
    trajectory.Waypoint(dq.from_pose(dq.mul(np.r_[turn, 0, 0, 0, 0], np.r_[down, 0, 0, 0, 0])[:4],
                                     [0.55, 0.00, 0.30]), blend_radius=0.02),
    trajectory.Waypoint(dq.from_pose(down, [0.55, 0.15, 0.25])),
]
plan = trajectory.plan(waypoints, limits, "tool_linear")
print(f"duration {plan.duration:.3f} s")
for i, s in enumerate(plan.segments):
    print(f"  segment {i}: {s.start:.3f} .. {s.start + s.duration:.3f} s, bound by {s.binding}")

samples = plan.at_rate(1000.0)
d = trajectory.derivatives(samples.time, samples.pose)
slack = 1.01            # finite differences of a piecewise-constant jerk overshoot a little
for name, values in (("linear velocity", d.velocity), ("angular velocity", d.angular_velocity),
                     ("linear acceleration", d.acceleration),
                     ("angular acceleration", d.angular_acceleration)):
    peak = np.linalg.norm(values, axis=1).max()
    bound = getattr(limits, "max_" + name.replace(" ", "_"))
    print(f"  peak {name}: {peak:.4f} (limit {bound:g})")
    assert peak <= bound * slack

# the ends are the waypoints, and before the blend the tool point is on the straight line
for k, w in ((0, waypoints[0]), (-1, waypoints[-1])):
    sign = np.sign(samples.pose[k, :4] @ w.pose[:4])          # q and -q are one pose
    assert np.allclose(sign * samples.pose[k], w.pose, atol=1e-12)
first = d.position[samples.time < plan.segments[1].start]
assert np.abs(first[:, 1:] - [0.0, 0.30]).max() < 1e-9
print("limits hold on every sample; the tool point stays on the line until the blend")
