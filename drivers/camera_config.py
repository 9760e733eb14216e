"""What a camera pose source is configured with: pinhole :class:`Intrinsics` and the target
(:class:`BoardSpec`, a ChArUco board or one ArUco marker), each also read from YAML or JSON
(:func:`load_intrinsics`, ROS ``camera_info`` and OpenCV files included; :func:`load_board`).
Lengths in metres, pixel sizes ``(width, height)``; a bad value raises ``ValueError`` naming it.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from typing import Optional

import cv2
import numpy as np

__all__ = ["Intrinsics", "BoardSpec", "load_intrinsics", "load_board"]


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
