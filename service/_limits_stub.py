"""Stand-in for ``service.trajectory.Limits`` until the trajectory branch is merged.

The issue-10 contract defines ``Limits`` in :mod:`service.trajectory`; :mod:`service.smoothing`
imports it from here meanwhile. At the merge this file is deleted and the import in
``service/smoothing.py`` points at ``service.trajectory``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields


@dataclass(frozen=True)
class Limits:
    """Limits of the tool point (linear) and of the tool (angular), as norms, in the base frame."""
    max_linear_velocity: float                    # m/s      required > 0
    max_angular_velocity: float                   # rad/s    required > 0
    max_linear_acceleration: float                # m/s^2    required > 0
    max_angular_acceleration: float               # rad/s^2  required > 0
    max_linear_jerk: float = 0.0                  # m/s^3    0 = no limit
    max_angular_jerk: float = 0.0                 # rad/s^3  0 = no limit

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            try:
                v = float(v)
            except (TypeError, ValueError):
                raise ValueError(f"limits.{f.name}: expected a number, got {v!r}") from None
            if not math.isfinite(v):
                raise ValueError(f"limits.{f.name}: {v!r} is not finite")
            jerk = f.name.endswith("_jerk")
            if v < 0 or (v == 0 and not jerk):
                need = ">= 0 (0 = no limit)" if jerk else "> 0"
                raise ValueError(f"limits.{f.name}: {v!r} must be {need}")
            object.__setattr__(self, f.name, v)
