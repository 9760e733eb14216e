"""Other readings of the data: the setup swapped or the camera poses inverted (refused when they
fit far better than the reading given), and the two that fit (nearly) as well as the right one,
so that the residuals cannot refuse them and only plausibility tells: both poses inverted
(``T_flange_base`` and ``T_target_camera``: ``F⁻¹ Z C⁻¹ = X``, X and Z exchanged); the camera's
translations at another scale (a wrong board size) are :mod:`~dqpose.handeye.scale`'s.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from dqpose import dq, lie
from dqpose.errors import Infeasible
from dqpose.handeye.closed_form import closed_form
from dqpose.handeye.setups import EYE_IN_HAND, other_setup, reading

if TYPE_CHECKING:
    from dqpose.handeye.checks import Prepared

_READING_FACTOR = 5.0                  # another reading fits this many times better: refuse
_MAX_MOUNT = 1.0                       # (m) a flange-mounted camera or target farther, or
_MIN_FIXED = 0.25                      # (m) a fixed one nearer the base's origin: warn
                                       # (only when both poses inverted would be plausible)


def _spread(A, C, X, Z, use):
    """Median rotation (rad) and position (m) of the per-sample ``A_i X C_i`` about ``Z``."""
    E = dq.mul(dq.mul(dq.mul(dq.inv(Z), A[use]), X), C[use])
    ang = 2.0 * np.arctan2(np.linalg.norm(E[:, 1:4], axis=1), np.abs(E[:, 0]))
    pos = np.linalg.norm(dq.to_pose(E)[1], axis=1)
    return float(np.median(ang)), float(np.median(pos))


def compare_readings(F, A, C, setup, use, closed, s_th, s_d) -> tuple:
    """``(reading, median rad, median m)`` of the closed form's fit of the reading given
    (``closed``), the setup swapped and the camera poses inverted, over the samples ``use``;
    ``Infeasible`` when another fits far better (``s_th``, ``s_d``: the robust σ of the motions'
    angle and pitch differences). Both swapped is no alternative: ``F⁻¹ Z C⁻¹ = X`` is the same
    equation with X and Z exchanged."""
    readings = []
    other = other_setup(setup)
    for name, Ar, Cr in ((setup, A, C),
                         (other, reading(F, other), C),
                         (f"{setup}, camera_target inverted", A, dq.inv(C))):
        res = closed if Ar is A and Cr is C else closed_form(Ar, Cr, use)
        if res is None:
            continue
        readings.append((name,) + _spread(Ar, Cr, res[0], res[1], use))
    given = readings[0]
    best = min(readings[1:], key=lambda r: r[1] / s_th + r[2] / s_d, default=None)
    if best is not None and (given[1] > _READING_FACTOR * best[1] + np.radians(0.05)
                             and given[2] > _READING_FACTOR * best[2] + 1e-3):
        hint = ("the setup is swapped, or base_flange holds T_flange_base"
                if "inverted" not in best[0] else
                "camera_target holds T_target_camera" if best[0].startswith(setup) else
                "the setup is swapped and camera_target holds T_target_camera")
        raise Infeasible(f"base_flange, camera_target: the data fit {best[0]} far better than "
                         f"{setup} as given (median residual {np.degrees(best[1]):.3g}° / "
                         f"{1e3 * best[2]:.3g} mm against {np.degrees(given[1]):.3g}° / "
                         f"{1e3 * given[2]:.3g} mm): {hint}?")
    return tuple(readings)


@dataclass(frozen=True)
class _Reading:
    reach_ok: bool    # the flange-mounted part near the flange
    base_ok: bool     # the fixed part off the base
    front: bool       # the target in front of the camera (z > 0 in T_camera_target), every sample
    behind: bool      # ... behind it in every sample
    says: str

    @property
    def mount_ok(self) -> bool:
        return self.reach_ok and self.base_ok


def plausible(p: Prepared, X, Z, inlier, inverted: bool = False) -> _Reading:
    """How plausible the answer ``(X, Z)`` is as a mount (``inverted``: the reading of both poses
    inverted, where ``(Z, X)`` of the given fit is the answer and ``C⁻¹`` the camera poses)."""
    mount, fixed = (X, Z) if p.setup == EYE_IN_HAND else (Z, X)
    reach = float(np.linalg.norm(dq.to_pose(mount)[1]))
    base = float(np.linalg.norm(dq.to_pose(fixed)[1]))
    C = p.C[inlier]
    depth = dq.to_pose(dq.inv(C) if inverted else C)[1][:, 2]
    what = ("camera", "target") if p.setup == EYE_IN_HAND else ("target", "camera")
    return _Reading(reach <= _MAX_MOUNT, base >= _MIN_FIXED, bool(np.all(depth > 0.0)),
                    bool(np.all(depth < 0.0)),
                    f"the {what[0]} comes out {reach:.2f} m from the flange and the {what[1]} "
                    f"{base:.2f} m from the robot base")


def inverse_noise(T, S):
    return None if S is None else lie.cov_inverse(T, S)


def moved(a, b) -> float:
    return float(np.linalg.norm(dq.to_pose(a)[1] - dq.to_pose(b)[1]))
