"""``dqpose handeye capture`` and ``dqpose handeye solve``: hand-eye calibration from the shell.

``capture DIR`` drives a UR (the simulator by default, or ``--arm ur:HOST``) through views of a
ChArUco board chosen to be informative (a spread of rotation axes first, then the solver's
next-best pose among candidate views), grabs an image at each (rendered by the simulated camera,
or from ``--camera``) and saves the folder ``solve`` reads: the images, the flange poses
(``poses.json``), the intrinsics and the board, and for a simulation the truth (``truth.json``).

``solve DIR`` detects the board in each image with :class:`drivers.camera.CharucoCamera`, solves
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

from service.cli.common import client, connection_args, fail, failure, missing_extra

SETUPS = ("eye_in_hand", "eye_to_hand")
CHOICES = ("next-best", "spread", "random")
POSE_FILES = ("poses.json", "poses.csv")
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
CAPTURE_EPILOG = """\
Without --arm the UR simulator is started and a simulated camera renders the board (the truth
is saved as truth.json, and solve then reports its error against it). With --arm ur:HOST (a real
arm) give --camera (a device index, video or folder) and --intrinsics: start with the camera
looking at the board from about the working distance; every move is a straight tool line
(moveL) within the arm's limits, so keep the space around the board clear.
"""

# The simulated cell. Eye-in-hand: a 7x5 board face up on the table, a camera on the flange
# 6 cm off its axis and turned 80 deg about it; eye-to-hand: a camera on a post looking at a
# board held 5 cm out along the tool z axis.
_SIM_X = {"eye_in_hand": ((0.06, -0.02, 0.04), (0.08, -0.12, 1.40)),
          "eye_to_hand": ((0.50, -0.85, 0.55), None)}
_SIM_Z = {"eye_in_hand": ((0.40, 0.10, 0.0), (math.pi, 0.0, 0.0)),
          "eye_to_hand": ((-0.14, -0.10, 0.05), (0.0, 0.0, 0.0))}
#: the simulator's own tool speed limits (drivers/sim/ursim.py), faster than a bench arm's
_SIM_SPEED = dict(max_linear_speed=1.0, max_angular_speed=3.0, max_linear_accel=4.0,
                  max_angular_accel=8.0)
#: Capture sends whole moves, each run by the controller itself, never a servo stream: a pause
#: of the data stream this short is no fault (and a simulator on a busy machine makes them)
STALE_AFTER = 1.0
_CANDIDATES = 200        # candidate views the next one is chosen from
_SPREAD_FIRST = 3        # views chosen for their spread of rotations before the solver chooses


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
                       epilog=CAPTURE_EPILOG)
    c.add_argument("dir", metavar="DIR", help="folder to write (created; must hold no views)")
    c.add_argument("--setup", choices=SETUPS, default="eye_in_hand",
                   help="eye_in_hand (default): camera on the flange; eye_to_hand: camera "
                        "fixed, board on the flange")
    c.add_argument("--views", type=int, default=15, help="views to capture (default 15)")
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
    action = {"capture": _capture, "solve": _solve}[args.action]
    try:
        return action(args)
    except ModuleNotFoundError as e:    # OpenCV, ur_rtde: the [devices] extra
        return missing_extra(f"handeye {args.action}", e)



# ---- solve ------------------------------------------------------------------------------------

def _find(folder: str, names) -> str | None:
    for n in names:
        path = os.path.join(folder, n)
        if os.path.isfile(path):
            return path
    return None


class _Views:
    """The folder's views: image paths, flange poses, how the poses were read."""

    def __init__(self, args):
        from drivers.camera import IMAGE_EXTENSIONS
        from service.cli.posefile import read_robot_poses
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
    from drivers.camera import BoardSpec, CharucoCamera, load_board, load_intrinsics
    intr = args.intrinsics or _find(args.dir, ("intrinsics.json", "intrinsics.yaml",
                                               "intrinsics.yml"))
    if intr is None:
        raise ValueError(f"--intrinsics: required (no intrinsics.json or .yaml in {args.dir!r})")
    board = args.board or _find(args.dir, ("board.json", "board.yaml", "board.yml"))
    return CharucoCamera(load_intrinsics(intr), load_board(board) if board else BoardSpec())


def _detect(camera, images: list) -> list:
    """The detection (or rejection) of each image, with a progress bar on a terminal."""
    from tqdm import tqdm

    from drivers.camera import read_image
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
        from drivers.base import pose_covariance
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

    from service import handeye
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
            from service.cli.plots import plot_calibration
            plot_calibration(out["plot"], cal, names,
                             title=f"dqpose handeye solve {args.dir} ({views.setup})",
                             truth=truth)
            print(f"plot: {out['plot']}", file=sys.stderr)
        except ModuleNotFoundError as e:
            from service.errors import missing
            print(f"no plot: {missing(e)}", file=sys.stderr)
    except OSError as e:
        return fail("handeye solve", str(e))
    print(f"report: {out['report']}, result: {out['output']}", file=sys.stderr)
    return 0


def read_truth(folder: str, setup: str):
    """``(x, z)`` of a simulated capture (its truth.json), when it is one of this setup."""
    from service import dq
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

    from drivers.rotvec import rotvec_from_quat
    from service import dq
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

    from service import dq, lie
    fx, fz = _FRAMES[cal.setup]
    lines = [f"hand-eye calibration, {cal.setup}: {len(names)} views used of "
             f"{len(views.images)} (poses: {views.poses_file})"]
    lines += [f"note: {n}" for n in views.notes]
    lines += [f"not detected: {n}: {d}" for n, d in skipped]
    lines += [""] + _pose_lines(f"X = {fx}", cal.x, cal.covariance_x)
    lines += _pose_lines(f"Z = {fz}", cal.z, cal.covariance_z)
    lines.append("(1 sigma per axis of the covariance: rotation first, right perturbation "
                 "T * Exp(xi), in the pose's own frame)")
    rejected = {r.index: r.reason for r in cal.rejected}
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

    from service.cli.posefile import pose_json
    return {"setup": cal.setup, "x": pose_json(cal.x), "z": pose_json(cal.z),
            "covariance_x": np.asarray(cal.covariance_x).ravel().tolist(),
            "covariance_z": np.asarray(cal.covariance_z).ravel().tolist(),
            "covariance_convention": "6x6 row-major, rotation first [wx wy wz vx vy vz], right "
                                     "perturbation T * Exp(xi) (GTSAM Pose3)",
            "images": names,
            "residuals": np.asarray(cal.residuals).reshape(-1, 2).tolist(),
            "warnings": list(cal.warnings)}


# ---- capture ----------------------------------------------------------------------------------

def _pose(t, rotvec):
    import numpy as np

    from drivers.rotvec import pose_from_rotvec
    return pose_from_rotvec(np.concatenate([t, rotvec]))


def _sim_cell(setup: str, board):
    """The simulated cell's truth ``(x, z)`` and the flange's start pose, from which the camera
    sees the board's centre from 0.45 m."""
    import numpy as np

    from drivers.sim.camera import look_at
    from service import dq, handeye
    w, h = board.extent
    centre = np.array([w / 2, h / 2, 0.0])
    home_view = look_at(centre + [0.0, 0.0, -0.45], centre)
    z = _pose(*_SIM_Z[setup])
    if setup == "eye_in_hand":
        x = _pose(*_SIM_X[setup])
    else:   # the camera on its post looks at where the board is at the start, image up
        eye = np.array(_SIM_X[setup][0])
        x = dq.inv(look_at(eye, eye + [0.0, 0.45, -0.1], (0.0, 0.0, 1.0)))   # T_base_camera
    return x, z, handeye.flange_for(home_view, x, z, setup)


class _Capture:
    """The views taken so far and the choice of the next (spread first, then next-best)."""

    def __init__(self, setup: str, start_flange, start_detection, board, rng,
                 choose: str = "next-best"):
        import numpy as np

        from drivers.sim.camera import random_view
        from service import dq
        self.setup = setup
        start_view = start_detection.pose
        self.flanges, self.views = [start_flange], [start_view]
        self.covariances = [start_detection.covariance]
        # A first guess: the camera at the flange (eye-in-hand) or the board at the flange
        # (eye-to-hand); the solver's answer replaces it once there is one.
        ident = dq.from_pose(np.array([1.0, 0, 0, 0]), np.zeros(3))
        if setup == "eye_in_hand":
            self.x = ident
            self.z = dq.mul(dq.mul(start_flange, self.x), start_view)
        else:
            self.z = ident
            self.x = dq.mul(dq.mul(start_flange, self.z), dq.inv(start_view))
        d = float(np.linalg.norm(dq.to_pose(start_view)[1]))
        self.candidates = [random_view(rng, board, distance=(0.8 * d, 1.25 * d),
                                       max_tilt_deg=40.0, max_roll_deg=60.0)
                           for _ in range(_CANDIDATES)]
        self.calibration = None
        self.choose = choose
        self.taken = 1           # views taken, the start's included (detected or not)

    def add(self, flange, detection) -> None:
        import numpy as np

        from service import handeye
        self.flanges.append(flange)
        self.views.append(detection.pose)
        self.covariances.append(detection.covariance)
        if len(self.views) > _SPREAD_FIRST:
            try:
                self.calibration = handeye.calibrate(
                    np.array(self.flanges), np.array(self.views), self.setup,
                    camera_covariance=np.array(self.covariances))
                self.x, self.z = self.calibration.x, self.calibration.z
            except ValueError:      # not yet determined: keep the guess and the spread rule
                self.calibration = None

    def drop(self, k: int) -> None:
        self.candidates.pop(k)

    def rule(self) -> str:
        """How the next view is chosen: the solver's next-best pose once it has an answer, the
        view whose rotation is farthest from every view taken before (``choose`` "spread":
        always), or the candidates as they come (``choose`` "random")."""
        if self.choose == "random":
            return "random"
        if self.choose == "next-best" and self.calibration is not None:
            return "next-best pose"
        return "rotation spread"

    def order(self, flanges) -> list:
        """Candidate indices, best first, by :meth:`rule`."""
        import numpy as np
        rule = self.rule()
        if rule == "random":
            return list(range(len(flanges)))
        if rule == "next-best pose":
            from service import handeye
            return list(handeye.next_best_pose(self.calibration, np.array(self.flanges),
                                               np.array(self.views), np.array(flanges)))
        from drivers.base import pose_delta
        gaps = [min(pose_delta(c, v)[1] for v in self.views) for c in self.candidates]
        return list(np.argsort(gaps)[::-1])


def _capture(args) -> int:
    import contextlib

    import numpy as np

    from service import handeye

    if args.views < 4:
        return fail("handeye capture", f"--views: at least 4, got {args.views}")
    if args.arm and not args.arm.startswith("ur:"):
        return fail("handeye capture", f"--arm: ur:HOST (a UR arm), got {args.arm!r}")
    if args.arm and not (args.camera and args.intrinsics):
        return fail("handeye capture", "--arm: a real arm needs --camera and --intrinsics (the "
                                       "simulated camera sees only the simulated arm)")
    if os.path.isdir(args.dir) and (_find(args.dir, POSE_FILES) or glob.glob(
            os.path.join(args.dir, "view_*"))):
        return fail("handeye capture", f"DIR: {args.dir!r} already holds a capture")
    import cv2

    import drivers
    from drivers.base import Limits
    from drivers.camera import BoardSpec, CharucoCamera, load_board, load_intrinsics
    from drivers.rotvec import rotvec_from_pose
    from drivers.sim.camera import DEFAULT_INTRINSICS, BoardRenderer
    from drivers.sim.ursim import URSimProcess
    rng = np.random.default_rng(args.seed)
    sim = not args.arm
    speed = args.speed or (0.8 if sim else 0.25)
    settle = args.settle if args.settle is not None else (0.0 if sim else 0.3)
    try:
        board = load_board(args.board) if args.board else BoardSpec()
        intr = load_intrinsics(args.intrinsics) if args.intrinsics else DEFAULT_INTRINSICS
        detector = CharucoCamera(intr, board)
        with contextlib.ExitStack() as stack:
            if sim:
                x_true, z_true, home = _sim_cell(args.setup, board)
                ursim = stack.enter_context(URSimProcess())
                ursim.set_pose(rotvec_from_pose(home))
                arm = stack.enter_context(drivers.open_arm(f"ur:{ursim.host}",
                                                           limits=Limits(**_SIM_SPEED),
                                                           stale_after=STALE_AFTER))
                renderer = BoardRenderer(board, intr)

                def grab(flange):
                    return renderer.render(handeye.view_at(flange, x_true, z_true, args.setup),
                                           blur=args.blur, noise=args.noise, rng=rng)
            else:
                from drivers.camera import open_frames
                arm = stack.enter_context(drivers.open_arm(args.arm, stale_after=STALE_AFTER))
                frames = open_frames(args.camera)
                stack.callback(frames.close)

                def grab(flange):
                    img = frames.read(5.0)
                    if img is None:
                        raise OSError(f"--camera: {args.camera} gave no image")
                    return img
            os.makedirs(args.dir, exist_ok=True)
            images, flanges = [], []

            def shoot(flange):
                img = grab(flange)
                name = f"view_{len(images):03d}.png"
                if not cv2.imwrite(os.path.join(args.dir, name), img):
                    raise OSError(f"DIR: cannot write {os.path.join(args.dir, name)}")
                images.append(name)
                flanges.append(flange)
                return detector.detect(img)

            _, start = arm.tool_pose()
            first = shoot(start)
            if not first.ok:
                os.remove(os.path.join(args.dir, images.pop()))
                raise ValueError(f"the camera does not see the board at the start pose "
                                 f"({first}); start with the board in view")
            state = _Capture(args.setup, start, first, board, rng, args.choose)
            print(f"view 0: the start pose ({'simulated UR' if sim else args.arm})",
                  file=sys.stderr)
            try:
                stop = _views_loop(args, arm, state, shoot, speed, settle)
            finally:    # what was taken is kept, also when the arm or camera failed midway
                if images:
                    _save(args, images, flanges, intr, board,
                          (x_true, z_true) if sim else None)
    except (ValueError, OSError, RuntimeError) as e:
        return fail("handeye capture", str(e))
    if stop:
        return fail("handeye capture", f"{stop}; {len(images)} views saved in {args.dir}")
    print(f"{len(images)} views in {args.dir}; solve with: dqpose handeye solve {args.dir}")
    return 0


#: a capture stops when the board was not detected in this many views in a row
MAX_MISSES = 5


def _views_loop(args, arm, state, shoot, speed: float, settle: float) -> str | None:
    """Moves to the chosen views and shoots until ``args.views`` are taken; why it stopped
    early, else None."""
    from service import dq, handeye
    misses = 0
    while state.taken < args.views:
        targets = [handeye.flange_for(v, state.x, state.z, args.setup) for v in state.candidates]
        for k in state.order(targets):
            try:
                arm.limits.check_workspace("pose", dq.to_pose(targets[k])[1], "")
                break
            except ValueError:
                continue
        else:
            return "no candidate view left within the arm's workspace"
        how = state.rule()
        state.drop(k)
        _move(arm, targets[k], speed)
        if settle:
            import time
            time.sleep(settle)
        _, reached = arm.tool_pose()
        d = shoot(reached)
        print(f"view {state.taken}: {how}" + ("" if d.ok else f" (not detected: {d})"),
              file=sys.stderr)
        state.taken += 1
        if d.ok:
            state.add(reached, d)
            misses = 0
        else:
            misses += 1
            if misses >= MAX_MISSES:
                return (f"the board was not detected in {misses} views in a row (the camera, "
                        f"the board or the lighting?)")
    return None


def _save(args, images, flanges, intr, board, truth) -> None:
    """The folder ``solve`` reads: ``poses.json``, the intrinsics, the board and, for a
    simulation, the truth ``(x, z)``."""
    import numpy as np

    from service.cli.posefile import pose_json, robot_poses_json
    with open(os.path.join(args.dir, "poses.json"), "w", encoding="utf-8") as f:
        f.write(robot_poses_json(images, np.array(flanges), args.setup))
    with open(os.path.join(args.dir, "intrinsics.json"), "w", encoding="utf-8") as f:
        json.dump({"K": intr.K.tolist(), "dist": intr.dist.tolist(),
                   "image_size": list(intr.size)}, f, indent=1)
    with open(os.path.join(args.dir, "board.json"), "w", encoding="utf-8") as f:
        json.dump({"kind": board.kind, "squares": list(board.squares),
                   "square_length": board.square_length, "marker_length": board.marker_length,
                   "dictionary_name": board.dictionary_name}, f, indent=1)
    if truth is not None:
        with open(os.path.join(args.dir, "truth.json"), "w", encoding="utf-8") as f:
            json.dump({"setup": args.setup, "x": pose_json(truth[0]), "z": pose_json(truth[1])},
                      f, indent=1)


def _move(arm, target, speed: float) -> None:
    """A straight tool move to ``target`` at up to ``speed`` m/s, slowed so that the tool's turn
    stays within the arm's angular speed limit (UR turns the tool in step with the line)."""
    from drivers.base import pose_delta
    L = arm.limits
    _, here = arm.tool_pose()
    dist, angle = pose_delta(here, target)
    v = min(speed, L.max_linear_speed)
    if angle > 1e-9 and dist > 1e-9:
        v = min(v, 0.95 * L.max_angular_speed * dist / angle)
    arm.move(target, v, min(1.0, L.max_linear_accel))
