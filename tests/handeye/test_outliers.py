"""The χ² gate (service/handeye/outliers.py): when it would leave too few samples to solve on,
the answer names the samples it doubts."""
from __future__ import annotations

from dqpose import handeye
from tests import _handeye
from tests.handeye._cases import _nees


def test_gate_leaving_too_few_samples_is_not_silent():
    """A camera noise given 100× too small (in σ): nearly every sample fails the gate, the
    loop cannot leave them out (fewer than 3 would remain) and keeps them; the warning names
    them (before, the answer came with no warning at all)."""
    s = _handeye.scene(12, "eye_in_hand", "wrist", camera_noise=(0.5, 3.0), seed=2)
    cal = handeye.calibrate(s.base_flange, s.camera_target,
                            camera_covariance=s.camera_covariance * 1e-4)
    assert not cal.rejected
    doubted = [w for w in cal.warnings if "fail the χ² gate" in w]
    assert len(doubted) == 1 and doubted[0].startswith("samples 0, 1, ")


def test_a_screen_on_few_samples_never_raises():
    """10 poses of OpenCV's geometry at 0.5° / 2 mm with the noise estimated: the fit after the
    robust screen started from the trimmed noise estimate, one of whose components sat at its
    floor, and raised numpy's LinAlgError (an internal error) instead of answering. It answers
    now, within its covariance."""
    s = _handeye.scene(10, "eye_in_hand", "opencv", camera_noise=(0.5, 2.0), seed=1032)
    cal = handeye.calibrate(s.base_flange, s.camera_target)
    assert _nees(cal.x, s.x, cal.covariance_x) < 30.0
