"""dqpose.handeye.readings: malformed input named by its field."""
from dataclasses import replace

import numpy as np
import pytest

from dqpose import handeye
from dqpose.errors import FieldError
from tests import _handeye as H


# ---- malformed input ---------------------------------------------------------------------------
def test_malformed_input_named():
    s = H.scene(5, seed=7)
    F, C = s.base_flange.copy(), s.camera_target.copy()
    bad = F.copy()
    bad[3, 2] = np.nan
    with pytest.raises(FieldError, match=r"^base_flange\[3\]: .*NaN"):
        handeye.calibrate(bad, C)
    bad = C.copy()
    bad[2, :4] *= 1.5
    with pytest.raises(FieldError, match=r"^camera_target\[2\]: .*unit"):
        handeye.calibrate(F, bad)
    with pytest.raises(FieldError, match=r"^camera_target: 4 poses for 5"):
        handeye.calibrate(F, C[:4])
    with pytest.raises(FieldError, match=r"^base_flange: expected shape"):
        handeye.calibrate(F[:, :7], C)
    with pytest.raises(FieldError, match=r"^setup: "):
        handeye.calibrate(F, C, "eye_on_hand")
    with pytest.raises(FieldError, match=r"^camera_covariance: not symmetric"):
        handeye.calibrate(F, C, camera_covariance=np.triu(np.ones((6, 6))))
    with pytest.raises(FieldError, match=r"^camera_covariance: expected shape"):
        handeye.calibrate(F, C, camera_covariance=np.eye(5))
    with pytest.raises(FieldError, match=r"^camera_covariance: needed"):
        handeye.calibrate(F, C, robot_covariance=np.eye(6))
    with pytest.raises(FieldError, match=r"^candidates: "):
        c = handeye.calibrate(F, C)
        handeye.next_best_pose(c, F, C, np.zeros((0, 8)))
    # a Calibration without its information matrix (as a client may build one)
    with pytest.raises(FieldError, match=r"^calibration: "):
        handeye.next_best_pose(replace(c, information=None), F, C, F[:1])
