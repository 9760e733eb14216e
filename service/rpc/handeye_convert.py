"""The ``dqpose.v1.HandEye`` messages <-> :func:`dqpose.handeye.calibrate`'s arguments and its
:class:`~dqpose.handeye.Calibration`: a ``CalibrateRequest`` to the domain's arrays (pairs,
covariances, corners with one camera matrix), its errors renamed to the request's fields
(``base_flange`` -> ``pairs[3].base_to_flange``), and the answer back (the client's).
"""
from __future__ import annotations

import math
import re
from typing import NamedTuple

import numpy as np

from dqpose import handeye
from dqpose.errors import FieldError, rename_all
from dqpose.rpc._proto.dqpose.v1 import handeye_pb2 as hpb
from dqpose.rpc.checks import field_named
from dqpose.rpc.geometry import (
    COVARIANCE_SIZE,
    dq_to_pose,
    flat_to_dqs,
    pose_arrays,
    pose_msgs,
    pose_to_dq,
    poses_to_flat,
)

#: the domain's setups (:data:`dqpose.handeye.SETUPS`) as the proto's Setup values
SETUP_ENUMS = {name: hpb.Setup.Value(f"SETUP_{name.upper()}") for name in handeye.SETUPS}
SETUP_NAMES = {code: name for name, code in SETUP_ENUMS.items()}
#: the domain's argument names -> the request's fields (``{}``: the pair's index)
CALIBRATE_FIELDS = {"base_flange": "pairs{}.base_to_flange",
                    "camera_target": "pairs{}.camera_to_target",
                    "camera_covariance": "pairs{}.camera_covariance",
                    "robot_covariance": "pairs{}.robot_covariance",
                    "corners": "pairs{}.corners", "board_points": "target_points"}


class CalibrateArgs(NamedTuple):
    """A ``CalibrateRequest`` as the arguments of :func:`dqpose.handeye.calibrate`."""
    setup: str
    base_flange: np.ndarray      # (n, 8) T_base_flange, unit
    camera_target: np.ndarray    # (n, 8) T_camera_target, unit
    robust: bool
    camera_covariance: np.ndarray | None    # (n, 6, 6)
    robot_covariance: np.ndarray | None     # (n, 6, 6)
    corners: list | None                    # per pair (target_points, image_points, K)
    refine_focal: bool
    pixel_sigma: float | None


#: the fields of a CalibrateRequest an error may start with
CALIBRATE_REQUEST = ("setup", "pairs", "robust", "camera_matrix", "refine_focal", "pixel_sigma")


def calibrate_error(e: ValueError) -> FieldError:
    """A :func:`dqpose.handeye.calibrate` error with the request's field names, wherever the
    message has the domain's (``"base_flange, camera_target: ..."``); Infeasible stays so; one
    from inside NumPy about none of them named ``pairs``."""
    renamed = rename_all(e, CALIBRATE_FIELDS)
    # the domain takes a camera matrix per view; the request has one
    renamed = type(renamed)(re.sub(r"pairs\[\d+\]\.corners\.K\b", "camera_matrix",
                                   str(renamed)))
    return field_named(renamed, CALIBRATE_REQUEST, "pairs")


def _corners(req) -> list | None:
    """Every pair's corners as the domain takes them, or None when no pair has any."""
    has = [p.HasField("corners") for p in req.pairs]
    if not any(has):
        return None
    if not all(has):
        i, given = has.index(False), has.index(True)
        raise FieldError(f"pairs[{i}].corners: required, as pairs[{given}] has corners (on "
                         f"every pair or on none)")
    if len(req.camera_matrix) != 9:
        raise FieldError(f"camera_matrix: {len(req.camera_matrix)} values; 9 (row-major) are "
                         f"needed with corners")
    K = np.array(req.camera_matrix, dtype=np.float64).reshape(3, 3)
    out = []
    for i, p in enumerate(req.pairs):
        c = p.corners
        if len(c.target_points) % 3 or len(c.image_points) % 2:
            bad = "target_points" if len(c.target_points) % 3 else "image_points"
            raise FieldError(f"pairs[{i}].corners.{bad}: {len(getattr(c, bad))} values, not "
                             f"{'3' if bad == 'target_points' else '2'} per corner")
        out.append((np.array(c.target_points, dtype=np.float64).reshape(-1, 3),
                    np.array(c.image_points, dtype=np.float64).reshape(-1, 2), K))
    return out


def _pair_covariances(pairs, name: str) -> np.ndarray | None:
    """The ``name`` covariances of every pair, ``(n, 6, 6)``, or None when no pair has one."""
    counts = [len(getattr(p, name)) for p in pairs]
    if not any(counts):
        return None
    for i, k in enumerate(counts):
        if k != COVARIANCE_SIZE:
            given = next(j for j, c in enumerate(counts) if c)
            raise FieldError(f"pairs[{i}].{name}: {k} values; expected {COVARIANCE_SIZE} "
                             f"(6x6, row-major) on every pair, as pairs[{given}] has, or on none")
    return np.array([getattr(p, name) for p in pairs], dtype=np.float64).reshape(-1, 6, 6)


def calibrate_from_msg(req) -> CalibrateArgs:
    """A ``CalibrateRequest`` to :class:`CalibrateArgs`; errors name the field."""
    setup = SETUP_NAMES.get(req.setup)
    if setup is None:
        if req.setup == hpb.SETUP_UNSPECIFIED:
            raise FieldError("setup: required: SETUP_EYE_IN_HAND (the camera on the flange) or "
                             "SETUP_EYE_TO_HAND (the camera fixed, the target on the flange)")
        raise FieldError(f"setup: unknown Setup value {req.setup}")
    poses = {}
    for name in ("base_to_flange", "camera_to_target"):
        for i, p in enumerate(req.pairs):
            if not p.HasField(name):
                raise FieldError(f"pairs[{i}].{name}: required")
        poses[name] = flat_to_dqs(poses_to_flat([getattr(p, name) for p in req.pairs]), "pairs",
                                  f".{name}")
    robust = req.robust if req.HasField("robust") else True
    corners = _corners(req)
    if corners is None and (req.refine_focal or req.pixel_sigma or req.camera_matrix):
        field = "refine_focal" if req.refine_focal else \
            "pixel_sigma" if req.pixel_sigma else "camera_matrix"
        raise FieldError(f"{field}: only with corners (PosePair.corners)")
    if req.pixel_sigma < 0 or not math.isfinite(req.pixel_sigma):
        raise FieldError(f"pixel_sigma: must be a positive number of pixels (0: estimated), got "
                         f"{req.pixel_sigma!r}")
    return CalibrateArgs(setup, poses["base_to_flange"], poses["camera_to_target"], robust,
                         _pair_covariances(req.pairs, "camera_covariance"),
                         _pair_covariances(req.pairs, "robot_covariance"), corners,
                         req.refine_focal, req.pixel_sigma or None)


def _per_pair(cov, name: str, n: int) -> list | None:
    """Client side: a ``(6, 6)`` or ``(n, 6, 6)`` covariance as n rows of 36 values."""
    if cov is None:
        return None
    c = np.asarray(cov, dtype=np.float64)
    if c.shape == (6, 6):
        c = np.broadcast_to(c, (n, 6, 6))
    if c.shape != (n, 6, 6):
        raise ValueError(f"{name}: expected shape (6, 6) or ({n}, 6, 6), got {c.shape}")
    return c.reshape(n, COVARIANCE_SIZE).tolist()


def calibrate_msg(base_flange, camera_target, setup: str = handeye.EYE_IN_HAND,
                  robust: bool = True,
                  camera_covariance=None, robot_covariance=None, corners=None,
                  refine_focal: bool = False,
                  pixel_sigma: float | None = None) -> "hpb.CalibrateRequest":
    """Client side: the ``CalibrateRequest`` of :func:`dqpose.handeye.calibrate`'s arguments,
    poses as given (the server names what is wrong with them)."""
    if setup not in SETUP_ENUMS:
        raise ValueError(f"setup: unknown {setup!r}; expected one of {', '.join(SETUP_ENUMS)}")
    a = np.asarray(base_flange, dtype=np.float64)
    b = np.asarray(camera_target, dtype=np.float64)
    for name, v in (("base_flange", a), ("camera_target", b)):
        if v.ndim != 2 or v.shape[1] != 8:
            raise ValueError(f"{name}: expected shape (n, 8), got {v.shape}")
    if len(a) != len(b):
        raise ValueError(f"camera_target: {len(b)} poses for {len(a)} base_flange poses")
    pairs = [hpb.PosePair(base_to_flange=f, camera_to_target=c)
             for f, c in zip(pose_msgs(*pose_arrays(a)), pose_msgs(*pose_arrays(b)))]
    for name, cov in (("camera_covariance", camera_covariance),
                      ("robot_covariance", robot_covariance)):
        rows = _per_pair(cov, name, len(pairs))
        for p, row in zip(pairs, rows or ()):
            getattr(p, name).extend(row)
    # protoc's .pyi types Enum.Value() as int, the field as the enum class
    request = hpb.CalibrateRequest(setup=SETUP_ENUMS[setup],  # type: ignore[arg-type]
                                   pairs=pairs, robust=bool(robust),
                                   refine_focal=bool(refine_focal),
                                   pixel_sigma=float(pixel_sigma or 0.0))
    if corners is not None:
        _corners_msgs(request, corners)
    return request


def _corners_msgs(request, corners) -> None:
    """Client side: :func:`dqpose.handeye.calibrate`'s ``corners`` (one ``(board_points,
    image_points, K)`` per pair, one K for all) into the request."""
    corners = list(corners)
    if len(corners) != len(request.pairs):
        raise ValueError(f"corners: {len(corners)} views for {len(request.pairs)} pairs")
    Ks = [np.asarray(k, dtype=np.float64) for _, _, k in corners]
    if any(k.shape != (3, 3) or not np.array_equal(k, Ks[0]) for k in Ks):
        raise ValueError("corners: one camera matrix K (3, 3) for every view (the service "
                         "takes one camera)")
    request.camera_matrix.extend(Ks[0].ravel().tolist())
    for p, (b, u, _) in zip(request.pairs, corners):
        p.corners.target_points.extend(np.asarray(b, dtype=np.float64).ravel().tolist())
        p.corners.image_points.extend(np.asarray(u, dtype=np.float64).ravel().tolist())


def calibration_to_msg(c) -> "hpb.CalibrateResponse":
    """A :class:`dqpose.handeye.Calibration` into a ``CalibrateResponse``."""
    msg = hpb.CalibrateResponse(
        covariance_x=np.asarray(c.covariance_x).ravel().tolist(),
        covariance_z=np.asarray(c.covariance_z).ravel().tolist(),
        residuals=np.asarray(c.residuals).ravel().tolist(), warnings=list(c.warnings),
        rejected=[hpb.RejectedPair(index=r.index, reason=r.reason) for r in c.rejected],
        agreement=[float(v) for v in c.agreement], rotation_condition=c.rotation_condition,
        excitation=c.excitation, iterations=c.iterations, noise_model=c.noise_model,
        readings=[hpb.Reading(reading=r, rotation=a, translation=d) for r, a, d in c.readings],
        focal_scale=c.focal_scale, focal_sigma=c.focal_sigma, pixel_sigma=c.pixel_sigma,
        camera_scale=c.camera_scale[0], camera_scale_sigma=c.camera_scale[1])
    for field, pose in (("x", c.x), ("z", c.z), ("closed_form_x", c.closed_form_x),
                        ("closed_form_z", c.closed_form_z)):
        if pose is not None:
            dq_to_pose(pose, getattr(msg, field))
    for field in ("leave_one_out", "nis", "covariance", "reprojection", "inliers"):
        value = getattr(c, field)
        if value is not None:
            getattr(msg, field).extend(np.asarray(value).ravel().tolist())
    return msg


def calibration_from_msg(msg, setup: str):
    """Client side: a ``CalibrateResponse`` back into the :class:`dqpose.handeye.Calibration`
    it was made from (without the noise model's matrices, which stay on the server)."""
    def rows(values, width):
        return np.array(values, dtype=np.float64).reshape(-1, width)

    rejected = tuple(handeye.Rejection(r.index, r.reason) for r in msg.rejected)
    covariance = rows(msg.covariance, 12) if msg.covariance else None
    return handeye.Calibration(
        setup=setup, x=pose_to_dq(msg.x), z=pose_to_dq(msg.z),
        covariance_x=rows(msg.covariance_x, 6), covariance_z=rows(msg.covariance_z, 6),
        residuals=rows(msg.residuals, 2), warnings=tuple(msg.warnings),
        inliers=np.array(msg.inliers, dtype=bool),
        rejected=rejected, covariance=covariance,
        information=None if covariance is None else np.linalg.inv(covariance),
        noise_model=msg.noise_model, nis=np.array(msg.nis, dtype=np.float64),
        leave_one_out=rows(msg.leave_one_out, 2),
        closed_form_x=pose_to_dq(msg.closed_form_x) if msg.HasField("closed_form_x") else None,
        closed_form_z=pose_to_dq(msg.closed_form_z) if msg.HasField("closed_form_z") else None,
        agreement=tuple(msg.agreement), rotation_condition=msg.rotation_condition,
        excitation=msg.excitation, iterations=msg.iterations,
        readings=tuple((r.reading, r.rotation, r.translation) for r in msg.readings),
        reprojection=np.array(msg.reprojection, dtype=np.float64) if msg.reprojection else None,
        focal_scale=msg.focal_scale, focal_sigma=msg.focal_sigma, pixel_sigma=msg.pixel_sigma,
        camera_scale=(msg.camera_scale, msg.camera_scale_sigma))
