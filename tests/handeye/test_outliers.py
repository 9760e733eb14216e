"""The χ² gate (service/handeye/outliers.py): when it would leave too few samples to solve on,
the answer names the samples it doubts."""
from __future__ import annotations

from dqpose import handeye
from tests import _handeye


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
