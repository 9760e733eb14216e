"""``dqpose handeye solve DIR``: detects the board in each image with
:class:`dqpose.drivers.camera.CharucoCamera`, solves on a server (the ``dqpose.v1.HandEye``
service) or ``--local``ly by the same code, and writes the report
(:mod:`dqpose.cli.handeye_report`): text (also printed), a PNG (residuals per view, covariance
ellipsoids) and the result as JSON."""
from __future__ import annotations

import argparse
import glob
import math
import os
import re
import sys

from dqpose.cli.common import client, connection_args, failure
from dqpose.cli.handeye_folder import POSE_FILES, find, read_truth
from dqpose.cli.inputs import add_quaternion_order

SOLVE_EPILOG = """\
DIR holds:
  images       one per robot pose (.png, .jpg, ...), the board (ChArUco) in view
  poses.json   the flange pose T_base_flange of each image, as the robot reported it:
                 {"setup": "eye_in_hand", "units": "m", "poses": [
                    {"image": "view_000.png", "base_to_flange": POSE}, ...]}
               POSE: {"position": [x, y, z], "orientation": {"w": .., "x": .., "y": ..,
                     "z": ..}} (or "orientation_xyzw": [x, y, z, w] / "orientation_wxyz":
                     [w, x, y, z]), [x, y, z, rx, ry, rz] (a UR rotation vector, radians),
                     or 7 numbers x, y, z and a quaternion in --quaternion-order's order
  or poses.csv [image,]x,y,z,qx,qy,qz,qw (by header, any order; a file without a header needs
               --quaternion-order) or [image,]x,y,z,rx,ry,rz (UR); without image names the
               poses go with the images in name order
  intrinsics.json (or .yaml)  K, dist, image_size (OpenCV and ROS camera_info files work)
  board.json (optional)       squares, square_length, marker_length, dictionary_name
Positions beyond 3 m are read as millimetres (--units to say), 6-value poses as UR rotation
vectors; the report says so.

writes (next to the images unless told otherwise): handeye_report.txt (printed too),
handeye.png (residuals per view, covariance ellipsoids), handeye.json (X, Z, covariances).
Covariances: 6x6, rotation first, right perturbation T * Exp(xi) (GTSAM Pose3 convention).

example: dqpose handeye capture calib && dqpose handeye solve calib --local
"""


def add_parser(sub) -> None:
    """The ``solve`` action and its options."""
    from dqpose.handeye import SETUPS  # NumPy and the C core: only for this command's help
    s = sub.add_parser("solve", help="solve from a folder of images and robot poses",
                       description="Detect the board in every image of DIR, solve hand-eye "
                                   "with the robot poses (on the server at --server, or "
                                   "--local) and write a report.",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       epilog=SOLVE_EPILOG)
    s.add_argument("dir", metavar="DIR", help="the folder (see below)")
    s.add_argument("--setup", choices=SETUPS,
                   help="eye_in_hand: camera on the flange; eye_to_hand: camera fixed, board "
                        "on the flange (default: the poses file's, else eye_in_hand)")
    s.add_argument("--poses", metavar="FILE", help="robot poses (default: DIR/poses.json or .csv)")
    s.add_argument("--intrinsics", metavar="FILE", help="default: DIR/intrinsics.json or .yaml")
    s.add_argument("--board", metavar="FILE", help="default: DIR/board.json, else 7x5 ChArUco, "
                                                   "40 mm squares, 30 mm markers, DICT_5X5_100")
    s.add_argument("--units", choices=("auto", "m", "mm"), default="auto",
                   help="of the robot positions (default: auto, millimetres beyond 3 m)")
    s.add_argument("--estimate-noise", action="store_true",
                   help="estimate the camera's noise from the residuals (default: each view's "
                        "covariance from the detector, which weighs each view and axis by what "
                        "its corners say)")
    s.add_argument("--robot-noise", nargs=2, type=float, metavar=("DEG", "MM"),
                   help="the robot poses' noise, 1 sigma per axis (default: exact); with the "
                        "detector's covariances only")
    s.add_argument("--corners", action="store_true",
                   help="refine on the detected corners' reprojection too (corner level; on "
                        "the simulator's renders no better than the default, see "
                        "docs/benchmarks/handeye.md)")
    s.add_argument("--refine-focal", action="store_true",
                   help="with --corners: estimate a scale of the focal lengths too")
    s.add_argument("--keep-outliers", action="store_true",
                   help="use every view (default: gross outliers are left out, with reasons)")
    s.add_argument("--report", metavar="TXT", help="default: DIR/handeye_report.txt")
    s.add_argument("--plot", metavar="PNG", help="default: DIR/handeye.png")
    s.add_argument("-o", "--output", metavar="JSON", help="default: DIR/handeye.json")
    s.add_argument("--local", action="store_true",
                   help="solve in this process instead of on a server")
    add_quaternion_order(s)
    connection_args(s)


class _Views:
    """The folder's views: image paths, flange poses, how the poses were read."""

    def __init__(self, args):
        from dqpose.cli.posefile import read_robot_poses
        from dqpose.drivers.camera import IMAGE_EXTENSIONS
        from dqpose.handeye.setups import EYE_IN_HAND
        if not os.path.isdir(args.dir):
            raise ValueError(f"DIR: no such folder: {args.dir!r}")
        path = args.poses or find(args.dir, POSE_FILES)
        if path is None:
            raise ValueError(f"DIR: no {' or '.join(POSE_FILES)} in {args.dir!r} (or give "
                             f"--poses FILE)")
        robot = read_robot_poses(path, args.units, args.quaternion_order)
        if robot.images[0] is not None:
            self.images = [os.path.join(args.dir, im) for im in robot.images]
            missing = [im for im, p in zip(robot.images, self.images) if not os.path.isfile(p)]
            if missing:
                raise ValueError(f"{path}: {len(missing)} image(s) not in {args.dir!r}: "
                                 f"{', '.join(missing[:5])}")
        else:
            self.images = sorted(p for p in glob.glob(os.path.join(args.dir, "*"))
                                 if p.lower().endswith(IMAGE_EXTENSIONS))
            if len(self.images) != len(robot.base_flange):
                raise ValueError(f"{path}: {len(robot.base_flange)} poses for "
                                 f"{len(self.images)} images in {args.dir!r}; name each "
                                 f"pose's image (an \"image\" key or column)")
        self.base_flange = robot.base_flange
        self.notes = list(robot.notes)
        self.setup = args.setup or robot.setup
        if self.setup is None:
            self.setup = EYE_IN_HAND
            self.notes.append("setup: eye_in_hand (the default; --setup eye_to_hand for a "
                              "camera fixed in the cell)")
        self.poses_file = path


def _camera(args):
    from dqpose.drivers.camera import BoardSpec, CharucoCamera, load_board, load_intrinsics
    intr = args.intrinsics or find(args.dir, ("intrinsics.json", "intrinsics.yaml",
                                               "intrinsics.yml"))
    if intr is None:
        raise ValueError(f"--intrinsics: required (no intrinsics.json or .yaml in {args.dir!r})")
    board = args.board or find(args.dir, ("board.json", "board.yaml", "board.yml"))
    return CharucoCamera(load_intrinsics(intr), load_board(board) if board else BoardSpec())


def _detect(camera, images: list) -> list:
    """The detection (or rejection) of each image, with a progress bar on a terminal."""
    from tqdm import tqdm

    from dqpose.drivers.camera import read_image
    return [camera.detect(read_image(p))
            for p in tqdm(images, desc="detecting", unit="image", leave=False, file=sys.stderr,
                          disable=None)]


def _noise(args, detections: list) -> dict:
    """The noise arguments of the solve: the detector's covariance of each view (unless
    ``--estimate-noise``) and ``--robot-noise`` as a diagonal covariance."""
    import numpy as np
    if args.estimate_noise:
        if args.robot_noise:
            raise ValueError("--robot-noise: needs the detector's covariances (drop "
                             "--estimate-noise)")
        return {}
    out = {"camera_covariance": np.array([d.covariance for d in detections]).reshape(-1, 6, 6)}
    if args.robot_noise:
        from dqpose.drivers.base import pose_covariance
        deg, mm = args.robot_noise
        try:
            out["robot_covariance"] = pose_covariance(math.radians(deg), mm * 1e-3)
        except ValueError:
            raise ValueError(f"--robot-noise: two positive numbers, got {deg:g} {mm:g}") \
                from None
    return out


def _corners(args, camera, detections: list) -> dict:
    """``--corners``: each view's detected corners for the corner-level refinement, the image
    points undistorted (the solver's camera is a pinhole)."""
    import numpy as np
    if not args.corners:
        if args.refine_focal:
            raise ValueError("--refine-focal: needs --corners")
        return {}
    K, dist = camera.intrinsics.K, camera.intrinsics.dist
    views = []
    for d in detections:
        u = d.image_points
        if np.any(dist):
            import cv2
            u = cv2.undistortPoints(u.reshape(-1, 1, 2), K, dist, P=K).reshape(-1, 2)
        views.append((d.object_points, u, K))
    return {"corners": views, "refine_focal": args.refine_focal}


def solve(args) -> int:
    import numpy as np

    from dqpose import handeye
    from dqpose.cli import handeye_report
    names: list = []
    try:
        views = _Views(args)
        camera = _camera(args)
        found = _detect(camera, views.images)
        used = [i for i, d in enumerate(found) if d.ok]
        names = [os.path.basename(views.images[i]) for i in used]
        base_flange = views.base_flange[used]
        camera_target = np.array([found[i].pose for i in used]).reshape(-1, 8)
        noise = _noise(args, [found[i] for i in used])
        noise.update(_corners(args, camera, [found[i] for i in used]))
        robust = not args.keep_outliers
        if args.local:
            cal = handeye.calibrate(base_flange, camera_target, views.setup, robust=robust,
                                    **noise)
        else:
            with client(args) as c:
                cal = c.calibrate(base_flange, camera_target, views.setup, robust=robust,
                                  **noise)
    except Exception as e:
        from_server = hasattr(e, "code")
        if names and isinstance(e, ValueError) and not from_server:
            # the solver's base_flange[3] -> its image
            e = type(e)(handeye_report.with_image_names(str(e), names))
        code = failure("handeye solve", args, e)
        if names and from_server and re.search(r"pairs\[|samples? \d", str(e)):
            # the server's pairs[k] and samples k, by image
            print("dqpose handeye solve: views: " + ", ".join(
                f"pairs[{k}] = {n}" for k, n in enumerate(names)), file=sys.stderr)
        return code
    skipped = [(os.path.basename(views.images[i]), found[i]) for i in range(len(found))
               if not found[i].ok]
    truth = read_truth(args.dir, views.setup)
    text = handeye_report.report(cal, views, names, skipped, truth)
    sys.stdout.write(text)
    return handeye_report.write(args, cal, views, names, truth, text)
