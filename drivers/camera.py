"""Camera pose source: ChArUco boards and single ArUco markers with OpenCV's object API.

Each accepted view gives ``T_camera_board`` (maps board points to camera coordinates) with a
6x6 covariance; a rejected view gives a :class:`Rejection` with the reason. Frames come from a
``cv2.VideoCapture`` device, a video file, a folder of images, any object with ``read()`` and
``close()`` (a frame source of your own), or images passed to :meth:`CharucoCamera.detect`.
Frame sources return the next image, or None at their end; a live device is read by a
background thread (:class:`LiveFrames`), so ``read(timeout)`` can give up on a stalled camera
and always returns the newest frame rather than a queue of old ones.

Board frame: origin at the outer top-left chessboard corner (for a single marker: its centre),
x along the squares, y down the board, z into the board.

ChArUco corners: OpenCV's detector finds them and refines each with ``cornerSubPix``; we refine
them once more, each in the largest window that stays off the two markers beside the corner
(:mod:`dqpose.drivers.charuco_corners`). OpenCV's window reaches into those markers, whose edges
pull every corner of a view the same way under perspective (toward the far side of the board):
an error shared by all of a view's corners, invisible in the residuals, that made each pose's
covariance too confident and hand-eye calibration end to end claim too much (mean NEES of X 8.9
instead of 6; docs/benchmarks/handeye.md#corner-detection).

Covariance convention: the fusion convention of :class:`dqpose.drivers.base.Measurement`, a right
(body-frame) perturbation with the SE(3) exponential, ``T_true = T_est * Exp(xi)``,
``xi = (omega, v)``, rotation first (radians), then translation (metres), both in the board
frame (GTSAM's ``Pose3``). It is ``s^2 (J^T J)^-1`` with ``J`` the Jacobian of the reprojected
corners with respect to ``xi`` at 0 and ``s^2`` the pixel noise's variance per coordinate as the
view's residuals tell it, ``sum r^2 / (2N - 8)`` (floored at ``min_pixel_sigma^2``): a variance
estimated from ``nu = 2N - 6`` degrees of freedom, ``sum r^2 / nu``, is unbiased, but its
inverse, the information a fusion weighs the view by, is ``nu / (nu - 2)`` too large on average
(``E[1/s^2] = nu / ((nu - 2) sigma^2)``): views of a full board (24 corners) had a mean NEES of
6.3-6.7 against their truth (1200 views of each of three seeds), views of 6 corners 8.3 (150
views, tests/drivers/test_camera.py), where ``2N - 8`` gives 6.0-6.4 and 5.6. Four corners (a
single marker, ``nu = 2``) leave no finite factor; their ``s^2`` is ``sum r^2 / 2``. OpenCV's
Jacobian is with respect to its own parameters, the rotation vector and translation
``(rvec, tvec)``; :func:`pnp_chart` is the exact chain-rule factor from ``xi`` to them.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Iterator, Optional, Union

import cv2
import numpy as np

from dqpose import dq, lie
from dqpose.drivers.base import Measurement, PoseSource
from dqpose.drivers.camera_config import BoardSpec, Intrinsics, load_board, load_intrinsics
from dqpose.drivers.camera_frames import (
    IMAGE_EXTENSIONS,
    FolderFrames,
    LiveFrames,
    VideoFrames,
    open_frames,
    read_image,
)
from dqpose.drivers.charuco_corners import marker_free_reach, refine_off_markers

# The configuration, the frame sources and the corner windows live in their own modules
# (camera_config, camera_frames, charuco_corners); their names stay importable from here.
__all__ = ["Intrinsics", "BoardSpec", "Detection", "Rejection", "CharucoCamera", "pnp_chart",
           "marker_free_reach", "load_intrinsics", "load_board", "open_frames", "FolderFrames",
           "VideoFrames", "LiveFrames", "read_image", "IMAGE_EXTENSIONS"]


# ---- results -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Detection:
    """An accepted view: ``pose`` is ``T_camera_board``; ``covariance`` as in the module doc;
    ``rms`` the reprojection error in pixels (RMS point distance); ``ambiguity`` how much worse
    the other IPPE solution explains the corners, in pixel-noise variances (large is good)."""
    pose: np.ndarray
    covariance: np.ndarray
    rms: float
    n_points: int
    ambiguity: float
    ids: np.ndarray
    image_points: np.ndarray
    object_points: np.ndarray

    @property
    def ok(self) -> bool:
        return True


@dataclass(frozen=True)
class Rejection:
    """A rejected view. ``reason`` is one of ``no_board``, ``too_few_corners``, ``collinear``,
    ``ambiguous``, ``reprojection``, ``pnp_failed``, or ``no_frame`` (the source gave no frame
    within the timeout); ``message`` says it in words."""
    reason: str
    message: str
    n_points: int = 0

    @property
    def ok(self) -> bool:
        return False

    def __str__(self) -> str:
        return self.message


# ---- the detector ------------------------------------------------------------------------------
def pnp_chart(rvec) -> np.ndarray:
    """``d(rvec, tvec) / d xi`` at ``xi = 0`` for ``T(rvec, tvec) * Exp(xi)``, 6x6.

    With ``R = Exp(rvec)``, ``T * Exp(xi)`` has rotation ``R Exp(omega)`` and translation
    ``t + R Jl(omega) v`` (the SE(3) exponential's translation is ``Jl(omega) v``). The rotation
    vector of ``R Exp(omega)`` is ``rvec + Jr(rvec)^-1 omega`` to first order; ``Jl(omega) v`` is
    ``v + O(|omega| |v|)``, so its derivative at 0 is ``R`` in ``v`` and 0 in ``omega``. Hence
    ``[[Jr(rvec)^-1, 0], [0, R]]``: the SO(3) x R^3 right perturbation ``(R Exp(omega), t + R v)``
    and the SE(3) one share their first derivative at the pose (they differ at second order),
    and it is this factor, not the identity, between OpenCV's parameters and either.
    """
    w = np.asarray(rvec, dtype=np.float64).ravel()
    J = np.zeros((6, 6))
    J[:3, :3] = lie.so3_right_jacobian_inv(w)
    J[3:, 3:] = cv2.Rodrigues(w)[0]
    return J


def _to_gray(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.dtype != np.uint8:
        if img.dtype == np.uint16:
            img = (img / 257).astype(np.uint8)
        else:
            raise ValueError(f"image: expected uint8 or uint16 pixels, got {img.dtype}")
    if img.ndim == 2:
        return img
    if img.ndim == 3 and img.shape[2] == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.ndim == 3 and img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
    if img.ndim == 3 and img.shape[2] == 1:
        return img[:, :, 0]
    raise ValueError(f"image: expected a grey or BGR image, got shape {img.shape}")


class CharucoCamera(PoseSource):
    """Pose source for a ChArUco board or a single ArUco marker.

    ``source`` (optional) is anything :func:`open_frames` accepts; without it, call
    :meth:`detect` on images yourself. Rejection thresholds: ``min_corners`` (ChArUco corners),
    ``min_spread`` (smallest singular value of the centred board points over the largest: below
    it the corners are collinear), ``ambiguity_chi2`` (the second IPPE solution's sum of squared
    reprojection errors must exceed the first's by this many pixel-noise variances, the
    variance estimated from the first's residual), ``max_reprojection_px`` (RMS point distance).
    """

    @classmethod
    def open(cls, channel: str, *, intrinsics: Union[Intrinsics, str, None] = None,
             **kwargs) -> "CharucoCamera":
        """``drivers.open_source("charuco:<source>", intrinsics=...)``: ``source`` is anything
        :func:`open_frames` accepts (folder, image, video file, device index)."""
        if intrinsics is None:
            raise ValueError("intrinsics: required (an Intrinsics or a YAML/JSON file such as "
                             "the poses.json of `dqpose sim camera`)")
        return cls(intrinsics, source=channel, **kwargs)

    def __init__(self, intrinsics: Union[Intrinsics, str], board: Optional[BoardSpec] = None,
                 source=None, *, name: str = "camera", min_corners: int = 6,
                 min_spread: float = 0.1, ambiguity_chi2: float = 25.0,
                 max_reprojection_px: float = 1.0,
                 min_pixel_sigma: float = 0.02):
        self.intrinsics = load_intrinsics(intrinsics) if isinstance(intrinsics, str) \
            else intrinsics
        if not isinstance(self.intrinsics, Intrinsics):
            raise ValueError("intrinsics: expected an Intrinsics or a path to a YAML/JSON file")
        self.board = board or BoardSpec()
        if self.board.kind == "charuco" and min_corners < 4:
            raise ValueError(f"min_corners: PnP needs at least 4, got {min_corners}")
        self.name = name
        self.min_corners = int(min_corners)
        self.min_spread = float(min_spread)
        self.ambiguity_chi2 = float(ambiguity_chi2)
        self.max_reprojection_px = float(max_reprojection_px)
        self.min_pixel_sigma = float(min_pixel_sigma)
        self.last_rejection: Optional[Rejection] = None
        self.last_detection: Optional[Detection] = None
        if self.board.kind == "charuco":
            self._cv_board = self.board.cv_board
            self._detector = cv2.aruco.CharucoDetector(
                self._cv_board, cv2.aruco.CharucoParameters(), cv2.aruco.DetectorParameters(),
                cv2.aruco.RefineParameters())
        else:
            params = cv2.aruco.DetectorParameters()
            params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
            self._detector = cv2.aruco.ArucoDetector(self.board.dictionary, params)
            h = self.board.marker_length / 2
            # ArUco corner order: top-left, top-right, bottom-right, bottom-left (y down)
            self._marker_obj = np.array([[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0]],
                                        dtype=np.float64)
        self.frames = open_frames(source) if source is not None else None
        self.exhausted = False

    # ---- detection ---------------------------------------------------------------------------
    def _points(self, gray) -> Union[tuple[np.ndarray, np.ndarray, np.ndarray], Rejection]:
        if self.board.kind == "charuco":
            corners, ids, _, marker_ids = self._detector.detectBoard(gray)
            n = 0 if ids is None else len(ids)
            if n == 0 and (marker_ids is None or len(marker_ids) == 0):
                return Rejection("no_board", "no board in view (no markers found)")
            if n < self.min_corners:
                return Rejection("too_few_corners", f"too few ChArUco corners: {n} < "
                                 f"{self.min_corners}", n)
            obj, img = self._cv_board.matchImagePoints(corners, ids)
            return (obj.reshape(-1, 3).astype(np.float64), img.reshape(-1, 2).astype(np.float64),
                    ids.ravel())
        corners, ids, _ = self._detector.detectMarkers(gray)
        if ids is None or len(ids) == 0:
            return Rejection("no_board", "no marker in view")
        ids = ids.ravel()
        if self.board.marker_id is None:
            if len(ids) > 1:
                return Rejection("no_board", f"{len(ids)} markers in view ({sorted(ids)}) and "
                                 "no marker_id chosen")
            k = 0
        else:
            hits = np.flatnonzero(ids == self.board.marker_id)
            if hits.size == 0:
                return Rejection("no_board", f"marker {self.board.marker_id} not in view "
                                 f"(saw {sorted(ids.tolist())})")
            k = int(hits[0])
        return (self._marker_obj.copy(), corners[k].reshape(4, 2).astype(np.float64),
                ids[k:k + 1])

    def detect(self, image: np.ndarray) -> Union[Detection, Rejection]:
        """Detect the board in one image (grey or BGR). Also sets ``last_detection`` /
        ``last_rejection``."""
        result = self._detect(_to_gray(image))
        if isinstance(result, Rejection):
            self.last_rejection = result
        else:
            self.last_detection = result
        return result

    def _pnp(self, obj: np.ndarray, img: np.ndarray):
        """IPPE's solutions (SQPnP's for a view IPPE cannot take) and the sum of squared
        reprojection errors of each: ``(rvecs, tvecs, ss)``, or a :class:`Rejection`."""
        K, dist = self.intrinsics.K, self.intrinsics.dist
        n = len(obj)
        try:
            count, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, K, dist,
                                                         flags=cv2.SOLVEPNP_IPPE)
            good = [k for k in range(count)
                    if np.all(np.isfinite(rvecs[k])) and np.all(np.isfinite(tvecs[k]))]
            rvecs = [rvecs[k] for k in good]
            tvecs = [tvecs[k] for k in good]
            if not rvecs:
                # IPPE's decomposition divides by the tilt, so it returns NaN for an exactly
                # fronto-parallel view; there its two solutions coincide and there is no flip.
                count, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, K, dist,
                                                             flags=cv2.SOLVEPNP_SQPNP)
        except cv2.error as e:
            return Rejection("pnp_failed", f"solvePnP failed: {getattr(e, 'msg', e)}", n)
        if not rvecs or not np.all(np.isfinite(rvecs[0])):
            return Rejection("pnp_failed", "solvePnP found no solution", n)
        ss = []
        for rv, tv in zip(rvecs, tvecs):
            p, _ = cv2.projectPoints(obj, rv, tv, K, dist)
            ss.append(float(np.sum((p.reshape(-1, 2) - img) ** 2)))
        return rvecs, tvecs, ss

    def _refine_corners(self, gray: np.ndarray, obj: np.ndarray, img: np.ndarray, rvec,
                        tvec) -> np.ndarray:
        """The ChArUco corners refined again with windows that keep off the markers
        (:func:`~dqpose.drivers.charuco_corners.refine_off_markers`); a subclass can keep
        OpenCV's corners instead (tests/bench/bench_handeye.py compares the two)."""
        return refine_off_markers(gray, obj, img, rvec, tvec, self.intrinsics, self.board)

    def _detect(self, gray: np.ndarray) -> Union[Detection, Rejection]:
        pts = self._points(gray)
        if isinstance(pts, Rejection):
            return pts
        obj, img, ids = pts
        n = len(obj)
        centred = obj[:, :2] - obj[:, :2].mean(axis=0)
        sv = np.linalg.svd(centred, compute_uv=False)
        spread = sv[1] / sv[0] if sv[0] > 0 else 0.0
        if spread < self.min_spread:
            return Rejection("collinear", f"corners nearly collinear (spread {spread:.3f} < "
                             f"{self.min_spread})", n)
        K, dist = self.intrinsics.K, self.intrinsics.dist
        found = self._pnp(obj, img)
        if isinstance(found, Rejection):
            return found
        if self.board.kind == "charuco":
            best = int(np.argmin(found[2]))
            img = self._refine_corners(gray, obj, img, found[0][best], found[1][best])
            found = self._pnp(obj, img)
            if isinstance(found, Rejection):
                return found
        rvecs, tvecs, ss = found
        order = np.argsort(ss)
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvecs[order[0]].copy(),
                                          tvecs[order[0]].copy())
        if not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
            return Rejection("pnp_failed", "pose refinement diverged", n)
        proj, J = cv2.projectPoints(obj, rvec, tvec, K, dist)
        r = (proj.reshape(-1, 2) - img).ravel()
        rms = float(math.sqrt(np.sum(r ** 2) / n))   # RMS point distance in pixels
        if not math.isfinite(rms) or rms > self.max_reprojection_px:
            return Rejection("reprojection", f"reprojection error {rms:.3f} px > "
                             f"{self.max_reprojection_px} px", n)
        if float(tvec[2, 0]) <= 0:
            return Rejection("pnp_failed", "solution puts the board behind the camera", n)
        R, _ = cv2.Rodrigues(rvec)
        J_delta = J[:, 0:6] @ pnp_chart(rvec)
        dof = max(2 * n - 6, 1)
        s2 = max(float(r @ r) / dof, self.min_pixel_sigma ** 2)   # the flip test's unit
        # the covariance's: its inverse is the unbiased information (module doc)
        s2_cov = max(float(r @ r) / max(dof - 2, 2), self.min_pixel_sigma ** 2)
        try:
            info = J_delta.T @ J_delta / s2
            cov = np.linalg.inv(info) * (s2_cov / s2)
        except np.linalg.LinAlgError:
            return Rejection("collinear", "pose is not observable from these corners "
                             "(singular Jacobian)", n)
        cov = 0.5 * (cov + cov.T)
        M = np.eye(4)
        M[:3, :3] = R
        M[:3, 3] = tvec.ravel()
        pose = dq.from_matrix(M)
        # The planar flip: IPPE's other solution is a distinct local minimum. It matters when it
        # explains the corners almost as well (small chi-square difference) yet lies outside the
        # uncertainty of the accepted pose (large Mahalanobis distance); when both are small the
        # two solutions are one blurry minimum that the covariance already describes.
        ambiguity = math.inf
        if len(rvecs) > 1:
            ambiguity = (ss[order[1]] - float(r @ r)) / s2
            Rf, _ = cv2.Rodrigues(rvecs[order[1]])
            Mf = np.eye(4)
            Mf[:3, :3] = Rf
            Mf[:3, 3] = np.ravel(tvecs[order[1]])
            d_flip = 2.0 * dq.log(dq.mul(dq.inv(pose), dq.from_matrix(Mf)))
            apart = float(d_flip @ info @ d_flip)
            if ambiguity < self.ambiguity_chi2 and apart > self.ambiguity_chi2:
                return Rejection("ambiguous", f"ambiguous pose: IPPE's flipped solution "
                                 f"reprojects with {math.sqrt(ss[order[1]] / n):.3f} px RMS "
                                 f"against {rms:.3f} px (chi-square difference {ambiguity:.1f} "
                                 f"< {self.ambiguity_chi2:g}) but lies "
                                 f"{math.sqrt(apart):.1f} sigma away", n)
        return Detection(pose=pose, covariance=cov, rms=rms, n_points=n,
                         ambiguity=ambiguity, ids=np.asarray(ids), image_points=img,
                         object_points=obj)

    # ---- PoseSource ---------------------------------------------------------------------------
    def grab(self, timeout: Optional[float] = None) -> Optional[np.ndarray]:
        """The next frame of ``source`` (None at its end; ``TimeoutError`` when a live source
        gives none within ``timeout`` seconds)."""
        if self.frames is None:
            raise ValueError("source: this camera has no frame source; call detect(image)")
        frame = self.frames.read(timeout)
        if frame is None:
            self.exhausted = True
        return frame

    def read(self, timeout: Optional[float] = None) -> Optional[Measurement]:
        """The next frame as a measurement; None when the view was rejected, or no frame came
        within ``timeout`` seconds (see ``last_rejection``), or the source has ended
        (``exhausted``)."""
        try:
            frame = self.grab(timeout)
        except TimeoutError as e:
            self.last_rejection = Rejection("no_frame", f"camera {self.name}: {e}")
            return None
        if frame is None:
            return None
        stamp = time.time()
        result = self.detect(frame)
        if isinstance(result, Rejection):
            return None
        self.last_rejection = None
        return Measurement(source=self.name, time=stamp, pose=result.pose,
                           covariance=result.covariance)

    def __iter__(self) -> Iterator[Measurement]:
        """Accepted views until the source ends (rejected views are skipped)."""
        while True:
            m = self.read()
            if m is not None:
                yield m
            elif self.exhausted:
                return

    def close(self) -> None:
        if self.frames is not None:
            self.frames.close()
