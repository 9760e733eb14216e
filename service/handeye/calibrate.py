"""``calibrate``: the hand-eye solve as its stages, data checks and closed form, the noise model,
maximum likelihood with the χ² gate, the diagnostics after it, the readings plausibility tells
apart, and the corner level (the method and its conventions: :mod:`dqpose.handeye`).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

import numpy as np

from dqpose import dq, lie
from dqpose.errors import FieldError, Infeasible
from dqpose.handeye.checks import Prepared, prepare, samples
from dqpose.handeye.corners import corner_fit, corner_views
from dqpose.handeye.likelihood import Fit
from dqpose.handeye.noise import noise_model
from dqpose.handeye.outliers import against, gated, leave_one_out
from dqpose.handeye.readings import inverse_noise, moved, plausible
from dqpose.handeye.result import Calibration
from dqpose.handeye.scale import (
    MIN_SCALE,
    SCALE_SIGMAS,
    SCREEN_SIGMAS,
    camera_scale,
    evidence,
)
from dqpose.handeye.setups import EYE_IN_HAND

_MAX_RESCALES = 8        # re-solves towards the joint optimum of the scale


def calibrate(base_flange, camera_target, setup: str = EYE_IN_HAND, *, robust: bool = True,
              corners=None, camera_covariance=None, robot_covariance=None,
              refine_focal: bool = False, pixel_sigma: Optional[float] = None) -> Calibration:
    """Solve ``A_i X C_i = Z`` (see :mod:`dqpose.handeye`) for ``x`` and ``z`` with covariances.

    ``camera_covariance`` / ``robot_covariance``: noise of ``camera_target`` / ``base_flange``
    ((6, 6) or (n, 6, 6), right perturbation, rotation first); with neither given the noise is
    estimated from the residuals; with only the camera's given the robot poses are taken as exact.
    ``robust`` rejects samples failing the χ² gate (named in ``rejected``); otherwise they are
    kept and named in a warning.

    ``corners`` (one ``(board_points (k,3), image_points (k,2), K)`` per sample, undistorted
    pixels, board points in the target frame) adds a corner-level refinement after the pose-level
    one (:func:`~dqpose.handeye.corners.corner_fit`): ``x``, ``z`` and their covariances then
    come from the corners, ``reprojection`` holds each view's RMS error (px); ``refine_focal``
    estimates one scale of the focal lengths too (``focal_scale``); ``pixel_sigma`` (px) is the
    corner noise, estimated per view from the reprojection errors when not given (the reported
    one their pooled RMS). The robot's noise there is ``robot_covariance`` when given, estimated
    when neither covariance is given, and none (exact robot poses) when only
    ``camera_covariance`` is.

    Two readings of the data fit as well as the one given, and are caught by plausibility
    instead (:mod:`dqpose.handeye.readings`): both poses inverted (``T_flange_base`` and
    ``T_target_camera``: X and Z exchange roles exactly) and the camera's translations at
    another scale (a wrong board size). Where the data say which reading is right, the answer is
    that reading's, with a warning saying what was corrected; where they cannot, ``Infeasible``.

    The stages, in order (:func:`_calibrate`):

    1. the data checks and the closed form (:mod:`~dqpose.handeye.checks`);
    2. the noise model, given or estimated (:mod:`~dqpose.handeye.noise`);
    3. maximum likelihood on ``(X, Z)`` with the χ² gate (:mod:`~dqpose.handeye.likelihood`,
       :mod:`~dqpose.handeye.outliers`);
    4. the diagnostics: residuals, leave-one-out, the closed form's agreement;
    5. the readings: re-solved rescaled, then (at the scale found) inverted, when the data
       say so (:func:`_rescale`, :func:`_both_inverted`);
    6. the corner level, when ``corners`` are given (:func:`_corner_level`).
    """
    return _calibrate(_Request(base_flange, camera_target, setup, robust, corners,
                               camera_covariance, robot_covariance, refine_focal, pixel_sigma))


@dataclass(frozen=True)
class _Request:
    """The arguments of :func:`calibrate`; a re-solve on another reading replaces some."""
    base_flange: object
    camera_target: object
    setup: str
    robust: bool
    corners: object
    camera_covariance: object
    robot_covariance: object
    refine_focal: bool
    pixel_sigma: Optional[float]
    inverted: bool = False        # the re-solve on both poses inverted (not to be turned back)
    # (λ, σ): the re-solve on camera translations scaled by λ (whose uncertainty then enters
    # the covariance)
    rescaled: Optional[tuple[float, float]] = None


def _calibrate(q: _Request) -> Calibration:
    """:func:`calibrate`, stage by stage."""
    # 1. the data checks and the closed form
    p = prepare(q.base_flange, q.camera_target, q.setup)
    n = p.F.shape[0]
    views = None if q.corners is None else corner_views(q.corners, n)
    if q.pixel_sigma is not None and not (np.isfinite(q.pixel_sigma) and q.pixel_sigma > 0):
        raise FieldError(f"pixel_sigma: must be a positive number of pixels, got "
                         f"{q.pixel_sigma!r}")
    # 2. the noise model
    SC, SRob, noise = noise_model(p, q.camera_covariance, q.robot_covariance)
    estimate = noise.estimate
    warnings = list(p.warnings)
    # 3. maximum likelihood with the χ² gate
    fit, inlier, rejected = gated(p, noise, q.robust, warnings)
    # 4. the diagnostics
    r_all, S_all, nis = against(p, fit, noise, inlier)
    idx = np.flatnonzero(inlier)
    loo = leave_one_out(fit, idx, n)
    residuals = _residuals(p, fit, r_all)
    agree = _agreement(fit, p.closed[0], idx, warnings)
    # 5. the readings the residuals cannot tell apart: the scale first, since a mount's
    # plausibility read off a fit at the wrong scale is no evidence (a monocular camera's X and
    # Z come out at the wrong distances, and both-inverted looked the likelier)
    found = camera_scale(fit, p.C[inlier], noise, inlier)
    scale: tuple[float, float] = (found.lam, found.sigma)
    P_scale: float | np.ndarray = 0.0
    if q.rescaled is not None:
        # The re-solve on scaled translations: λ's uncertainty widens the covariance.
        P_scale = found.extra
        scale = (q.rescaled[0] * found.lam, q.rescaled[0] * found.sigma)
    elif (abs(found.lam - 1.0) > max(SCREEN_SIGMAS * found.sigma, MIN_SCALE)
          and evidence(p, fit, noise, inlier, found) > SCALE_SIGMAS ** 2):
        return _rescale(q, p, views, SC, SRob, fit, idx, scale)
    # a re-solve whose scale has not settled is one step of _rescale's loop: judged at its end
    settled = q.rescaled is None or abs(found.lam - 1.0) <= 0.1 * found.sigma
    cal = _both_inverted(q, p, fit, inlier, SC, SRob, warnings, settled)
    if cal is not None:
        return cal
    # 6. the corner level
    X, Z, P = fit.X, fit.Z, fit.reported + P_scale
    Hx = np.linalg.inv(P)
    corner = {}
    if views is not None:
        X, Z, P, Hx, corner, scale = _corner_level(q, p, views, X, Z, inlier,
                                                   "estimate" if estimate else SRob, scale,
                                                   warnings)
    return Calibration(
        setup=p.setup, x=X, z=Z, covariance_x=P[:6, :6].copy(),
        covariance_z=P[6:, 6:].copy(), residuals=residuals, warnings=tuple(warnings),
        inliers=inlier, rejected=rejected, covariance=P, information=Hx,
        noise_model="estimated" if estimate else "given",
        camera_covariance=noise.covariances()[0] if estimate else SC,
        **({"robot_covariance": noise.covariances()[1] if estimate else SRob} | corner),
        residual_covariance=np.array(S_all), nis=nis, leave_one_out=loo,
        closed_form_x=p.closed[0], closed_form_z=p.closed[1], agreement=agree,
        rotation_condition=p.condition, excitation=p.excitation, iterations=fit.iterations,
        readings=p.readings, camera_scale=scale[:2])


def _residuals(p: Prepared, fit: Fit, r: np.ndarray) -> np.ndarray:
    """``(n, 2)``: each sample's residual rotation (rad, of ``r``) and the target's position
    (m) from it."""
    E = dq.mul(dq.mul(dq.mul(dq.inv(fit.Z), p.A), fit.X), p.C)
    return np.column_stack([np.linalg.norm(r[:, :3], axis=1),
                            np.linalg.norm(dq.to_pose(E)[1], axis=1)])


def _agreement(fit: Fit, X0, idx, warnings: list) -> tuple[float, float, float]:
    """The closed form ``X0`` against the refined X: rad, m and NEES in the reported covariance;
    a warning when they disagree grossly."""
    xi = lie.se3_log(dq.mul(dq.inv(fit.X), X0))
    agree = (float(np.linalg.norm(xi[:3])), moved(X0, fit.X),
             float(xi @ np.linalg.solve(fit.reported[:6, :6], xi)))
    # The closed form weighs nothing and is far less precise than the refinement (on OpenCV's
    # geometry 10–20 mm off at 0.1° / 0.5 mm noise): only a gross disagreement is a sign.
    if agree[2] > 1e4 and (agree[0] > np.radians(3.0) or agree[1] > 0.05):
        warnings.append(f"{samples(idx)}: the closed form and the refined X differ by "
                        f"{np.degrees(agree[0]):.2f}° / {1e3 * agree[1]:.1f} mm "
                        f"(NEES {agree[2]:.3g}): the model may not fit the data")
    return agree


def _both_inverted(q: _Request, p: Prepared, fit: Fit, inlier, SC, SRob,
                   warnings: list, settled: bool = True) -> Optional[Calibration]:
    """Robot and camera poses both inverted fit exactly as well as the truth (F⁻¹ Z C⁻¹ = X: X
    and Z exchange roles), so the residuals cannot tell; plausibility can. The re-solve as
    inverted when the mount is implausible as given and the depths say inverted, ``Infeasible``
    when they cannot tell, a warning when the mount is implausible either way; else None. Not
    ``settled`` (a re-solve at a scale still moving): the warning alone."""
    idx = np.flatnonzero(inlier)
    given, other = plausible(p, fit.X, fit.Z, inlier), plausible(p, fit.Z, fit.X, inlier, True)
    if not given.mount_ok and not q.inverted and settled:
        if other.mount_ok and other.front and given.behind:
            cal = _calibrate(replace(q, base_flange=dq.inv(p.F), camera_target=dq.inv(p.C),
                                     setup=p.setup, camera_covariance=inverse_noise(p.C, SC),
                                     robot_covariance=inverse_noise(p.F, SRob), inverted=True))
            return _warned(cal, f"{samples(idx)}: base_flange and camera_target look both "
                                f"inverted (T_flange_base, T_target_camera): as given "
                                f"{given.says}, and the target lies behind the camera in every "
                                f"sample; inverted, {other.says} with the target in front. "
                                f"Solved as inverted; fix the conventions (the flange in the "
                                f"robot's base frame, the target in the camera's)")
        if other.mount_ok and not (given.front and other.behind):
            raise Infeasible(f"base_flange, camera_target: as given {given.says}; with both "
                             f"inverted (T_flange_base, T_target_camera: an exact fit too) "
                             f"{other.says}. The data cannot tell which; check both pose "
                             f"conventions (the flange in the robot's base frame, the target "
                             f"in the camera's) ({samples(idx)})")
    # A fixed part near the base is only a sign of inverted poses when the inverted reading is
    # plausible; alone it is a real mount (a target 0.21 m from the base is legitimate).
    if not given.reach_ok or (not given.base_ok and other.mount_ok):
        why = ("though the target lies in front of the camera as given and behind it "
               "inverted" if given.front and other.behind else
               f"and as inverted poses {other.says}")
        warnings.append(f"{samples(idx)}: {given.says}, {why}: check the mount and the pose "
                        f"conventions (both poses inverted fit as well)")
    return None


def _rescale(q: _Request, p: Prepared, views, SC, SRob, fit: Fit, idx, scale) -> Calibration:
    """The re-solve with camera_target's translations (and the board's points) scaled by the
    best-fitting ``λ``, its uncertainty in the covariance, with a warning. ``scale[0]`` is one
    Newton step from λ = 1; the scale, the inliers and the noise are re-solved together until the
    scale the re-solve finds on its data is 1 within a tenth of its σ (the joint optimum: a
    monocular camera at half the scale took λ to 3.03 in one step, where 2 is right)."""
    n = p.F.shape[0]
    lam, sigma = scale[0], scale[1]
    for _ in range(_MAX_RESCALES):
        Cs = p.C.copy()
        Cs[:, 4:] *= lam            # the dual part carries the translation linearly
        D = np.diag([1.0] * 3 + [lam] * 3)
        cs = None if views is None else [
            (views.points[views.view == k] * lam, views.pixels[views.view == k], views.K[k])
            for k in range(n)]
        cal = _calibrate(replace(q, base_flange=p.F, camera_target=Cs, setup=p.setup, corners=cs,
                                 camera_covariance=None if SC is None else D @ SC @ D,
                                 robot_covariance=SRob, rescaled=(lam, sigma)))
        found, sigma = cal.camera_scale
        if not (np.isfinite(found) and found > 0.0) or abs(found - lam) <= 0.1 * sigma:
            break
        lam = found
    return _warned(cal, f"{samples(idx)}: the camera's translations fit best scaled by "
                        f"{cal.camera_scale[0]:.4f} ± {cal.camera_scale[1]:.4f} against the "
                        f"robot's: a wrong board size, or a camera scale error? Solved with "
                        f"camera_target's translations (and the board's points) scaled by "
                        f"{lam:.4f}, its uncertainty in the covariance; X's translation was off "
                        f"by {1e3 * moved(fit.X, cal.x):.2f} mm without")


def _corner_level(q: _Request, p: Prepared, views, X, Z, inlier, robot, scale,
                  warnings: list):
    """The corner-level refinement from the pose level's ``(X, Z)``: ``(X, Z, P, information,
    the Calibration's corner fields, camera scale)``, with a warning naming the views whose
    reprojection errors stand out."""
    cf = corner_fit(p.F, p.setup, X, Z, views, inlier, robot, q.refine_focal, q.pixel_sigma,
                     refine_board=q.rescaled is not None)
    if q.rescaled is not None:
        scale = (q.rescaled[0] * cf.board_scale, q.rescaled[0] * cf.board_sigma)
    corner = dict(reprojection=cf.reprojection, focal_scale=cf.focal_scale,
                  focal_sigma=cf.focal_sigma, pixel_sigma=cf.pixel_sigma)
    if cf.robot_covariance is not None:
        corner["robot_covariance"] = cf.robot_covariance
    bad = np.flatnonzero(inlier & (cf.reprojection > 5.0 * cf.pixel_sigma + 0.5))
    if len(bad):
        warnings.append(f"{samples(bad)}: reprojection errors of " + ", ".join(
            f"{cf.reprojection[k]:.2f}" for k in bad) + f" px, against {cf.pixel_sigma:.2f} "
            f"px overall: corners misdetected, or the robot pose off?")
    return cf.X, cf.Z, cf.P, np.linalg.inv(cf.P), corner, scale


def _warned(cal: Calibration, warning: str) -> Calibration:
    return replace(cal, warnings=(warning,) + cal.warnings)
