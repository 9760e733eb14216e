"""Synthetic hand-eye scenes, the one generator the hand-eye tests and the benchmark share.

``scene(n, setup, geometry, camera_noise, robot_noise, seed)`` returns a :class:`Scene`: the robot
poses ``base_flange`` (``T_base_flange``) and the detector's ``camera_target``
(``T_camera_target``), both ``(n, 8)`` and noisy as asked, the noiseless ones they came from, and
the truth ``x`` and ``z`` in the API's meaning:

* eye_in_hand: ``x = T_flange_camera``, ``z = T_base_target``, so
  ``camera_target = x⁻¹ · base_flange⁻¹ · z``;
* eye_to_hand: ``x = T_base_camera``, ``z = T_flange_target``, so
  ``camera_target = x⁻¹ · base_flange · z``.

Noise is per axis, a right perturbation ``T · Exp(ξ)`` (the covariance convention of
``service/lie.py``) with ``ξ = [rotation (rad), translation (m)]`` drawn independently per axis with
standard deviations ``(deg, mm)`` converted to radians and metres; ``camera_covariance`` and
``robot_covariance`` are the matching diagonal 6×6 covariances.

Geometries:

* ``"wrist"``: a camera 0.3–0.6 m from a 7×5 ChArUco board (0.04 m squares), looking at a point near
  the board's centre from 15–45° off its normal, in every direction, rolled by up to ±90° about
  its optical axis: rotation axes well spread. Eye-in-hand: the camera on the flange, the board on
  the table; eye-to-hand: the camera fixed ~1 m from the robot, the board on the flange (the same
  views, the roles swapped).
* ``"opencv"``: OpenCV's own hand-eye test data (``simulateData`` in
  modules/calib3d/test/test_calibration_hand_eye.cpp): every pose a rotation of ``θ · a`` with the
  components of ``a`` uniform in [-1, 1] (not normalised, as there) and θ of random sign, and a
  translation with each component's magnitude uniform in a range and its sign random; the ranges are
  OpenCV's (camera in gripper 10–50°, 0.05–0.5 m; target in base 5–85°, 0.5–3.5 m; gripper in
  base 5–45°, 0.5–1.5 m). For eye-to-hand the camera takes the target's range in the base and the
  target the camera's range in the gripper. Only the noise is ours (the arguments), not OpenCV's
  fixed values.

No pytest here: the benchmark imports this module.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from dqpose import dq, handeye, lie

SETUPS = handeye.SETUPS
GEOMETRIES = ("wrist", "opencv")

BOARD_SIZE = (0.28, 0.20)   # 7 × 5 squares of 0.04 m: the board of the ChArUco notes


@dataclass(frozen=True)
class Scene:
    setup: str
    geometry: str
    base_flange: np.ndarray          # (n, 8) T_base_flange as the robot reports it (noisy if asked)
    camera_target: np.ndarray        # (n, 8) T_camera_target as the detector reports it
    x: np.ndarray                    # truth: T_flange_camera (eye_in_hand) / T_base_camera
    z: np.ndarray                    # truth: T_base_target (eye_in_hand) / T_flange_target
    true_base_flange: np.ndarray     # (n, 8) the poses before noise
    true_camera_target: np.ndarray
    camera_noise: tuple[float, float]            # (deg, mm) per axis
    robot_noise: Optional[tuple[float, float]]   # (deg, mm) per axis, None: exact robot poses
    seed: int

    @property
    def camera_covariance(self) -> np.ndarray:
        return covariance(self.camera_noise)

    @property
    def robot_covariance(self) -> Optional[np.ndarray]:
        return None if self.robot_noise is None else covariance(self.robot_noise)


def covariance(noise: tuple[float, float]) -> np.ndarray:
    """The diagonal 6×6 covariance (rotation first, rad² then m²) of ``(deg, mm)`` per axis."""
    deg, mm = noise
    return np.diag([np.radians(deg) ** 2] * 3 + [(mm * 1e-3) ** 2] * 3)


def pose_error(estimate, truth) -> tuple[float, float]:
    """``(degrees, millimetres)``: the angle of ``R̂ᵀR`` and ``‖t̂ − t‖`` (what OpenCV's test and
    the notes' figures measure, up to OpenCV's rotation-vector difference)."""
    d = dq.mul(dq.inv(estimate), truth)
    angle = 2.0 * np.arctan2(np.linalg.norm(d[1:4]), abs(d[0]))   # exact near 0, unlike arccos
    te, tt = dq.to_pose(estimate)[1], dq.to_pose(truth)[1]
    return float(np.degrees(angle)), float(1e3 * np.linalg.norm(te - tt))


def rotation(rotvec) -> np.ndarray:
    """Rotation vectors ``(..., 3)`` to pure-rotation poses ``(..., 8)``."""
    rotvec = np.asarray(rotvec, dtype=np.float64)
    return lie.se3_exp(np.concatenate([rotvec, np.zeros_like(rotvec)], axis=-1))


def pose(rotvec, t) -> np.ndarray:
    """Rotation vector and translation to a pose (rotation applied first, then the translation)."""
    r = rotation(rotvec)
    q = r[..., :4]
    return dq.from_pose(q, np.asarray(t, dtype=np.float64))


def perturb(T: np.ndarray, noise: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
    """``T · Exp(ξ)``, ξ per axis with standard deviations ``(deg, mm)``."""
    deg, mm = noise
    xi = rng.normal(size=T.shape[:-1] + (6,))
    xi[..., :3] *= np.radians(deg)
    xi[..., 3:] *= mm * 1e-3
    return dq.mul(T, lie.se3_exp(xi))


def _look_at(z_axis: np.ndarray, roll: float) -> np.ndarray:
    """A rotation matrix whose third column is ``z_axis``, rolled by ``roll`` about it."""
    z = z_axis / np.linalg.norm(z_axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll), np.sin(roll)
    return np.column_stack([c * x + s * y, -s * x + c * y, z])


def _wrist_views(n: int, rng: np.random.Generator) -> np.ndarray:
    """``T_target_camera`` (n, 8): the camera 0.3–0.6 m from a point near the board's centre,
    its optical axis 15–45° off the board's normal (board z points into the board, away from the
    camera), azimuth anywhere, roll ±90°."""
    out = np.empty((n, 8))
    centre = np.array([BOARD_SIZE[0] / 2, BOARD_SIZE[1] / 2, 0.0])
    for i in range(n):
        tilt = np.radians(rng.uniform(15.0, 45.0))
        azimuth = rng.uniform(0.0, 2 * np.pi)
        d = np.array([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)])
        look = centre + np.append(rng.uniform(-0.03, 0.03, 2), 0.0)
        M = np.eye(4)
        M[:3, :3] = _look_at(d, rng.uniform(-np.pi / 2, np.pi / 2))
        M[:3, 3] = look - rng.uniform(0.3, 0.6) * d
        out[i] = dq.from_matrix(M)
    return out


def _random_rotvec(rng, lo_deg, hi_deg) -> np.ndarray:
    axis = rng.normal(size=3)
    return np.radians(rng.uniform(lo_deg, hi_deg)) * axis / np.linalg.norm(axis)


def _wrist(n, setup, rng):
    views = _wrist_views(n, rng)                      # T_target_camera
    if setup == "eye_in_hand":
        x = pose(_random_rotvec(rng, 10, 60),
                 [rng.uniform(-0.08, 0.08), rng.uniform(-0.08, 0.08), rng.uniform(0.03, 0.12)])
        # The board flat on the table, face up (its z into the table), anywhere in yaw.
        down = dq.mul(rotation([0.0, 0.0, rng.uniform(-np.pi, np.pi)]), rotation([np.pi, 0, 0]))
        z = dq.mul(pose([0, 0, 0], [rng.uniform(0.4, 0.6), rng.uniform(-0.2, 0.2),
                                    rng.uniform(0.0, 0.1)]), down)
        # T_base_target T_target_camera T_camera_flange
        base_flange = dq.mul(dq.mul(z, views), dq.inv(x))
    else:
        # The camera 1 m off the base, looking back at the workspace.
        eye = np.array([rng.uniform(0.8, 1.1), rng.uniform(-0.3, 0.3), rng.uniform(0.5, 0.8)])
        M = np.eye(4)
        M[:3, :3] = _look_at(np.array([0.5, 0.0, 0.2]) - eye, rng.uniform(-np.pi, np.pi))
        M[:3, 3] = eye
        x = dq.from_matrix(M)
        z = pose(_random_rotvec(rng, 10, 60),
                 [rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), rng.uniform(0.03, 0.10)])
        base_flange = dq.mul(dq.mul(x, dq.inv(views)), dq.inv(z))
    return x, z, base_flange


def _opencv_pose(rng, theta, t_range) -> np.ndarray:
    # OpenCV's generatePose with random_sign: the axis is not normalised there, nor here.
    axis = rng.uniform(-1.0, 1.0, 3)
    angle = np.radians(rng.uniform(*theta)) * np.sign(rng.uniform(-1.0, 1.0))
    t = rng.uniform(*t_range, 3) * np.sign(rng.uniform(-1.0, 1.0, 3))
    return pose(angle * axis, t)


def _opencv(n, setup, rng):
    hand = _opencv_pose(rng, (10.0, 50.0), (0.05, 0.5))     # cam2gripper's range
    world = _opencv_pose(rng, (5.0, 85.0), (0.5, 3.5))      # target2base's range
    base_flange = np.stack([_opencv_pose(rng, (5.0, 45.0), (0.5, 1.5)) for _ in range(n)])
    if setup == "eye_in_hand":
        return hand, world, base_flange
    return world, hand, base_flange


def scene(n: int, setup: str = "eye_in_hand", geometry: str = "wrist",
          camera_noise: tuple[float, float] = (0.1, 0.5),
          robot_noise: Optional[tuple[float, float]] = None, seed: int = 0) -> Scene:
    """``n`` samples of ``setup`` in ``geometry``; noise ``(deg, mm)`` per axis (``(0, 0)``:
    exact). The same seed gives the same scene."""
    if setup not in SETUPS:
        raise ValueError(f"setup: expected one of {SETUPS}, got {setup!r}")
    if geometry not in GEOMETRIES:
        raise ValueError(f"geometry: expected one of {GEOMETRIES}, got {geometry!r}")
    rng = np.random.default_rng(seed)
    x, z, base_flange = (_wrist if geometry == "wrist" else _opencv)(n, setup, rng)
    base_flange = dq.normalize(base_flange)
    camera_target = dq.normalize(handeye.view_at(base_flange, x, z, setup))
    noisy_camera = perturb(camera_target, camera_noise, rng)
    noisy_robot = base_flange if robot_noise is None else perturb(base_flange, robot_noise, rng)
    return Scene(setup, geometry, noisy_robot, noisy_camera, x, z, base_flange, camera_target,
                 tuple(camera_noise), None if robot_noise is None else tuple(robot_noise), seed)


# ---- broken data: what the checks must flag ----------------------------------------------------
BROKEN = ("two_poses", "duplicates", "pure_translation", "parallel_axes", "small_rotations",
          "time_shift", "millimetres", "board_scale", "inverted_camera", "inverted_robot",
          "inverted_both", "swapped_setup", "outliers", "marker_flips")


@dataclass(frozen=True)
class Broken:
    kind: str
    setup: str              # the setup to solve it as (swapped_setup: the wrong one)
    base_flange: np.ndarray
    camera_target: np.ndarray
    bad: tuple[int, ...]    # the samples at fault (empty when the whole set is)
    scene: Scene            # the healthy scene it was made from


def _motion_scene(n, setup, rng, twists, seed, camera_noise):
    """A scene whose robot poses are ``F0 · Exp(twist_i)`` (twists in the flange frame)."""
    base = scene(n, setup, "wrist", camera_noise=(0.0, 0.0), seed=seed)
    F0 = base.true_base_flange[0]
    F = dq.normalize(dq.mul(F0, lie.se3_exp(twists)))
    C = dq.normalize(handeye.view_at(F, base.x, base.z, setup))
    Cn = perturb(C, camera_noise, rng)
    return Scene(setup, "wrist", F, Cn, base.x, base.z, F, C, tuple(camera_noise), None, seed)


def broken(kind: str, n: int = 20, setup: str = "eye_in_hand", seed: int = 0,
           camera_noise: tuple[float, float] = (0.1, 0.5)) -> Broken:
    """A data set broken in one way (``BROKEN``), from a healthy wrist scene."""
    rng = np.random.default_rng(10_000 + seed)
    s = scene(n, setup, "wrist", camera_noise=camera_noise, seed=seed)
    F, C, bad = s.base_flange.copy(), s.camera_target.copy(), ()
    solve_as = setup
    if kind == "two_poses":
        s = scene(2, setup, "wrist", camera_noise=camera_noise, seed=seed)
        F, C = s.base_flange, s.camera_target
    elif kind == "duplicates":
        k = n // 3
        idx = np.concatenate([np.arange(n - k), rng.choice(n - k, k, replace=False)])
        F, C = F[idx], C[idx]
        bad = tuple(int(i) for i in range(n - k, n))
    elif kind in ("pure_translation", "parallel_axes", "small_rotations"):
        tw = np.zeros((n, 6))
        tw[:, 3:] = rng.uniform(-0.1, 0.1, (n, 3))
        if kind == "parallel_axes":
            axis = rng.normal(size=3)
            tw[:, :3] = np.outer(np.radians(rng.uniform(-40, 40, n)), axis / np.linalg.norm(axis))
        elif kind == "small_rotations":
            tw[:, :3] = np.radians(rng.uniform(-1.0, 1.0, (n, 3)))
        s = _motion_scene(n, setup, rng, tw, seed, camera_noise)
        F, C = s.base_flange, s.camera_target
    elif kind == "time_shift":
        C = np.roll(C, 1, axis=0)
    elif kind == "millimetres":
        C = C.copy()
        C[:, 4:] *= 1000.0            # the dual part carries the translation linearly
    elif kind == "board_scale":       # the board's square size given 2 % wrong
        C = C.copy()
        C[:, 4:] *= 1.02
    elif kind == "inverted_camera":
        C = dq.inv(C)
    elif kind == "inverted_robot":
        F = dq.inv(F)
    elif kind == "inverted_both":     # fits as well as the truth, X and Z exchanged
        F, C = dq.inv(F), dq.inv(C)
    elif kind == "swapped_setup":
        solve_as = "eye_to_hand" if setup == "eye_in_hand" else "eye_in_hand"
    elif kind == "outliers":
        k = max(1, n // 5)
        idx = np.sort(rng.choice(n, k, replace=False))
        off = np.concatenate([rng.normal(size=(k, 3)), rng.normal(size=(k, 3))], axis=1)
        off[:, :3] *= np.radians(rng.uniform(3, 20, k)
                                 / np.linalg.norm(off[:, :3], axis=1))[:, None]
        off[:, 3:] *= (rng.uniform(0.01, 0.05, k) / np.linalg.norm(off[:, 3:], axis=1))[:, None]
        C[idx] = dq.mul(C[idx], lie.se3_exp(off))
        bad = tuple(int(i) for i in idx)
    elif kind == "marker_flips":
        # The planar-pose ambiguity: the board's rotation tipped about an in-plane axis, its
        # position (the origin) unchanged.
        k = max(1, n // 10)
        idx = np.sort(rng.choice(n, k, replace=False))
        a = rng.uniform(0, 2 * np.pi, k)
        tip = np.radians(rng.uniform(20, 40, k))
        rv = np.column_stack([np.cos(a), np.sin(a), np.zeros(k)]) * tip[:, None]
        C[idx] = dq.mul(C[idx], rotation(rv))
        bad = tuple(int(i) for i in idx)
    else:
        raise ValueError(f"kind: expected one of {BROKEN}, got {kind!r}")
    return Broken(kind, solve_as, dq.normalize(F), dq.normalize(C), bad, s)


# ---- corners: what a detector would report of the board ----------------------------------------
CAMERA_MATRIX = np.array([[900.0, 0.0, 640.0], [0.0, 900.0, 360.0], [0.0, 0.0, 1.0]])


def board_points(squares=(7, 5), size: float = 0.04) -> np.ndarray:
    """The inner chessboard corners of the ChArUco board, in its frame (z = 0)."""
    gx, gy = np.meshgrid(np.arange(1, squares[0]), np.arange(1, squares[1]))
    return np.column_stack([gx.ravel() * size, gy.ravel() * size, np.zeros(gx.size)])


def project(T_camera_target, points: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Board points seen through a pinhole ``K`` (no distortion) at ``T_camera_target``:
    ``(n, 2)`` pixels, pixel centres at integers (OpenCV's and the renderer's convention)."""
    pc = dq.transform(T_camera_target, points)
    return (K[:2, :2] @ (pc[:, :2] / pc[:, 2:]).T).T + K[:2, 2]


def corners(s: Scene, pixel_noise: float = 0.2, K: np.ndarray = CAMERA_MATRIX, seed: int = 0):
    """One ``(board_points, image_points, K)`` per sample: the board's inner corners projected
    through the true ``T_camera_target`` with Gaussian pixel noise (px per axis)."""
    rng = np.random.default_rng(20_000 + seed)
    P = board_points()
    out = []
    for C in s.true_camera_target:
        u = project(C, P, K)
        out.append((P, u + rng.normal(scale=pixel_noise, size=u.shape), K))
    return out


def exact_corners(s: Scene, squares, size: float = 0.015, K: np.ndarray = CAMERA_MATRIX):
    """One ``(board_points, image_points, K)`` per sample of a ``squares`` board: its corners
    projected through the measured ``T_camera_target`` without noise (a request's largest legal
    corner count, cheaply)."""
    P = board_points(squares, size)
    return [(P, project(C, P, K), K) for C in s.camera_target]


def near_side_pull(T_camera_target, points: np.ndarray, image_points: np.ndarray,
                   K: np.ndarray) -> float:
    """The mean of one view's corner errors (detected minus true, px) along the image direction
    in which the board's scale grows, i.e. toward its near side: what an error all of a view's
    corners share under perspective shows as (drivers/camera.py, ``_refine_corners``). The
    direction is the least-squares gradient over the image of the local scale ``f / depth``."""
    truth = project(T_camera_target, points, K)
    depth = dq.transform(T_camera_target, points)[:, 2]
    A = np.column_stack([np.ones(len(truth)), truth - truth.mean(axis=0)])
    g = np.linalg.lstsq(A, K[0, 0] / depth, rcond=None)[0][1:]
    return float(np.mean((image_points - truth) @ (g / np.linalg.norm(g))))
