"""The readings plausibility tells apart (service/handeye/readings.py): a mount near the base is
not taken for inverted poses."""
from __future__ import annotations

import numpy as np

from dqpose import dq, handeye
from tests import _handeye


def test_target_near_the_base_is_no_warning():
    """A noise-free scene with the board 0.21 m from the robot base is a real mount: the
    inverted reading is implausible too (its fixed part would be the camera, ~0.1 m from the
    base), so there is nothing to warn about."""
    s = _handeye.scene(12, "eye_in_hand", "wrist", camera_noise=(0.0, 0.0), seed=3)
    t = dq.to_pose(s.z)[1]
    shift = _handeye.pose([0.0, 0.0, 0.0], 0.21 * t / np.linalg.norm(t) - t)
    F = dq.normalize(dq.mul(shift, s.base_flange))            # the whole world moved: Z = shift Z
    cal = handeye.calibrate(F, s.camera_target)
    assert abs(np.linalg.norm(dq.to_pose(cal.z)[1]) - 0.21) < 1e-6
    assert cal.warnings == ()
