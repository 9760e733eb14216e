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
(:meth:`CharucoCamera._refine_corners`). OpenCV's window reaches into those markers, whose edges
pull every corner of a view the same way under perspective (toward the far side of the board):
an error shared by all of a view's corners, invisible in the residuals, that made each pose's
covariance too confident and hand-eye calibration end to end claim too much (mean NEES of X 8.9
instead of 6; docs/benchmarks/handeye.md#corner-detection).

Covariance convention: the fusion convention of :class:`dqpose.drivers.base.Measurement`, a right
(body-frame) perturbation with the SE(3) exponential, ``T_true = T_est * Exp(xi)``,
``xi = (omega, v)``, rotation first (radians), then translation (metres), both in the board
frame (GTSAM's ``Pose3``). It is ``s^2 (J^T J)^-1`` with ``J`` the Jacobian of the reprojected
corners with respect to ``xi`` at 0 and ``s^2`` the residual variance per pixel coordinate
(``sum r^2 / (2N - 6)``, floored at ``min_pixel_sigma^2``). OpenCV's Jacobian is with respect
to its own parameters, the rotation vector and translation ``(rvec, tvec)``; :func:`pnp_chart`
is the exact chain-rule factor from ``xi`` to them.
"""
from __future__ import annotations

import glob
import json
import math
import os
import threading
import time
from dataclasses import dataclass, field
from typing import Iterator, Optional, Union

import cv2
import numpy as np

from dqpose.drivers.base import Measurement, PoseSource
from dqpose import dq, lie

__all__ = ["Intrinsics", "BoardSpec", "Detection", "Rejection", "CharucoCamera", "pnp_chart",
           "marker_free_reach", "load_intrinsics", "load_board", "open_frames", "FolderFrames",
           "VideoFrames", "IMAGE_EXTENSIONS"]

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")


# ---- configuration -----------------------------------------------------------------------------
@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics: ``K`` 3x3, OpenCV distortion coefficients, image ``size`` (w, h)."""
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    size: tuple[int, int] = (640, 480)

    def __post_init__(self):
        K = np.asarray(self.K, dtype=float)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise ValueError(f"K: expected a finite 3x3 matrix, got shape {K.shape}")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1 or np.any(K[[1, 2, 2], [0, 0, 1]] != 0):
            raise ValueError("K: expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
        dist = np.asarray(self.dist, dtype=float).ravel()
        if dist.size not in (0, 4, 5, 8, 12, 14) or not np.all(np.isfinite(dist)):
            raise ValueError(f"dist: expected 4, 5, 8, 12 or 14 finite coefficients, got "
                             f"{dist.size}")
        size = tuple(int(v) for v in self.size)
        if len(size) != 2 or min(size) <= 0:
            raise ValueError(f"size: expected (width, height) > 0, got {self.size!r}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist if dist.size else np.zeros(5))
        object.__setattr__(self, "size", size)


def _read_mapping(path: str, what: str) -> dict:
    if not os.path.isfile(path):
        raise ValueError(f"{what}: no such file: {path!r}")
    with open(path, "r", encoding="utf-8") as f:
        text = f.read()
    try:
        if path.lower().endswith(".json"):
            data = json.loads(text)
        else:
            import yaml
            # OpenCV FileStorage YAML starts with a %YAML directive and tags matrices.
            if text.startswith("%YAML"):
                text = text.split("\n", 1)[1].replace("!!opencv-matrix", "")
            data = yaml.safe_load(text)
    except Exception as e:  # json and yaml raise different types; the message is what matters
        raise ValueError(f"{what}: cannot parse {path!r}: {e}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{what}: {path!r} does not hold a mapping")
    return data


def _matrix(value, key: str, shape=None) -> np.ndarray:
    # OpenCV / ROS style {rows, cols, data}
    if isinstance(value, dict) and "data" in value:
        a = np.asarray(value["data"], dtype=float)
        if "rows" in value and "cols" in value:
            a = a.reshape(int(value["rows"]), int(value["cols"]))
    else:
        try:
            a = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            raise ValueError(f"{key}: not a numeric array") from None
    if shape is not None:
        if a.size != int(np.prod(shape)):
            raise ValueError(f"{key}: expected {int(np.prod(shape))} numbers, got {a.size}")
        a = a.reshape(shape)
    return a


def load_intrinsics(path: str) -> Intrinsics:
    """Read intrinsics from YAML or JSON. Accepted keys: ``K`` / ``camera_matrix`` (3x3 nested
    list, 9 numbers, or ``{rows, cols, data}``), ``dist`` / ``distortion`` /
    ``distortion_coefficients`` / ``D``, and ``image_size`` / ``size`` ``[w, h]`` or
    ``image_width`` + ``image_height`` (ROS ``camera_info`` and OpenCV files both work)."""
    data = _read_mapping(path, "intrinsics")

    def pick(*keys):
        for k in keys:
            if k in data:
                return k, data[k]
        return None, None
    k, K = pick("K", "camera_matrix", "cameraMatrix")
    if K is None:
        raise ValueError(f"intrinsics: {path!r} has no K (or camera_matrix)")
    K = _matrix(K, f"intrinsics.{k}", (3, 3))
    kd, dist = pick("dist", "distortion", "distortion_coefficients", "dist_coeffs", "D")
    dist = np.zeros(5) if dist is None else _matrix(dist, f"intrinsics.{kd}").ravel()
    ks, size = pick("image_size", "size")
    if size is None:
        if "image_width" in data and "image_height" in data:
            size = (data["image_width"], data["image_height"])
        else:
            raise ValueError(f"intrinsics: {path!r} has no image_size (or image_width and "
                             "image_height)")
    try:
        size = tuple(int(v) for v in _matrix(size, "intrinsics.image_size").ravel())
    except ValueError:
        raise ValueError(f"intrinsics.image_size: expected [width, height], got {size!r}") \
            from None
    return Intrinsics(K=K, dist=dist, size=size)


@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board (``kind="charuco"``: ``squares`` (x, y), ``square_length`` and
    ``marker_length`` in metres) or one ArUco marker (``kind="marker"``: ``marker_length``,
    ``marker_id``; None accepts the only marker in view)."""
    kind: str = "charuco"
    squares: tuple[int, int] = (7, 5)
    square_length: float = 0.04
    marker_length: float = 0.03
    dictionary_name: str = "DICT_5X5_100"
    marker_id: Optional[int] = None

    def __post_init__(self):
        if self.kind not in ("charuco", "marker"):
            raise ValueError(f"board.kind: expected 'charuco' or 'marker', got {self.kind!r}")
        if not hasattr(cv2.aruco, self.dictionary_name) or \
                not self.dictionary_name.startswith("DICT_"):
            raise ValueError(f"board.dictionary_name: unknown ArUco dictionary "
                             f"{self.dictionary_name!r}")
        if not (self.marker_length > 0 and math.isfinite(self.marker_length)):
            raise ValueError(f"board.marker_length: must be positive, got {self.marker_length}")
        if self.kind == "charuco":
            sx, sy = (int(v) for v in self.squares)
            if sx < 2 or sy < 2:
                raise ValueError(f"board.squares: need at least 2x2 squares, got {self.squares}")
            if not self.square_length > self.marker_length:
                raise ValueError("board.marker_length: must be smaller than square_length")
            object.__setattr__(self, "squares", (sx, sy))

    @property
    def dictionary(self):
        return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary_name))

    @property
    def cv_board(self) -> "cv2.aruco.CharucoBoard":
        return cv2.aruco.CharucoBoard(self.squares, self.square_length, self.marker_length,
                                      self.dictionary)

    @property
    def extent(self) -> tuple[float, float]:
        """Width and height of the pattern in metres."""
        if self.kind == "charuco":
            return self.squares[0] * self.square_length, self.squares[1] * self.square_length
        return self.marker_length, self.marker_length

    @property
    def n_corners(self) -> int:
        return (self.squares[0] - 1) * (self.squares[1] - 1) if self.kind == "charuco" else 4


def load_board(path: str) -> BoardSpec:
    """A :class:`BoardSpec` from YAML/JSON with the same field names."""
    data = _read_mapping(path, "board")
    allowed = {"kind", "squares", "square_length", "marker_length", "dictionary_name",
               "marker_id"}
    extra = set(data) - allowed
    if extra:
        raise ValueError(f"board: unknown keys {sorted(extra)} in {path!r}")
    if "squares" in data:
        data["squares"] = tuple(data["squares"])
    return BoardSpec(**data)


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


# ---- frame sources -----------------------------------------------------------------------------
class FolderFrames:
    """Images of a folder in name order. An unreadable image raises ``ValueError``."""

    def __init__(self, folder: str):
        if not os.path.isdir(folder):
            raise ValueError(f"source: no such folder: {folder!r}")
        self.paths = sorted(p for p in glob.glob(os.path.join(folder, "*"))
                            if p.lower().endswith(IMAGE_EXTENSIONS))
        if not self.paths:
            raise ValueError(f"source: no images ({', '.join(IMAGE_EXTENSIONS)}) in {folder!r}")
        self._next = 0
        self.current: Optional[str] = None

    def read(self, timeout: Optional[float] = None) -> Optional[np.ndarray]:
        if self._next >= len(self.paths):
            return None
        path = self.paths[self._next]
        self._next += 1
        self.current = path
        return read_image(path)

    def close(self) -> None:
        pass


class VideoFrames:
    """A ``cv2.VideoCapture`` device index or video file."""

    def __init__(self, source: Union[int, str]):
        self.cap = cv2.VideoCapture(source)
        if not self.cap.isOpened():
            self.cap.release()
            what = f"camera device {source}" if isinstance(source, int) else f"video {source!r}"
            raise ValueError(f"source: cannot open {what}")
        self.current = source

    def read(self, timeout: Optional[float] = None) -> Optional[np.ndarray]:
        ok, frame = self.cap.read()
        return frame if ok else None

    def close(self) -> None:
        self.cap.release()


class LiveFrames:
    """A live frame source (a camera device) read by a background thread that keeps only the
    newest frame: ``read(timeout)`` returns a frame not returned before, waits at most
    ``timeout`` seconds for one (then raises ``TimeoutError``: a stalled or unplugged camera must
    not hang a fusion loop), and returns None once the source has ended. A consumer slower than
    the camera skips frames instead of falling behind; ``dropped`` counts them."""

    def __init__(self, frames):
        self._frames = frames
        self.current = getattr(frames, "current", None)
        self._cond = threading.Condition()
        self._frame: Optional[np.ndarray] = None
        self._fresh = False
        self._ended = False
        self._error: Optional[BaseException] = None
        self._closing = False
        self.dropped = 0
        self._thread = threading.Thread(target=self._run, name="camera-frames", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            while not self._closing:
                frame = self._frames.read()
                with self._cond:
                    if frame is None:
                        break
                    self.dropped += self._fresh
                    self._frame, self._fresh = frame, True
                    self._cond.notify_all()
        except Exception as e:   # handed to the reader, which raises it
            self._error = e
        with self._cond:
            self._ended = True
            self._cond.notify_all()

    def read(self, timeout: Optional[float] = None) -> Optional[np.ndarray]:
        with self._cond:
            if not self._cond.wait_for(lambda: self._fresh or self._ended, timeout):
                raise TimeoutError(f"no frame within {timeout:g} s")
            if self._fresh:
                self._fresh = False
                return self._frame
            if self._error is not None:
                raise self._error
            return None

    def close(self) -> None:
        self._closing = True
        self._frames.close()        # also unblocks a read() in progress on most backends
        self._thread.join(timeout=2.0)


def read_image(path: str) -> np.ndarray:
    if not os.path.isfile(path):
        raise ValueError(f"image: no such file: {path!r}")
    img = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"image: cannot decode {path!r} (not an image, or corrupt)")
    return img


def open_frames(source: Union[int, str]):
    """A device index (int or digit string), a folder of images, one image, a video file, or a
    frame source object (``read(timeout=None)`` and ``close()``), used as it is."""
    if isinstance(source, (int, np.integer)) or (isinstance(source, str) and source.isdigit()):
        return LiveFrames(VideoFrames(int(source)))
    if callable(getattr(source, "read", None)) and callable(getattr(source, "close", None)):
        return source
    if not isinstance(source, (str, os.PathLike)):
        raise ValueError(f"source: expected a device index or a path, got {source!r}")
    source = os.fspath(source)
    if os.path.isdir(source):
        return FolderFrames(source)
    if not os.path.exists(source):
        raise ValueError(f"source: no such file or folder: {source!r}")
    if source.lower().endswith(IMAGE_EXTENSIONS):
        frames = FolderFrames.__new__(FolderFrames)
        frames.paths, frames._next, frames.current = [source], 0, None
        return frames
    return VideoFrames(source)


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


#: What ``cornerSubPix`` reads beyond its window, in pixels: the gradient at the window's edge
#: is a central difference of bilinear samples, so it reaches 2 px farther, and the last pixel
#: it reads integrates light from half a pixel beyond its centre.
_SUBPIX_REACH = 2.5
#: window half-sizes: at most OpenCV's own cap for ChArUco corners; at least 3, as smaller
#: windows hold too few edge pixels to fix a corner (on 21,000 clean rendered corners, RMS
#: error 0.18-0.53 px with 3x3 windows, 0.06-0.11 px with 5x5 and 0.05-0.10 px with 7x7, where
#: OpenCV's windows give 0.05-0.09 px); a corner whose markers are nearer than that keeps a 7x7
#: window, which there reaches only the markers' outer rim (pull toward the near side over
#: the 1,230 such corners of 900 views: -0.0005 px)
_MIN_SUBPIX_WINDOW, _MAX_SUBPIX_WINDOW = 3, 10
#: refined to convergence: the refinement starts within ~0.1 px of its answer, and OpenCV's
#: default (stop once a step is under 0.1 px) would keep the start
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)


def marker_free_reach(J, gap: float) -> np.ndarray:
    """For each ChArUco corner, how far (in pixels, as a square's half-size around the corner)
    the image can be read before reaching a marker.

    ``J`` ``(n, 2, 2)``: the board's local scale in the image at each corner, image pixels per
    board metre along the board's x and y. ``gap``: the white gap between a chessboard corner
    and the markers beside it, ``(square_length − marker_length) / 2``; the markers lie where
    both board offsets from the corner are at least ``gap``. The image square ``|u|∞ ≤ r`` maps
    to the board parallelogram ``J⁻¹ u``; the answer is the ``r`` at which it first touches the
    region ``|dx| ≥ gap and |dy| ≥ gap``, i.e. ``gap / max over |u|∞ ≤ 1 of min(|a·u|, |b·u|)``
    (``a``, ``b`` the rows of ``J⁻¹``). For each sign pattern that maximum of the smaller of
    two linear functions over a square lies at a vertex or where the two are equal on an
    edge: six candidates, evaluated exactly.
    """
    Ji = np.linalg.inv(np.asarray(J, dtype=np.float64))
    n = len(Ji)
    best = np.zeros(n)
    for sa, sb in ((1, 1), (1, -1), (-1, 1), (-1, -1)):   # the four markers' quadrants
        a, b = sa * Ji[:, 0, :], sb * Ji[:, 1, :]
        c = a - b
        points = [np.broadcast_to(v, (n, 2))
                  for v in ((1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0))]
        for k in (0, 1):                # on the edge u_k = ±1, where a·u = b·u
            o = 1 - k
            for s in (1.0, -1.0):
                with np.errstate(divide="ignore", invalid="ignore"):
                    uo = -s * c[:, k] / c[:, o]
                u = np.zeros((n, 2))
                u[:, k] = s
                u[:, o] = np.where(np.abs(uo) <= 1, uo, np.nan)
                points.append(u)
        for u in points:
            best = np.fmax(best, np.minimum(np.sum(a * u, axis=1), np.sum(b * u, axis=1)))
    return gap / best


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
        """The ChArUco corners refined again with windows that keep off the markers.

        OpenCV refines each corner with ``cornerSubPix`` in a window of half-size "distance to
        the nearest marker corner − 2 px" (up to 10): a square that reaches into the two
        markers beside the corner, whose edges pull the corner off. Under perspective the pull
        of the nearer marker and the farther one do not cancel, so every corner of a view moves
        the same way (toward the far side of the board: 0.0067 ± 0.0002 px on average over
        3000 rendered views, more at larger tilts): an error the corners share, which no
        residual shows and which made the pose's covariance 1.3–1.5× too confident along the
        directions the corners fix best. Here each window is the largest whose pixels stay out
        of the markers (:func:`marker_free_reach`, from ``(rvec, tvec)``'s local scale of the
        board in the image, lens distortion included), less what ``cornerSubPix`` reads beyond
        its window (``_SUBPIX_REACH``), within ``_MIN_SUBPIX_WINDOW`` .. ``_MAX_SUBPIX_WINDOW``:
        pull −0.0001 ± 0.0002 px (tests/bench/bench_charuco_corners.py)."""
        K, dist = self.intrinsics.K, self.intrinsics.dist
        h = 1e-3 * self.board.square_length
        n = len(obj)
        moved = np.concatenate([obj, obj + [h, 0.0, 0.0], obj + [0.0, h, 0.0]])
        p, _ = cv2.projectPoints(moved, rvec, tvec, K, dist)
        p = p.reshape(3, n, 2)
        J = np.stack([p[1] - p[0], p[2] - p[0]], axis=-1) / h   # image px per board metre
        gap = (self.board.square_length - self.board.marker_length) / 2
        half = np.clip(np.floor(marker_free_reach(J, gap) - _SUBPIX_REACH), _MIN_SUBPIX_WINDOW,
                       _MAX_SUBPIX_WINDOW)
        out = img.copy()
        for w in np.unique(half).astype(int):
            sel = half == w
            q = cv2.cornerSubPix(gray, img[sel].astype(np.float32).reshape(-1, 1, 2), (w, w),
                                 (-1, -1), _SUBPIX_CRITERIA)
            out[sel] = q.reshape(-1, 2)
        return out

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
        s2 = max(float(r @ r) / dof, self.min_pixel_sigma ** 2)
        try:
            info = J_delta.T @ J_delta / s2
            cov = np.linalg.inv(info)
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
