"""What :func:`dqpose.handeye.calibrate` returns: the :class:`Calibration` and its
:class:`Rejection` s (conventions in :mod:`dqpose.handeye`)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np


@dataclass(frozen=True)
class Rejection:
    """A sample the χ² gate flagged, and why (left out in robust mode)."""
    index: int
    reason: str


@dataclass(frozen=True)
class Calibration:
    setup: str
    x: np.ndarray             # (8,) eye_in_hand: T_flange_camera; eye_to_hand: T_base_camera
    z: np.ndarray             # (8,) eye_in_hand: T_base_target;  eye_to_hand: T_flange_target
    covariance_x: np.ndarray  # (6,6) rotation first, right perturbation T·Exp(ξ) (GTSAM Pose3)
    covariance_z: np.ndarray  # (6,6) same convention
    residuals: np.ndarray     # (n,2) per sample: rotation (rad), then the target's position (m)
    warnings: tuple[str, ...]
    inliers: Optional[np.ndarray] = None                 # (n,) bool: samples in the answer
    rejected: tuple[Rejection, ...] = ()
    covariance: Optional[np.ndarray] = None              # (12,12) joint, [X; Z]
    information: Optional[np.ndarray] = None             # (12,12) its inverse, for next_best_pose
    noise_model: str = "estimated"                       # "given" or "estimated"
    camera_covariance: Optional[np.ndarray] = None       # (6,6) or (n,6,6) as used
    robot_covariance: Optional[np.ndarray] = None        # (6,6), (n,6,6) or None (exact robot)
    residual_covariance: Optional[np.ndarray] = None     # (n,6,6) Σ_r,i at the optimum
    nis: Optional[np.ndarray] = None                     # (n,) standardised residual, χ²₆
    leave_one_out: Optional[np.ndarray] = None           # (n,2) X moves (rad, m) without each
    closed_form_x: Optional[np.ndarray] = None           # (8,) the closed form's X
    closed_form_z: Optional[np.ndarray] = None
    agreement: tuple[float, float, float] = (0.0, 0.0, 0.0)  # closed form vs X: rad, m, NEES
    rotation_condition: float = 0.0     # condition number of the rotation information
    excitation: float = 0.0             # its smallest eigenvalue as an RMS angle (rad)
    iterations: int = 0
    readings: tuple[tuple[str, float, float], ...] = ()  # (reading, median rad, median m)
    reprojection: Optional[np.ndarray] = None  # (n,) RMS px per view, when corners were given
    focal_scale: float = 1.0            # the focal lengths' refined scale (refine_focal)
    focal_sigma: float = 0.0            # its standard deviation
    pixel_sigma: float = 0.0            # corner noise (px), given or estimated
    camera_scale: tuple[float, float] = (1.0, 0.0)  # best scale of the camera's translations, σ
