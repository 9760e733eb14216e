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

from service import dq


class Peaks(NamedTuple):
    """Largest norms over the samples: [velocity, acceleration, jerk] of the tool point (linear)
    and of the tool's rotation (angular, from the true rotations, not a coordinate chart)."""
    linear: np.ndarray
    angular: np.ndarray


def rotation_rates(q: np.ndarray, dt: float) -> np.ndarray:
    """Base-frame angular velocity between consecutive unit quaternions (N, 4) -> (N-1, 3)."""
    r = np.zeros((len(q), 8))
    r[:, :4] = q
    rel = dq.mul(r[1:], dq.conj(r[:-1]))          # q_{i+1} q_i^*: the rotation in the base frame
    rel[rel[:, 0] < 0] *= -1
    return 2 * dq.log(rel)[:, :3] / dt


def derivatives(times: np.ndarray, poses: np.ndarray):
    """Linear and angular (velocity, acceleration, jerk) arrays from uniformly spaced samples."""
    dt = float(times[1] - times[0])
    q, p = dq.to_pose(poses)
    v = np.diff(p, axis=0) / dt
    w = rotation_rates(q, dt)
    lin = [v, np.diff(v, axis=0) / dt]
    ang = [w, np.diff(w, axis=0) / dt]
    lin.append(np.diff(lin[1], axis=0) / dt)
    ang.append(np.diff(ang[1], axis=0) / dt)
    return lin, ang


def peaks(times: np.ndarray, poses: np.ndarray) -> Peaks:
    lin, ang = derivatives(times, poses)
    top = lambda xs: np.array([np.linalg.norm(x, axis=1).max(initial=0.0) for x in xs])
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
    for peak, lim, eps in zip(np.concatenate([p.linear, p.angular]), lim_lin + lim_ang, 2 * tuple(noise)):
        if lim > 0:
            worst = max(worst, (peak - eps) / lim - 1.0)
    return worst
