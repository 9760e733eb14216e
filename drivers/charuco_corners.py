"""ChArUco corners refined off the markers: each corner's ``cornerSubPix`` window is the largest
square around it whose pixels stay out of the two markers beside it (:func:`marker_free_reach`,
from the board's local scale in the image), within bounds measured on rendered boards
(:func:`refine_off_markers`). OpenCV's own window reaches into those markers, whose edges pull
every corner of a view the same way under perspective: an error the corners share, which no
residual shows (BENCHMARKS.md, "Issue 11: the corners' shared error").
"""
from __future__ import annotations

import cv2
import numpy as np

from dqpose.drivers.camera_config import BoardSpec, Intrinsics

__all__ = ["marker_free_reach", "refine_off_markers"]

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


def refine_off_markers(gray: np.ndarray, obj: np.ndarray, img: np.ndarray, rvec, tvec,
                       intrinsics: Intrinsics, board: BoardSpec) -> np.ndarray:
    """ChArUco corners ``img`` (their board points ``obj``, a pose ``(rvec, tvec)`` that fits them)
    refined again in ``gray`` with windows that keep off the markers.

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
    K, dist = intrinsics.K, intrinsics.dist
    h = 1e-3 * board.square_length
    n = len(obj)
    moved = np.concatenate([obj, obj + [h, 0.0, 0.0], obj + [0.0, h, 0.0]])
    p, _ = cv2.projectPoints(moved, rvec, tvec, K, dist)
    p = p.reshape(3, n, 2)
    J = np.stack([p[1] - p[0], p[2] - p[0]], axis=-1) / h   # image px per board metre
    gap = (board.square_length - board.marker_length) / 2
    half = np.clip(np.floor(marker_free_reach(J, gap) - _SUBPIX_REACH), _MIN_SUBPIX_WINDOW,
                   _MAX_SUBPIX_WINDOW)
    out = img.copy()
    for w in np.unique(half).astype(int):
        sel = half == w
        q = cv2.cornerSubPix(gray, img[sel].astype(np.float32).reshape(-1, 1, 2), (w, w),
                             (-1, -1), _SUBPIX_CRITERIA)
        out[sel] = q.reshape(-1, 2)
    return out
