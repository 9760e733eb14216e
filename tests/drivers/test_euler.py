"""sxyz Euler angles against independent references (SciPy, pytransform3d)."""
import math

import numpy as np
import pytest
from pytransform3d import rotations as pr
from scipy.spatial.transform import Rotation

from dqpose import dq
from dqpose.drivers.euler import (
    dq_from_xyz_sxyz,
    matrix_from_sxyz,
    quat_from_sxyz,
    sxyz_from_quat,
    xyz_sxyz_from_dq,
)

RNG = np.random.default_rng(7)


def _angles(n):
    return np.column_stack([RNG.uniform(-np.pi, np.pi, n), RNG.uniform(-np.pi / 2, np.pi / 2, n),
                            RNG.uniform(-np.pi, np.pi, n)])


def _same_rotation(qa, qb):
    return np.abs(np.abs(np.sum(qa * qb, axis=-1)) - 1.0)


def test_matches_scipy_extrinsic_xyz():
    e = _angles(500)
    ref = Rotation.from_euler("xyz", e).as_quat(scalar_first=True)  # lowercase = static axes
    ours = quat_from_sxyz(e[:, 0], e[:, 1], e[:, 2])
    assert np.max(_same_rotation(ours, ref)) < 1e-14
    assert np.allclose(matrix_from_sxyz(e[:, 0], e[:, 1], e[:, 2]),
                       Rotation.from_euler("xyz", e).as_matrix(), atol=1e-14)


def test_matrix_is_rz_ry_rx_product():
    for rx, ry, rz in _angles(20):
        R = (pr.active_matrix_from_angle(2, rz) @ pr.active_matrix_from_angle(1, ry)
             @ pr.active_matrix_from_angle(0, rx))
        assert np.allclose(matrix_from_sxyz(rx, ry, rz), R, atol=1e-14)


def test_round_trip_recovers_angles():
    e = _angles(1000)
    back = sxyz_from_quat(quat_from_sxyz(e[:, 0], e[:, 1], e[:, 2]))
    assert np.max(np.abs(back - e)) < 1e-9
    assert np.allclose(back, Rotation.from_quat(
        quat_from_sxyz(e[:, 0], e[:, 1], e[:, 2]), scalar_first=True).as_euler("xyz"), atol=1e-9)


@pytest.mark.parametrize("ry", [math.pi / 2, -math.pi / 2])
def test_gimbal_lock_gives_same_rotation(ry):
    for rx, rz in RNG.uniform(-np.pi, np.pi, (20, 2)):
        q = quat_from_sxyz(rx, ry, rz)
        back = sxyz_from_quat(q)
        assert back[2] == 0.0
        assert abs(back[1] - ry) < 1e-7
        assert _same_rotation(quat_from_sxyz(*back), q) < 1e-14


def test_dual_quaternion_helpers():
    xyz = RNG.normal(size=(10, 3))
    e = _angles(10)
    T = dq_from_xyz_sxyz(xyz, e)
    M = dq.to_matrix(T)
    assert np.allclose(M[:, :3, 3], xyz)
    assert np.allclose(M[:, :3, :3], Rotation.from_euler("xyz", e).as_matrix(), atol=1e-12)
    t, r = xyz_sxyz_from_dq(T)
    assert np.allclose(t, xyz) and np.allclose(r, e, atol=1e-9)
