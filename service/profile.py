"""Time laws for point-to-point moves: how far along a path of known length a move is at time t.

``Trapezoid`` is the one trapezoidal velocity profile the drivers and simulators run their moves
on (constant acceleration, cruise, constant deceleration; a triangle when the path is too short
to reach the speed). ``smoothstep`` is the cubic ``3s^2 - 2s^3`` for a caller that wants a
normalised rest-to-rest law. NumPy in and out; vectorised over ``t``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["Trapezoid", "smoothstep"]


def _positive(name: str, v) -> float:
    v = float(v)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name}: must be a positive finite number, got {v!r}")
    return v


@dataclass(frozen=True)
class Trapezoid:
    """Rest-to-rest motion over ``length`` with speed at most ``speed`` and acceleration at most
    ``accel`` (any consistent units: metres, radians, or a path parameter). ``length`` 0 is a
    move that is already over."""

    length: float
    speed: float
    accel: float

    def __post_init__(self):
        L = float(self.length)
        if not (math.isfinite(L) and L >= 0):
            raise ValueError(f"length: must be a finite number >= 0, got {self.length!r}")
        object.__setattr__(self, "length", L)
        object.__setattr__(self, "speed", _positive("speed", self.speed))
        object.__setattr__(self, "accel", _positive("accel", self.accel))

    @property
    def peak_speed(self) -> float:
        """The cruise speed, or the top of the triangle when ``speed`` is never reached."""
        return min(self.speed, math.sqrt(self.length * self.accel))

    @property
    def t_accel(self) -> float:
        """Duration of the acceleration (and of the deceleration) phase."""
        return self.peak_speed / self.accel

    @property
    def duration(self) -> float:
        v = self.peak_speed
        return 0.0 if v == 0 else self.length / v + v / self.accel

    def __call__(self, t):
        """Distance travelled at time ``t`` (scalar or array), clamped to ``[0, length]``."""
        t = np.asarray(t, dtype=np.float64)
        a, v, ta, T = self.accel, self.peak_speed, self.t_accel, self.duration
        t = np.clip(t, 0.0, T)
        r = T - t
        cruise = 0.5 * a * ta * ta + v * (t - ta)
        s = np.where(t < ta, 0.5 * a * t * t,
                     np.where(r < ta, self.length - 0.5 * a * r * r, cruise))
        s = np.clip(s, 0.0, self.length)
        return float(s) if s.ndim == 0 else s

    def fraction(self, t):
        """``self(t) / length``: 0 at the start, 1 from ``duration`` on (1 for a zero length)."""
        if self.length == 0:
            return 1.0 if np.ndim(t) == 0 else np.ones(np.shape(t))
        return self(t) / self.length


def smoothstep(s):
    """``3s^2 - 2s^3`` of ``s`` clamped to [0, 1]: rest to rest, bounded acceleration."""
    s = np.clip(np.asarray(s, dtype=np.float64), 0.0, 1.0)
    out = s * s * (3.0 - 2.0 * s)
    return float(out) if out.ndim == 0 else out
