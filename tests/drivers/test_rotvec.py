"""dqpose.drivers.rotvec: rotation vectors <-> quaternions <-> dual quaternions, checked against
SciPy and against closed forms that are exact where the tested code uses series."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dqpose import dq
from dqpose.drivers.rotvec import (
    pose_from_rotvec,
    quat_from_rotvec,
    rotvec_from_pose,
    rotvec_from_quat,
)


def _random_rotvecs(rng, n, max_angle=np.pi):
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    return axis * rng.uniform(0, max_angle, size=(n, 1))


def _same_rotation(q1, q2, atol):
    """q and -q are the same rotation."""
    d = np.minimum(np.abs(q1 - q2).max(axis=-1), np.abs(q1 + q2).max(axis=-1))
    return np.all(d <= atol)


# ------------------------------------------------------------------ rotation vectors
def test_quat_from_rotvec_matches_scipy(rng):
    r = _random_rotvecs(rng, 500, max_angle=2 * np.pi)
    q = quat_from_rotvec(r)
    ref = Rotation.from_rotvec(r).as_quat(scalar_first=True)
    assert _same_rotation(q, ref, 1e-15)
    assert np.allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-15)


def test_rotvec_round_trip(rng):
    r = _random_rotvecs(rng, 500)
    assert np.allclose(rotvec_from_quat(quat_from_rotvec(r)), r, rtol=0, atol=2e-15)
    q = rng.normal(size=(500, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    assert _same_rotation(quat_from_rotvec(rotvec_from_quat(q)), q, 2e-15)


@pytest.mark.parametrize("angle", [0.0, 1e-300, 1e-12, 1e-8, 1e-5, 9.999e-4, 1e-3, 1.0001e-3, 0.01])
def test_exact_near_zero(angle):
    axis = np.array([2.0, -3.0, 6.0]) / 7.0
    r = angle * axis
    q = quat_from_rotvec(r)
    # sin(a/2) and cos(a/2) have no cancellation at small a: an exact reference
    exact = np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])
    assert np.allclose(q, exact, rtol=4e-16, atol=0)
    back = rotvec_from_quat(q)
    assert np.allclose(back, r, rtol=4e-16, atol=0)


@pytest.mark.parametrize("gap", [0.0, 1e-15, 1e-12, 1e-9, 1e-6, 1e-3])
def test_exact_near_pi(gap):
    axis = np.array([2.0, -3.0, 6.0]) / 7.0
    r = (np.pi - gap) * axis
    back = rotvec_from_quat(quat_from_rotvec(r))
    assert np.allclose(back, r, rtol=0, atol=4e-15)
    # past pi the short way round flips the axis
    r2 = (np.pi + gap) * axis
    back2 = rotvec_from_quat(quat_from_rotvec(r2))
    if gap > 0:
        assert np.allclose(back2, -(np.pi - gap) * axis, rtol=0, atol=4e-15)
    assert np.linalg.norm(back2) <= np.pi + 1e-15


def test_sign_of_quaternion_does_not_matter(rng):
    q = rng.normal(size=(200, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    assert np.allclose(rotvec_from_quat(q), rotvec_from_quat(-q), atol=1e-15)
    assert np.all(np.linalg.norm(rotvec_from_quat(q), axis=-1) <= np.pi + 1e-15)


# ------------------------------------------------------------------ UR poses and dual quaternions
def test_pose_from_rotvec_matches_matrix(rng):
    p = np.concatenate([rng.normal(size=(300, 3)), _random_rotvecs(rng, 300)], axis=1)
    T = np.tile(np.eye(4), (300, 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(p[:, 3:]).as_matrix()
    T[:, :3, 3] = p[:, :3]
    assert np.allclose(dq.to_matrix(pose_from_rotvec(p)), T, atol=1e-14)


def test_pose_round_trips(rng, make_dqs):
    p = np.concatenate([rng.normal(size=(300, 3)), _random_rotvecs(rng, 300)], axis=1)
    assert np.allclose(rotvec_from_pose(pose_from_rotvec(p)), p, atol=1e-14)
    poses = make_dqs(300)
    back = pose_from_rotvec(rotvec_from_pose(poses))
    assert _same_rotation(back, poses, 1e-13)
    # single pose in, single pose out
    assert pose_from_rotvec(p[0]).shape == (8,) and rotvec_from_pose(poses[0]).shape == (6,)


def test_bad_input_names_the_argument():
    with pytest.raises(ValueError, match=r"^p6: expected shape \(\.\.\., 6\)"):
        pose_from_rotvec([0.0, 1.0, 2.0])
    with pytest.raises(ValueError, match="^p6: contains NaN"):
        pose_from_rotvec([0, 0, 0, np.nan, 0, 0])
    with pytest.raises(ValueError, match=r"^q\[1\]: quaternion norm 2 is not unit"):
        rotvec_from_quat([[1.0, 0, 0, 0], [2.0, 0, 0, 0]])
    with pytest.raises(ValueError, match="^rotvec: expected shape"):
        quat_from_rotvec(np.zeros((2, 4)))
    with pytest.raises(ValueError, match="^pose: expected shape"):
        rotvec_from_pose(np.zeros(7))
