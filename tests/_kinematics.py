"""Velocity, acceleration and jerk measured on sampled poses themselves (finite differences), for
the trajectory tests and the planning benchmark: what a controller receiving the stream would see,
whichever planner produced it.

A finite difference of uniformly spaced samples is a weighted mean of the true derivative over
its stencil, so it never exceeds the derivative's true maximum norm: a planner that respects a
limit passes, up to rounding.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from dqpose import trajectory


class Peaks(NamedTuple):
    """Largest norms over the samples: [velocity, acceleration, jerk] of the tool point (linear)
    and of the tool's rotation (angular, from the true rotations, not a coordinate chart)."""
    linear: np.ndarray
    angular: np.ndarray


def derivatives(times: np.ndarray, poses: np.ndarray):
    """Linear and angular [velocity, acceleration, jerk] arrays (dqpose.trajectory.derivatives,
    the one finite-difference measure)."""
    d = trajectory.derivatives(times, poses)
    return ([d.velocity, d.acceleration, d.jerk],
            [d.angular_velocity, d.angular_acceleration, d.angular_jerk])


def peaks(times: np.ndarray, poses: np.ndarray) -> Peaks:
    lin, ang = derivatives(times, poses)

    def top(xs):
        return np.array([np.linalg.norm(x, axis=1).max(initial=0.0) for x in xs])

    return Peaks(top(lin), top(ang))


# What rounding (float64 poses near 1 m, 1 ms steps) can add to [velocity, acceleration, jerk]
# measured by finite differences: ~1e-16 / dt^k, with room for the conversions.
NOISE_1KHZ = (1e-9, 1e-6, 1e-4)


def violation(p: Peaks, limits, noise=(0.0, 0.0, 0.0)) -> float:
    """The worst ratio over the limits (jerk 0 = none) minus 1, each peak first lowered by the
    rounding ``noise`` of its order: <= 0 means every limit held."""
    lim_lin = (limits.max_linear_velocity, limits.max_linear_acceleration, limits.max_linear_jerk)
    lim_ang = (limits.max_angular_velocity, limits.max_angular_acceleration,
               limits.max_angular_jerk)
    worst = -1.0
    for peak, lim, eps in zip(np.concatenate([p.linear, p.angular]), lim_lin + lim_ang,
                              2 * tuple(noise)):
        if lim > 0:
            worst = max(worst, (peak - eps) / lim - 1.0)
    return worst
