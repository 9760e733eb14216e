"""``dqpose handeye capture`` and ``dqpose handeye solve``: hand-eye calibration from the shell.

``capture DIR`` (:mod:`dqpose.cli.handeye_capture`) drives an arm through informative views of
a ChArUco board and saves the folder ``solve`` reads.

``solve DIR`` detects the board in each image with :class:`dqpose.drivers.camera.CharucoCamera`, solves
on a server (the ``dqpose.v1.HandEye`` service) or ``--local``ly by the same code, and writes a
report: text (also printed), a PNG (residuals per view, covariance ellipsoids) and the result as
JSON.
"""
from __future__ import annotations

import argparse
import glob
import json
import math
import os
import re
import sys

from dqpose.cli import handeye_capture
from dqpose.cli.handeye_capture import POSE_FILES, _find
from dqpose.cli.common import client, connection_args, fail, failure, missing_extra

SETUPS = ("eye_in_hand", "eye_to_hand")
CHOICES = ("next-best", "spread", "random")
SOLVE_EPILOG = """\
DIR holds:
  images       one per robot pose (.png, .jpg, ...), the board (ChArUco) in view
  poses.json   the flange pose T_base_flange of each image, as the robot reported it:
                 {"setup": "eye_in_hand", "units": "m", "poses": [
                    {"image": "view_000.png", "base_to_flange": POSE}, ...]}
               POSE: {"position": {...}, "orientation": {"w", "x", "y", "z"}},
                     [x, y, z, rx, ry, rz] (a UR rotation vector, radians) or
                     [x, y, z, qw, qx, qy, qz]
  or poses.csv [image,]x,y,z,qw,qx,qy,qz  or  [image,]x,y,z,rx,ry,rz (UR); without image
               names the poses go with the images in name order
  intrinsics.json (or .yaml)  K, dist, image_size (OpenCV and ROS camera_info files work)
  board.json (optional)       squares, square_length, marker_length, dictionary_name
Positions beyond 3 m are read as millimetres (--units to say), 6-value poses as UR rotation
vectors; the report says so.

writes (next to the images unless told otherwise): handeye_report.txt (printed too),
handeye.png (residuals per view, covariance ellipsoids), handeye.json (X, Z, covariances).
Covariances: 6x6, rotation first, right perturbation T * Exp(xi) (GTSAM Pose3 convention).

example: dqpose handeye capture calib && dqpose handeye solve calib --local
"""
def configure(name: str, p) -> None:
    p.description = ("Hand-eye calibration: capture views of a ChArUco board on an arm, and "
                     "solve for the camera's pose on the flange (eye-in-hand) or in the cell "
                     "(eye-to-hand) from a folder of images and robot poses.")
    sub = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    c = sub.add_parser("capture", help="drive an arm through informative views and save them",
                       description="Drive a UR through informative views of the board "
                                   "(the simulator, or --arm) and save images and robot poses "
                                   "into DIR for `dqpose handeye solve`.",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       epilog=handeye_capture.CAPTURE_EPILOG)
    c.add_argument("dir", metavar="DIR", help="folder to write (created; one that holds a "
                                              "capture needs --resume or --force)")
    c.add_argument("--setup", choices=SETUPS,
                   help="eye_in_hand (default): camera on the flange; eye_to_hand: camera "
                        "fixed, board on the flange (with --resume: the capture's)")
    c.add_argument("--views", type=int, default=15,
                   help="views to capture (default 15; with --resume, in all)")
    again = c.add_mutually_exclusive_group()
    again.add_argument("--resume", action="store_true",
                       help="continue the capture in DIR (an interrupted one) up to --views, "
                            "with its board, intrinsics and setup")
    again.add_argument("--force", action="store_true",
                       help="start over: the capture's files in DIR (views, poses, intrinsics, "
                            "board, truth, solve's outputs) are removed first")
    c.add_argument("--choose", choices=CHOICES, default="next-best",
                   help="how views are chosen: a spread of rotations, then, once the solver "
                        "has an answer, the candidate that shrinks X's covariance most "
                        "(next-best, the default); the spread rule throughout (spread); or "
                        "the candidates in their random order (random, a baseline)")
    c.add_argument("--arm", metavar="SPEC", help="a real arm, ur:HOST (default: start the "
                                                 "UR simulator)")
    c.add_argument("--camera", metavar="SOURCE", help="with --arm: a device index, video or "
                                                      "folder (drivers.camera.open_frames)")
    c.add_argument("--intrinsics", metavar="FILE", help="with --camera (YAML/JSON)")
    c.add_argument("--board", metavar="FILE", help="YAML/JSON board (default: 7x5 ChArUco)")
    c.add_argument("--speed", type=float, help="tool speed of the moves, m/s (default: 0.25 on "
                                               "an arm, 0.8 on the simulator)")
    c.add_argument("--settle", type=float, default=None,
                   help="seconds to wait after each move before the image (default 0.3 on an "
                        "arm, 0 on the simulator)")
    c.add_argument("--seed", type=int, default=0, help="of the candidate views and the "
                                                       "simulated camera's noise")
    c.add_argument("--noise", type=float, default=2.0,
                   help="simulated camera: pixel noise, grey levels (default 2)")
    c.add_argument("--blur", type=float, default=0.6,
                   help="simulated camera: Gaussian blur, pixels (default 0.6)")
    s = sub.add_parser("solve", help="solve from a folder of images and robot poses",
                       description="Detect the board in every image of DIR, solve hand-eye "
                                   "with the robot poses (on the server at --target, or "
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
                        "the simulator's renders no better than the default, see BENCHMARKS.md)")
    s.add_argument("--refine-focal", action="store_true",
                   help="with --corners: estimate a scale of the focal lengths too")
    s.add_argument("--keep-outliers", action="store_true",
                   help="use every view (default: gross outliers are left out, with reasons)")
    s.add_argument("--report", metavar="TXT", help="default: DIR/handeye_report.txt")
    s.add_argument("--plot", metavar="PNG", help="default: DIR/handeye.png")
    s.add_argument("-o", "--output", metavar="JSON", help="default: DIR/handeye.json")
    s.add_argument("--local", action="store_true", help="solve in this process instead of on a server")
    connection_args(s)
    p.set_defaults(func=_run)


def _run(args) -> int:
    action = {"capture": handeye_capture.capture, "solve": _solve}[args.action]
    try:
        return action(args)
    except ModuleNotFoundError as e:    # OpenCV, ur_rtde: the [devices] extra
        return missing_extra(f"handeye {args.action}", e)



# ---- solve ------------------------------------------------------------------------------------

class _Views:
    """The folder's views: image paths, flange poses, how the poses were read."""

    def __init__(self, args):
        from dqpose.drivers.camera import IMAGE_EXTENSIONS
        from dqpose.cli.posefile import read_robot_poses
        if not os.path.isdir(args.dir):
            raise ValueError(f"DIR: no such folder: {args.dir!r}")
        path = args.poses or _find(args.dir, POSE_FILES)
        if path is None:
            raise ValueError(f"DIR: no {' or '.join(POSE_FILES)} in {args.dir!r} (or give "
                             f"--poses FILE)")
        robot = read_robot_poses(path, args.units)
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
            self.setup = "eye_in_hand"
            self.notes.append("setup: eye_in_hand (the default; --setup eye_to_hand for a "
                              "camera fixed in the cell)")
        self.poses_file = path


def _camera(args):
    from dqpose.drivers.camera import BoardSpec, CharucoCamera, load_board, load_intrinsics
    intr = args.intrinsics or _find(args.dir, ("intrinsics.json", "intrinsics.yaml",
                                               "intrinsics.yml"))
    if intr is None:
        raise ValueError(f"--intrinsics: required (no intrinsics.json or .yaml in {args.dir!r})")
    board = args.board or _find(args.dir, ("board.json", "board.yaml", "board.yml"))
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


def _named(text: str, names: list) -> str:
    """``pairs[3]`` in a message followed by the image it came from."""
    return re.sub(r"\b(pairs|base_flange|camera_target)\[(\d+)\]",
                  lambda m: f"{m.group(0)} ({names[int(m.group(2))]})"
                  if int(m.group(2)) < len(names) else m.group(0), text)


def _solve(args) -> int:
    import numpy as np

    from dqpose import handeye
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
            e = type(e)(_named(str(e), names))      # the solver's base_flange[3] -> its image
        code = failure("handeye solve", args, e)
        if names and from_server and re.search(r"pairs\[|samples? \d", str(e)):
            # the server's pairs[k] and samples k, by image
            print("dqpose handeye solve: views: " + ", ".join(
                f"pairs[{k}] = {n}" for k, n in enumerate(names)), file=sys.stderr)
        return code
    skipped = [(os.path.basename(views.images[i]), found[i]) for i in range(len(found))
               if not found[i].ok]
    truth = read_truth(args.dir, views.setup)
    text = report(cal, views, names, skipped, truth)
    sys.stdout.write(text)
    out = {k: getattr(args, k) or os.path.join(args.dir, default) for k, default in
           (("report", "handeye_report.txt"), ("plot", "handeye.png"),
            ("output", "handeye.json"))}
    try:
        with open(out["report"], "w", encoding="utf-8") as f:
            f.write(text)
        with open(out["output"], "w", encoding="utf-8") as f:
            json.dump(result_json(cal, names), f, indent=1)
        try:
            from dqpose.cli.plots import plot_calibration
            plot_calibration(out["plot"], cal, names,
                             title=f"dqpose handeye solve {args.dir} ({views.setup})",
                             truth=truth)
            print(f"plot: {out['plot']}", file=sys.stderr)
        except ModuleNotFoundError as e:
            from dqpose.errors import missing
            print(f"no plot: {missing(e)}", file=sys.stderr)
    except OSError as e:
        return fail("handeye solve", str(e))
    print(f"report: {out['report']}, result: {out['output']}", file=sys.stderr)
    return 0


def read_truth(folder: str, setup: str):
    """``(x, z)`` of a simulated capture (its truth.json), when it is one of this setup."""
    from dqpose import dq
    path = os.path.join(folder, "truth.json")
    if not os.path.isfile(path):
        return None
    with open(path, encoding="utf-8") as f:
        doc = json.load(f)
    if doc.get("setup") != setup:
        return None
    return tuple(dq.from_pose([doc[k]["orientation"][c] for c in "wxyz"],
                              [doc[k]["position"][c] for c in "xyz"]) for k in ("x", "z"))


_FRAMES = {"eye_in_hand": ("T_flange_camera", "T_base_target"),
           "eye_to_hand": ("T_base_camera", "T_flange_target")}


def _pose_lines(label: str, pose, cov) -> list[str]:
    import numpy as np

    from dqpose.drivers.rotvec import rotvec_from_quat
    from dqpose import dq
    q, t = dq.to_pose(pose)
    q = -q if q[0] < 0 else q
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    rv = np.degrees(rotvec_from_quat(q))
    return [f"{label}",
            f"  position   [{t[0] * 1e3:10.3f} {t[1] * 1e3:10.3f} {t[2] * 1e3:10.3f}] mm    "
            f"1 sigma [{sd[3] * 1e3:.3f} {sd[4] * 1e3:.3f} {sd[5] * 1e3:.3f}] mm",
            f"  rotation   [{rv[0]:10.4f} {rv[1]:10.4f} {rv[2]:10.4f}] deg (rotation vector)  "
            f"1 sigma [{np.degrees(sd[0]):.4f} {np.degrees(sd[1]):.4f} "
            f"{np.degrees(sd[2]):.4f}] deg",
            f"  quaternion [{q[0]:.8f} {q[1]:.8f} {q[2]:.8f} {q[3]:.8f}] (w, x, y, z)"]


def report(cal, views, names: list, skipped: list, truth=None) -> str:
    """The text report of a solve: how the data was read, X and Z with their standard
    deviations, the residual of each view, the views left out and why, the warnings, and the
    error against the truth of a simulated capture."""
    import numpy as np

    from dqpose import dq, lie
    fx, fz = _FRAMES[cal.setup]
    rejected = {r.index: r.reason for r in cal.rejected}
    out = [f"{len(rejected)} left out by the robust solve"] if rejected else []
    out += [f"{len(skipped)} not detected"] if skipped else []
    lines = [f"hand-eye calibration, {cal.setup}: {len(names) - len(rejected)} views used of "
             f"{len(views.images)} images" + (f" ({'; '.join(out)})" if out else "")
             + f"; poses: {views.poses_file}"]
    lines += [f"note: {n}" for n in views.notes]
    lines += [f"not detected: {n}: {d}" for n, d in skipped]
    lines += [""] + _pose_lines(f"X = {fx}", cal.x, cal.covariance_x)
    lines += _pose_lines(f"Z = {fz}", cal.z, cal.covariance_z)
    lines.append("(1 sigma per axis of the covariance: rotation first, right perturbation "
                 "T * Exp(xi), in the pose's own frame)")
    res = np.asarray(cal.residuals, dtype=np.float64).reshape(-1, 2)
    loo = cal.leave_one_out if cal.leave_one_out is not None else np.full((len(res), 2), np.nan)
    lines += ["", "per view: its residual, and how far X moves when it is left out",
              f"{'view':>4s}  {'image':20s} {'residual deg':>12s} {'mm':>9s} "
              f"{'X moves deg':>12s} {'mm':>9s}"]
    for k, n in enumerate(names):
        tail = f"  left out: {rejected[k]}" if k in rejected else ""
        lines.append(f"{k:4d}  {n:20s} {math.degrees(res[k, 0]):12.4f} {res[k, 1] * 1e3:9.3f} "
                     f"{math.degrees(loo[k, 0]):12.4f} {loo[k, 1] * 1e3:9.3f}{tail}")
    keep = [k for k in range(len(res)) if k not in rejected]
    if keep:
        rms = np.sqrt(np.mean(res[keep] ** 2, axis=0))
        lines.append(f"RMS over the views used: {math.degrees(rms[0]):.4f} deg, "
                     f"{rms[1] * 1e3:.3f} mm")
    lines.append("")
    if cal.closed_form_x is not None:
        a = cal.agreement
        lines.append(f"closed form (Daniilidis) against the refined X: {math.degrees(a[0]):.4f} "
                     f"deg, {a[1] * 1e3:.3f} mm (NEES {a[2]:.2f})")
    lines.append(f"rotation excitation {math.degrees(cal.excitation):.2f} deg (near 0: rotation "
                 f"axes parallel), condition number {cal.rotation_condition:.3g}; "
                 + ("noise: each view's covariance as given" if cal.noise_model == "given" else
                    "noise estimated from the residuals")
                 + f", {cal.iterations} Gauss-Newton steps")
    if cal.reprojection is not None:
        lines.append(f"corner level: reprojection RMS per view {np.min(cal.reprojection):.3f}.."
                     f"{np.max(cal.reprojection):.3f} px, corner noise {cal.pixel_sigma:.3f} px"
                     + (f", focal lengths x {cal.focal_scale:.6f} +- {cal.focal_sigma:.6f}"
                        if cal.focal_sigma else ""))
    for r, a, d in cal.readings:
        lines.append(f"reading {r}: median residual {math.degrees(a):.4f} deg, {d * 1e3:.3f} mm")
    lines += [""] + ([f"warning: {_named(w, names)}" for w in cal.warnings] or ["no warnings"])
    if truth is not None:
        lines.append("")
        for label, est, cov, true in (("X", cal.x, cal.covariance_x, truth[0]),
                                      ("Z", cal.z, cal.covariance_z, truth[1])):
            xi = lie.se3_log(dq.mul(dq.inv(est), true))
            nees = float(xi @ np.linalg.solve(cov, xi))
            dt = np.linalg.norm(dq.to_pose(est)[1] - dq.to_pose(true)[1])
            lines.append(f"against the simulation's truth: {label} off by "
                         f"{math.degrees(np.linalg.norm(xi[:3])):.4f} deg, {dt * 1e3:.3f} mm "
                         f"(NEES {nees:.2f}; 6 expected, 22.5 the 99.9 % bound)")
    return "\n".join(lines) + "\n"


def result_json(cal, names: list) -> dict:
    """The calibration as JSON: the poses as the proto's Pose, covariances as 36 numbers."""
    import numpy as np

    from dqpose.cli.posefile import pose_json
    return {"setup": cal.setup, "x": pose_json(cal.x), "z": pose_json(cal.z),
            "covariance_x": np.asarray(cal.covariance_x).ravel().tolist(),
            "covariance_z": np.asarray(cal.covariance_z).ravel().tolist(),
            "covariance_convention": "6x6 row-major, rotation first [wx wy wz vx vy vz], right "
                                     "perturbation T * Exp(xi) (GTSAM Pose3)",
            "images": names,
            "residuals": np.asarray(cal.residuals).reshape(-1, 2).tolist(),
            "warnings": list(cal.warnings)}
