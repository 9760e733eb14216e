"""01 — Average noisy measurements of one pose, in process.

Three sensors see the same tool pose with a few millimetres and degrees of noise, and we trust
them differently. DIB gives the exact bi-invariant weighted mean; DLB is its fast approximation.

    .venv/bin/python examples/01_average_measurements.py
"""
import numpy as np

from dqpose import dq


def angle_deg(a, b):
    """Rotation angle between two poses."""
    q = dq.mul(dq.conj(a), b)[:4]
    return np.degrees(2 * np.arctan2(np.linalg.norm(q[1:]), abs(q[0])))


# quaternions are [w, x, y, z], w first (ROS, Eigen and scipy put it last): 34.4 deg about z
true = dq.from_pose([np.cos(0.3), 0, 0, np.sin(0.3)], [0.5, 0.1, 0.3])
rng = np.random.default_rng(7)
twist = np.concatenate([rng.normal(size=(3, 3)) * np.radians(2) / 2,      # log: half angles
                        rng.normal(size=(3, 3)) * 0.003 / 2], axis=1)
measured = dq.mul(true, dq.exp(twist))          # three noisy measurements, (3, 8)
weights = np.array([1.0, 0.5, 2.0])             # e.g. inverse variances

mean, steps, residual = dq.dib(measured, weights, return_info=True)
approx = dq.dlb(measured, weights)

for name, m in (("DIB", mean), ("DLB", approx)):
    t_err = np.linalg.norm(dq.to_pose(m)[1] - dq.to_pose(true)[1])
    print(f"{name}: {angle_deg(m, true):.3f} deg and {t_err * 1e3:.2f} mm from the true pose")
print(f"DIB took {steps} steps, final residual {residual:.1e}")
print(f"DIB and DLB differ by {angle_deg(mean, approx):.2e} deg for data this close together")

# A property worth knowing: the mean does not depend on which frame the poses are expressed in.
T = dq.from_pose([np.cos(1.0), np.sin(1.0), 0, 0], [2.0, -1.0, 0.5])
moved = dq.dib(dq.mul(T, measured), weights)
assert angle_deg(moved, dq.mul(T, mean)) < 1e-9
# q and -q are the same rotation: flipping the sign of one measurement changes nothing.
flipped = measured.copy()
flipped[1] *= -1
assert angle_deg(dq.dib(flipped, weights), mean) < 1e-9
print("mean is frame-independent and sign-independent: ok")
