"""Shared by the hand-eye tests: every setup with every scene geometry, poses equal up to sign, the
NEES of an estimate, and a reading as its setup gives it."""
import numpy as np

from dqpose import dq, lie
from tests import _handeye as H

CASES = [(setup, geometry) for setup in H.SETUPS for geometry in H.GEOMETRIES]


def _close(a, b, tol):
    """Poses equal up to sign, to ``tol`` in every component."""
    a, b = np.asarray(a), np.asarray(b)
    s = np.where((a[..., :4] * b[..., :4]).sum(-1, keepdims=True) < 0, -1.0, 1.0)
    return np.max(np.abs(a - s * b)) < tol


def _nees(estimate, truth, cov):
    xi = lie.se3_log(dq.mul(dq.inv(estimate), truth))
    return float(xi @ np.linalg.solve(cov, xi))


def flipped(n: int, fraction: float, tip_deg: tuple[float, float], seed: int,
            noise: tuple[float, float] = (0.1, 0.5)):
    """A wrist scene of ``n`` samples with camera noise ``noise`` (deg, mm per axis), a
    ``fraction`` of its camera poses marker-flipped: the board's rotation tipped by ``tip_deg``
    about an in-plane axis, its position unchanged. ``(scene, camera_target, flipped indices)``."""
    s = H.scene(n, "eye_in_hand", "wrist", camera_noise=noise, seed=seed)
    rng = np.random.default_rng(50_000 + seed)
    k = int(round(fraction * n))
    bad = np.sort(rng.choice(n, k, replace=False))
    a = rng.uniform(0.0, 2.0 * np.pi, k)
    tip = np.radians(rng.uniform(*tip_deg, k))
    C = s.camera_target.copy()
    C[bad] = dq.mul(C[bad], H.rotation(np.column_stack([np.cos(a), np.sin(a), np.zeros(k)])
                                       * tip[:, None]))
    return s, dq.normalize(C), bad


def depth_noisy(n: int, seed: int, rot_deg: float = 1.15, mm=(12.0, 12.0, 40.0),
                geometry: str = "wrist", setup: str = "eye_in_hand"):
    """A scene whose camera poses carry KinHEC's camera noise c5 by default: rotation ``rot_deg``
    per axis and translation ``mm`` per axis of the camera's own frame (depth the largest), no
    scale error. ``(scene, camera_target)``."""
    s = H.scene(n, setup, geometry, camera_noise=(0.0, 0.0), seed=seed)
    rng = np.random.default_rng(70_000 + seed)
    q, t = dq.to_pose(dq.mul(s.camera_target, H.rotation(
        np.radians(rot_deg) * rng.normal(size=(n, 3)))))
    t = t + 1e-3 * np.asarray(mm) * rng.normal(size=(n, 3))
    return s, dq.from_pose(q, t)


def monocular(n: int, seed: int, scale: float, from_base: float = 0.3):
    """A wrist scene of ``n`` samples seen by a monocular camera, as visual odometry gives it:
    the "target" is the camera's first pose, set ``from_base`` m from the robot's base (the base
    frame moved toward it), and the camera's translations are at ``scale``. Returns the scene
    (its ``x`` the truth), the flange poses in the moved base and the camera's poses."""
    s = H.scene(n, "eye_in_hand", "wrist", camera_noise=(0.1, 0.5), seed=seed)
    start = dq.mul(s.base_flange, s.x)[0]
    p = dq.to_pose(start)[1]
    base = dq.from_pose(np.array([1.0, 0.0, 0.0, 0.0]), (from_base / np.linalg.norm(p) - 1) * p)
    C = dq.mul(s.camera_target, dq.mul(dq.inv(s.z), start))
    C[:, 4:] *= scale               # the dual part carries the translation linearly
    return s, dq.mul(base, s.base_flange), dq.normalize(C)
