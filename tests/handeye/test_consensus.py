"""The consensus the fit starts from (service/handeye/consensus.py): outliers that screw
congruence lets through no longer anchor the fit."""
import numpy as np

from dqpose import handeye
from tests import _handeye as H
from tests.bench.fusion_scenes import nees
from tests.handeye._cases import flipped


def _flips(given):
    """The 40 seeds of 12 samples, 30 % of them marker flips of 1–4°: ``(flipped indices,
    calibration, scene)`` each."""
    for seed in range(40):
        s, C, bad = flipped(12, 0.3, (1.0, 4.0), seed)
        kw = {"camera_covariance": s.camera_covariance} if given else {}
        yield bad, handeye.calibrate(s.base_flange, C, **kw), s


def test_small_marker_flips_do_not_anchor_the_fit_with_the_noise_given():
    """12 samples, 30 % of them marker flips of 1–4° (rotation errors across the motions' axes,
    which screw congruence lets through), noise 0.1° / 0.5 mm given. The fit started on every
    sample that passed screw congruence: 9 of 40 seeds came out 1.1–4.4 mm off at NEES 40–346.
    From the consensus of minimal sets every flip is rejected by index in every seed, and X is
    as accurate as its covariance says."""
    for bad, cal, s in _flips(True):
        assert set(bad.tolist()) <= {r.index for r in cal.rejected}, s.seed
        assert nees(cal.x, cal.covariance_x, s.x) < 30.0, s.seed
        assert H.pose_error(cal.x, s.x)[1] < 2.0, s.seed


def test_small_marker_flips_do_not_inflate_the_estimated_noise():
    """The same data with the noise estimated: started on every sample, the flips inflated the
    estimated rotation noise up to 11 times (up to 1.1° for 0.1°) and so hid themselves; 69 of
    160 were rejected. From the consensus 153 were: the flips of 1.0–1.3° it let into the start
    still took the estimated rotation noise to 0.2–0.26°. With the robust screen
    (:func:`dqpose.handeye.outliers._screened`) 159 are, and X stays consistent; the one kept
    (seed 8) is one of two 1° flips among 10 samples that inflate the noise together."""
    missed = []
    for bad, cal, s in _flips(False):
        missed += [(s.seed, int(k)) for k in set(bad.tolist()) - {r.index for r in cal.rejected}]
        assert nees(cal.x, cal.covariance_x, s.x) < 30.0, s.seed
        assert H.pose_error(cal.x, s.x)[1] < 2.0, s.seed
    assert len(missed) <= 1, missed


def test_healthy_data_start_from_every_sample():
    """On healthy data the consensus keeps every sample: nothing is rejected, and the answer is
    the one the closed form's start gives (the same optimum)."""
    for seed in range(10):
        s = H.scene(20, "eye_in_hand", "wrist", camera_noise=(0.1, 0.5), seed=seed)
        for kw in ({}, {"camera_covariance": s.camera_covariance}):
            cal = handeye.calibrate(s.base_flange, s.camera_target, **kw)
            assert np.all(cal.inliers) or len(cal.rejected) <= 1, seed
