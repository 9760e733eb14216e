"""A simulated camera: renders a ChArUco board (or one ArUco marker) seen from a given pose with
given pinhole intrinsics, so the real detector runs on real pixels.

The board texture is warped into the image with the homography ``K [r1 r2 t] S`` (``S`` maps
texture pixels to board metres), at 4x supersampling, then downsampled with ``INTER_AREA``
(which averages, like a sensor pixel integrates light); optional Gaussian blur and noise follow.
Board frame as in :mod:`dqpose.drivers.camera`: origin at the outer top-left chessboard corner, x
along the squares, y down the board, z into the board.

From the shell: ``dqpose sim camera --out DIR --count 20`` writes rendered views and their true
poses (``poses.json``).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
from typing import Optional, Sequence

import cv2
import numpy as np

from dqpose import dq
from dqpose.drivers.camera_config import BoardSpec, Intrinsics

__all__ = ["BoardRenderer", "look_at", "random_view", "main", "add_arguments", "run",
           "DEFAULT_INTRINSICS"]

#: a 640x480 camera with a ~62 deg horizontal field of view, no distortion
DEFAULT_INTRINSICS = Intrinsics(K=np.array([[530.0, 0.0, 319.5], [0.0, 530.0, 239.5],
                                            [0.0, 0.0, 1.0]]),
                                dist=np.zeros(5), size=(640, 480))

_SS = 4  # supersampling factor


class BoardRenderer:
    """Renders ``board`` (a :class:`dqpose.drivers.camera.BoardSpec`) into ``intrinsics``' images.

    ``pixels_per_metre`` sets the texture resolution; it should exceed the image's pixels per
    metre on the board times the supersampling factor, or the render gets soft.
    """

    def __init__(self, board: Optional[BoardSpec] = None,
                 intrinsics: Intrinsics = DEFAULT_INTRINSICS, *,
                 pixels_per_metre: float = 8000.0, background: int = 110):
        self.board = board or BoardSpec()
        self.intrinsics = intrinsics
        if np.any(np.asarray(intrinsics.dist) != 0):
            raise ValueError("intrinsics.dist: the renderer is pinhole only; pass zero distortion")
        if not 0 <= background <= 255:
            raise ValueError(f"background: must be a grey level 0..255, got {background}")
        self.background = int(background)
        ppm = float(pixels_per_metre)
        w_m, h_m = self.board.extent
        # A white margin of one square around the board, as printed boards have.
        margin_m = self.board.square_length if self.board.kind == "charuco" else \
            self.board.marker_length / 4
        margin = int(round(margin_m * ppm))
        inner = (int(round(w_m * ppm)), int(round(h_m * ppm)))
        size = (inner[0] + 2 * margin, inner[1] + 2 * margin)
        if self.board.kind == "charuco":
            tex = self.board.cv_board.generateImage(size, marginSize=margin, borderBits=1)
        else:
            # generateImageMarker draws the marker with its black border filling side pixels.
            tex = np.full((size[1], size[0]), 255, np.uint8)
            tex[margin:margin + inner[1], margin:margin + inner[0]] = \
                cv2.aruco.generateImageMarker(self.board.dictionary, self.board.marker_id,
                                              inner[0], borderBits=1)
        self.texture = tex
        # Texture pixel (u, v) centres sit at board point ((u + 0.5 - margin)/ppm, ...), the
        # pixel grid's left edge being board x = -margin/ppm.
        sx, sy = w_m / inner[0], h_m / inner[1]
        self._S = np.array([[sx, 0.0, (0.5 - margin) * sx],
                            [0.0, sy, (0.5 - margin) * sy],
                            [0.0, 0.0, 1.0]])
        # the board-frame origin: for a single marker it is the marker centre
        if self.board.kind == "marker":
            half = self.board.marker_length / 2
            self._S = np.array([[1, 0, -half], [0, 1, -half], [0, 0, 1.0]]) @ self._S

    def homography(self, T_camera_board) -> np.ndarray:
        """Texture pixels to image pixels (at 1x)."""
        M = dq.to_matrix(np.asarray(T_camera_board, dtype=float))
        P = np.column_stack([M[:3, 0], M[:3, 1], M[:3, 3]])
        return self.intrinsics.K @ P @ self._S

    def render(self, T_camera_board, *, blur: float = 0.0, noise: float = 0.0,
               rng: Optional[np.random.Generator] = None) -> np.ndarray:
        """A grey ``uint8`` image of the board at ``T_camera_board``. ``blur`` is the Gaussian
        sigma in pixels, ``noise`` the standard deviation in grey levels."""
        T = np.asarray(T_camera_board, dtype=float)
        if T.shape != (8,):
            raise ValueError(f"T_camera_board: expected shape (8,), got {T.shape}")
        if dq.to_matrix(T)[2, 3] <= 0:
            raise ValueError("T_camera_board: the board is behind the camera (z <= 0)")
        w, h = self.intrinsics.size
        # 1x pixel x covers [x - 0.5, x + 0.5), i.e. 4x pixels 4x .. 4x + 3 with centre 4x + 1.5.
        A = np.array([[_SS, 0, (_SS - 1) / 2], [0, _SS, (_SS - 1) / 2], [0, 0, 1.0]])
        H = A @ self.homography(T)
        big = cv2.warpPerspective(self.texture, H, (w * _SS, h * _SS), flags=cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_CONSTANT, borderValue=self.background)
        img = cv2.resize(big, (w, h), interpolation=cv2.INTER_AREA)
        if blur > 0:
            img = cv2.GaussianBlur(img, (0, 0), blur)
        if noise > 0:
            rng = rng or np.random.default_rng()
            img = np.clip(img + rng.normal(0.0, noise, img.shape), 0, 255).round().astype(np.uint8)
        return img


def look_at(eye_board, target_board, up_board=(0.0, -1.0, 0.0)) -> np.ndarray:
    """``T_camera_board`` for a camera at ``eye`` (board frame) looking at ``target``, image
    up roughly along ``up``."""
    eye, tgt, up = (np.asarray(v, dtype=float) for v in (eye_board, target_board, up_board))
    z = tgt - eye
    z /= np.linalg.norm(z)
    x = np.cross(-up, z)  # image x is right, y down: y = z cross x
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("up_board: parallel to the viewing direction")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    M = np.eye(4)
    M[:3, :3] = np.column_stack([x, y, z])  # R_board_camera
    M[:3, 3] = eye
    return dq.inv(dq.from_matrix(M))


def random_view(rng: np.random.Generator, board: Optional[BoardSpec] = None,
                distance: tuple[float, float] = (0.3, 0.6), max_tilt_deg: float = 40.0,
                max_roll_deg: float = 30.0, jitter: float = 0.02) -> np.ndarray:
    """A random ``T_camera_board`` looking at the board centre (plus ``jitter`` metres) from
    ``distance`` metres, tilted up to ``max_tilt_deg`` off the board normal."""
    board = board or BoardSpec()
    w, h = board.extent
    centre = np.array([w / 2, h / 2, 0.0]) if board.kind == "charuco" else np.zeros(3)
    centre[:2] += rng.uniform(-jitter, jitter, 2)
    tilt = math.radians(rng.uniform(0, max_tilt_deg))
    az = rng.uniform(-math.pi, math.pi)
    d = rng.uniform(*distance)
    # the camera sits on the -z side (z points into the board)
    direction = np.array([math.sin(tilt) * math.cos(az), math.sin(tilt) * math.sin(az),
                          -math.cos(tilt)])
    roll = math.radians(rng.uniform(-max_roll_deg, max_roll_deg))
    up = np.array([math.sin(roll), -math.cos(roll), 0.0])
    return look_at(centre + d * direction, centre, up)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, help="folder to write the images into")
    p.add_argument("--count", type=int, default=20, help="number of random views (default 20)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--blur", type=float, default=0.0, help="Gaussian blur sigma in pixels")
    p.add_argument("--noise", type=float, default=0.0, help="noise sigma in grey levels")
    p.add_argument("--intrinsics", default=None,
                   help="YAML/JSON intrinsics (default: built-in 640x480, f = 530 px)")
    p.add_argument("--board", default=None, help="YAML/JSON board description (default 7x5 "
                   "ChArUco, 40 mm squares, 30 mm markers, DICT_5X5_100)")


def run(args: argparse.Namespace) -> int:
    from dqpose.drivers.camera_config import load_board, load_intrinsics
    if args.count < 1:
        print("dqpose sim camera: --count must be at least 1")
        return 2
    try:
        intr = load_intrinsics(args.intrinsics) if args.intrinsics else DEFAULT_INTRINSICS
        board = load_board(args.board) if args.board else BoardSpec()
        renderer = BoardRenderer(board, intr)
    except ValueError as e:
        print(f"dqpose sim camera: {e}")
        return 2
    os.makedirs(args.out, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    truth = {}
    views = range(args.count)
    if args.count >= 50 and sys.stderr.isatty():   # ~50 ms a view: worth a bar past a few seconds
        from tqdm import tqdm
        views = tqdm(views, desc="rendering", unit="view", leave=False)
    for i in views:
        T = random_view(rng, board)
        name = f"view_{i:04d}.png"
        img = renderer.render(T, blur=args.blur, noise=args.noise, rng=rng)
        if not cv2.imwrite(os.path.join(args.out, name), img):
            print(f"dqpose sim camera: cannot write {os.path.join(args.out, name)}")
            return 1
        truth[name] = T.tolist()
    with open(os.path.join(args.out, "poses.json"), "w") as f:
        json.dump({"T_camera_board": truth, "K": intr.K.tolist(), "dist": intr.dist.tolist(),
                   "image_size": list(intr.size)}, f, indent=1)
    print(f"wrote {args.count} views to {args.out}")
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="dqpose sim camera", description=__doc__.split("\n\n")[0])
    add_arguments(p)
    return run(p.parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
