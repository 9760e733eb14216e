"""The two hand-eye setups and the equation each poses, ``A_i · X · C_i = Z`` on absolute poses.

**eye_in_hand** (camera on the flange): ``X = T_flange_camera``, ``Z = T_base_target``,
``A_i = base_flange_i``. **eye_to_hand** (camera fixed, target on the flange):
``X = T_base_camera``, ``Z = T_flange_target``, ``A_i = base_flange_i⁻¹``. ``C_i`` is the
detector's ``camera_target_i`` in both; the rest of the package is written for ``A_i X C_i = Z``.
"""
from __future__ import annotations

import numpy as np

from dqpose import dq
from dqpose.errors import FieldError

SETUPS = ("eye_in_hand", "eye_to_hand")
EYE_IN_HAND, EYE_TO_HAND = SETUPS


def checked_setup(setup) -> str:
    if setup not in SETUPS:
        raise FieldError(f"setup: expected one of {', '.join(SETUPS)}, got {setup!r}")
    return setup


def reading(F, setup):
    """The ``A_i`` of the flange poses ``F`` in ``setup``."""
    return F if setup == EYE_IN_HAND else dq.inv(F)


def other_setup(setup: str) -> str:
    """The setup that is not ``setup``."""
    return EYE_TO_HAND if setup == EYE_IN_HAND else EYE_IN_HAND


def view_at(base_flange, x, z, setup: str = EYE_IN_HAND) -> np.ndarray:
    """The ``T_camera_target`` a calibration ``(x, z)`` predicts at the robot poses
    ``base_flange``: eye-in-hand ``x⁻¹ · base_flange⁻¹ · z``, eye-to-hand
    ``x⁻¹ · base_flange · z``."""
    if checked_setup(setup) == EYE_IN_HAND:
        return dq.mul(dq.mul(dq.inv(x), dq.inv(base_flange)), z)
    return dq.mul(dq.mul(dq.inv(x), base_flange), z)


def flange_for(camera_target, x, z, setup: str = EYE_IN_HAND) -> np.ndarray:
    """The ``T_base_flange`` at which a calibration ``(x, z)`` has the camera see the target at
    ``camera_target`` (the inverse of :func:`view_at`)."""
    if checked_setup(setup) == EYE_IN_HAND:
        return dq.mul(dq.mul(z, dq.inv(camera_target)), dq.inv(x))
    return dq.mul(dq.mul(x, camera_target), dq.inv(z))
