"""``dqpose handeye capture DIR``: drives a UR (the simulator by default, or ``--arm ur:HOST``)
through views of a ChArUco board chosen to be informative (a spread of rotation axes first, then
the solver's next-best pose among candidate views), grabs an image at each (rendered by the
simulated camera, or from ``--camera``) and saves the folder ``dqpose handeye solve`` reads: the
images, the flange poses (``poses.json``), the intrinsics and the board, and for a simulation the
truth (``truth.json``). ``--record FILE.mcap`` records each solve of the views taken so far (a
``dqpose.v1.HandEye/Calibrate`` call: the views, the solved X and Z with their covariances, the
per-view residuals), which Foxglove draws (docs/recording.md)."""
from __future__ import annotations

import argparse
import functools
import math
import os
import sys

from dqpose.cli.common import INTERRUPTED, fail
from dqpose.cli.handeye_folder import CAPTURE_FILES, POSE_FILES, Previous, find, save, view_files
from dqpose.cli.handeye_views import CHOICES, ViewPlan

CAPTURE_EPILOG = """\
Without --arm the UR simulator is started and a simulated camera renders the board (the truth
is saved as truth.json, and solve then reports its error against it). With --arm ur:HOST (a real
arm) give --camera (a device index, video or folder) and --intrinsics: start with the camera
looking at the board from about the working distance, 15-30 degrees off head-on (a head-on view
of a flat board is where its pose is least certain); every move is a straight tool line
(moveL) within the arm's limits, so keep the space around the board clear.

An interrupted capture (Ctrl-C: the arm is stopped, the views taken are saved) is continued with
--resume, up to --views in all, or replaced with --force.
"""

# The simulated cell. Eye-in-hand: a 7x5 board face up on the table, a camera on the flange
# 6 cm off its axis and turned 80 deg about it; eye-to-hand: a camera on a post looking at a
# board held 5 cm out along the tool z axis. (Keyed by the setups' names: this module's top level
# imports nothing heavy, dqpose.handeye included.)
_SIM_X = {"eye_in_hand": ((0.06, -0.02, 0.04), (0.08, -0.12, 1.40)),
          "eye_to_hand": ((0.50, -0.85, 0.55), None)}
_SIM_Z = {"eye_in_hand": ((0.40, 0.10, 0.0), (math.pi, 0.0, 0.0)),
          "eye_to_hand": ((-0.14, -0.10, 0.05), (0.0, 0.0, 0.0))}
#: the simulator's own tool speed limits (drivers/sim/ur/), faster than a bench arm's
_SIM_SPEED = dict(max_linear_velocity=1.0, max_angular_velocity=3.0, max_linear_acceleration=4.0,
                  max_angular_acceleration=8.0)
#: Capture sends whole moves, each run by the controller itself, never a servo stream: a pause
#: of the data stream this short is no fault (and a simulator on a busy machine makes them)
STALE_AFTER = 1.0


def _pose(t, rotvec):
    import numpy as np

    from dqpose.drivers.rotvec import pose_from_rotvec
    return pose_from_rotvec(np.concatenate([t, rotvec]))


#: How far the simulated camera's start view is from head-on to the board. Head-on, the rendered
#: board's detected pose was off along the view by 0.26-0.38 mm with or without noise (the
#: corners pushed outwards by 0.07 px), a NEES of 23.7 on average against its own covariance over
#: 20 renders, and the solver left that view, view 0, out of every capture; 20 deg off, 5.4 (6
#: expected), as for the candidate views (tilted up to 40 deg).
_START_TILT_DEG = 20.0


def _sim_cell(setup: str, board):
    """The simulated cell's truth ``(x, z)`` and the flange's start pose, from which the camera
    sees the board's centre from 0.45 m, :data:`_START_TILT_DEG` off its normal."""
    import numpy as np

    from dqpose import dq, handeye
    from dqpose.drivers.sim.camera import look_at
    from dqpose.handeye.setups import EYE_IN_HAND
    w, h = board.extent
    centre = np.array([w / 2, h / 2, 0.0])
    tilt = math.radians(_START_TILT_DEG)
    home_view = look_at(centre + 0.45 * np.array([0.0, math.sin(tilt), -math.cos(tilt)]),
                        centre)
    z = _pose(*_SIM_Z[setup])
    if setup == EYE_IN_HAND:
        x = _pose(*_SIM_X[setup])
    else:   # the camera on its post looks at where the board is at the start, image up
        eye = np.array(_SIM_X[setup][0])
        x = dq.inv(look_at(eye, eye + [0.0, 0.45, -0.1], (0.0, 0.0, 1.0)))   # T_base_camera
    return x, z, handeye.flange_for(home_view, x, z, setup)



def add_parser(sub) -> None:
    """The ``capture`` action and its options."""
    from dqpose.handeye import SETUPS  # NumPy and the C core: only for this command's help
    c = sub.add_parser("capture", help="drive an arm through informative views and save them",
                       description="Drive a UR through informative views of the board "
                                   "(the simulator, or --arm) and save images and robot poses "
                                   "into DIR for `dqpose handeye solve`.",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       epilog=CAPTURE_EPILOG)
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
    c.add_argument("--record", metavar="FILE.mcap",
                   help="record each solve of the views into FILE.mcap (the [record] extra): "
                        "the views, X and Z with their ellipsoids, the residuals per view")


def _prepare(args):
    """DIR made ready: a capture already there is refused, continued (``--resume``: returns
    :class:`Previous`) or removed (``--force``); None for a new capture."""
    held = os.path.isdir(args.dir) and (find(args.dir, POSE_FILES) or view_files(args.dir))
    if not held:
        if args.resume:
            print(f"nothing to resume in {args.dir}: a new capture", file=sys.stderr)
        return None
    if args.force:
        removed = view_files(args.dir) + [p for p in (os.path.join(args.dir, n)
                                                     for n in CAPTURE_FILES)
                                         if os.path.isfile(p)]
        for path in removed:
            os.remove(path)
        print(f"--force: removed the previous capture's {len(removed)} files from {args.dir}",
              file=sys.stderr)
        return None
    if not args.resume:
        n = len(view_files(args.dir))
        raise ValueError(f"DIR: {args.dir!r} already holds a capture ({n} views): --resume "
                         f"continues it up to --views, --force starts over (removes it)")
    previous = Previous(args.dir)
    if args.setup and previous.setup and args.setup != previous.setup:
        raise ValueError(f"--setup: {args.setup}, but the capture in {args.dir!r} is "
                         f"{previous.setup}")
    return previous


def capture(args) -> int:
    refused = _refused(args)
    if refused:
        return fail("handeye capture", refused)
    try:
        previous = _prepare(args)
    except ValueError as e:
        return fail("handeye capture", str(e))
    recorder = None
    if args.record:
        from dqpose.cli.demo_record import finish, open_file_recorder
        recorder, code = open_file_recorder("handeye capture", args.record, None)
        if recorder is None:
            return code
    try:
        return _capture(args, previous, recorder)
    finally:
        if recorder is not None:
            print(finish(recorder, args.record), file=sys.stderr)


def _capture(args, previous, recorder) -> int:
    import contextlib

    import numpy as np

    from dqpose.handeye.setups import EYE_IN_HAND
    args.setup = args.setup or (previous.setup if previous else None) or EYE_IN_HAND
    if previous and len(previous.images) >= args.views:
        print(f"{len(previous.images)} views in {args.dir} already (--views {args.views}); "
              f"solve with: dqpose handeye solve {args.dir}")
        return 0
    import cv2

    from dqpose.drivers.camera import (
        BoardSpec,
        CharucoCamera,
        load_board,
        load_intrinsics,
        read_image,
    )
    from dqpose.drivers.sim.camera import DEFAULT_INTRINSICS
    # a resumed capture draws its own noise and candidate views, not the first run's again
    rng = np.random.default_rng(args.seed + (len(previous.images) if previous else 0))
    sim = not args.arm
    speed = args.speed or (0.8 if sim else 0.25)
    settle = args.settle if args.settle is not None else (0.0 if sim else 0.3)
    images = list(previous.images) if previous else []
    flanges = list(previous.flanges) if previous else []
    try:
        board_file = args.board or (previous.board if previous else None)
        intr_file = args.intrinsics or (previous.intrinsics if previous else None)
        board = load_board(board_file) if board_file else BoardSpec()
        intr = load_intrinsics(intr_file) if intr_file else DEFAULT_INTRINSICS
        detector = CharucoCamera(intr, board)
        with contextlib.ExitStack() as stack:
            arm, grab, truth = _open_cell(args, stack, board, intr, flanges, rng)
            os.makedirs(args.dir, exist_ok=True)

            def shoot(flange):
                img = grab(flange)
                name = f"view_{len(images):03d}.png"
                if not cv2.imwrite(os.path.join(args.dir, name), img):
                    raise OSError(f"DIR: cannot write {os.path.join(args.dir, name)}")
                images.append(name)
                flanges.append(flange)
                return detector.detect(img)

            try:
                if previous:
                    state = _resumed(args, previous, detector, read_image, board, rng)
                    print(f"resuming: {len(images)} views in {args.dir}", file=sys.stderr)
                else:
                    state = _first_view(args, arm, shoot, images, flanges, board, rng)
                stop = _views_loop(args, arm, state, shoot, speed, settle,
                                   None if recorder is None else _solves_recorded(recorder))
            except KeyboardInterrupt:
                _stop_at_once(arm)
                raise
            finally:    # what was taken is kept, also when the arm or camera failed midway
                if images:
                    save(args, images, flanges, intr, board, truth)
    except KeyboardInterrupt:       # the arm was stopped and closed on the way out
        print(f"dqpose handeye capture: interrupted; {len(images)} views saved in {args.dir}: "
              f"`dqpose handeye capture {args.dir} --resume` continues it (to --views "
              f"{args.views}), --force starts over", file=sys.stderr)
        return INTERRUPTED
    except (ValueError, OSError, RuntimeError) as e:
        return fail("handeye capture", str(e))
    if stop:
        return fail("handeye capture", f"{stop}; {len(images)} views saved in {args.dir}")
    print(f"{len(images)} views in {args.dir}; solve with: dqpose handeye solve {args.dir}")
    return 0


def _refused(args) -> str | None:
    """Why the options cannot make a capture, or None."""
    if args.views < 4:
        return f"--views: at least 4, got {args.views}"
    if args.arm and not args.arm.startswith("ur:"):
        return f"--arm: ur:HOST (a UR arm), got {args.arm!r}"
    if args.arm and not (args.camera and (args.intrinsics or args.resume)):
        return ("--arm: a real arm needs --camera and --intrinsics (the simulated camera sees "
                "only the simulated arm)")
    return None


def _open_cell(args, stack, board, intr, flanges, rng):
    """The arm and the camera, closed with ``stack``: ``(arm, grab(flange) -> image, truth)``.
    Without ``--arm`` the UR simulator (at the last view's flange pose when resumed, else at
    the start) and a camera rendering the board from the simulated cell, whose ``(x, z)`` is
    the truth; with it the arm and ``--camera``, and no truth."""
    from dqpose import drivers, handeye
    if args.arm:
        from dqpose.drivers.camera import open_frames
        arm = stack.enter_context(drivers.open_arm(args.arm, stale_after=STALE_AFTER))
        frames = open_frames(args.camera)
        stack.callback(frames.close)

        def grab(flange):
            img = frames.read(5.0)
            if img is None:
                raise OSError(f"--camera: {args.camera} gave no image")
            return img
        return arm, grab, None
    from dqpose.drivers.base import Limits
    from dqpose.drivers.rotvec import rotvec_from_pose
    from dqpose.drivers.sim.camera import BoardRenderer
    from dqpose.drivers.sim.ur import URSimProcess
    x_true, z_true, home = _sim_cell(args.setup, board)
    ursim = URSimProcess()
    stack.push(functools.partial(_end_simulator, ursim))
    # a capture resumed goes on from where the arm stood at its last view
    ursim.set_pose(rotvec_from_pose(flanges[-1] if flanges else home))
    arm = stack.enter_context(drivers.open_arm(f"ur:{ursim.host}", limits=Limits(**_SIM_SPEED),
                                               stale_after=STALE_AFTER))
    renderer = BoardRenderer(board, intr)

    def grab(flange):
        return renderer.render(handeye.view_at(flange, x_true, z_true, args.setup),
                               blur=args.blur, noise=args.noise, rng=rng)
    return arm, grab, (x_true, z_true)


def _first_view(args, arm, shoot, images, flanges, board, rng) -> ViewPlan:
    """The view at the arm's start pose, which must show the board (else it is not kept), and
    the choice of views from it."""
    _, start = arm.tool_pose()
    first = shoot(start)
    if not first.ok:
        os.remove(os.path.join(args.dir, images.pop()))
        flanges.pop()
        raise ValueError(f"the camera does not see the board at the start "
                         f"pose ({first}); start with the board in view")
    state = ViewPlan(args.setup, start, first, board, rng, args.choose)
    print(f"view 0: the start pose ({args.arm or 'simulated UR'})", file=sys.stderr)
    return state


def _stop_at_once(arm) -> None:
    """A Ctrl-C: the arm stopped before anything else (the views taken are saved after it), and
    closed without ur_rtde's disconnect (2 s with its destructors; the connections close as this
    process ends, which it does next)."""
    from dqpose.drivers.base import ArmError
    try:
        arm.stop()
    except ArmError:
        pass            # closed or faulted: its close still sends the stop
    arm.disconnect_on_close = False


def _end_simulator(sim, exc_type, exc, tb) -> None:
    """The simulator's end as the capture ends (an exit callback): at once, unless the capture was
    interrupted. Then the arm's connections are left open for this process's end to close (as
    :func:`_stop_at_once` says), and a controller that closed them first would have ur_rtde's
    threads print their complaints after the capture's last words; the simulator ends by itself
    once this process has (``--exit-with-parent``)."""
    if exc_type is not KeyboardInterrupt:
        sim.close()


def _resumed(args, previous: Previous, detector, read_image, board, rng) -> ViewPlan:
    """The choice of views where the capture in DIR left it: its views detected again (the
    first, the start, must show the board) and the solver's answer from them."""
    found = [detector.detect(read_image(os.path.join(args.dir, im))) for im in previous.images]
    if not found[0].ok:
        raise ValueError(f"--resume: the board is not detected in {previous.images[0]}, the "
                         f"capture's first view; --force starts over")
    state = ViewPlan(args.setup, previous.flanges[0], found[0], board, rng, args.choose)
    for flange, d in zip(previous.flanges[1:], found[1:]):
        if d.ok:
            state.add(flange, d)
    state.taken = len(previous.images)
    return state


#: a capture stops when the board was not detected in this many views in a row
MAX_MISSES = 5


def _solves_recorded(recorder):
    """``record(state)``: the solver's answer from the views so far, when it has one, recorded
    as the ``HandEye/Calibrate`` call that gives it (the same arguments, the same answer)."""
    import numpy as np

    from dqpose.rpc._proto.dqpose.v1 import handeye_pb2 as hpb
    from dqpose.rpc.handeye_convert import calibrate_msg, calibration_to_msg

    def record(state) -> None:
        if state.calibration is None:
            return
        call = recorder.call("dqpose.v1.HandEye/Calibrate", hpb.CalibrateRequest,
                             hpb.CalibrateResponse)
        call.request(calibrate_msg(np.array(state.flanges), np.array(state.views),
                                        state.setup,
                                        camera_covariance=np.array(state.covariances)))
        call.answer(calibration_to_msg(state.calibration))
        call.end("OK")
    return record


def _views_loop(args, arm, state, shoot, speed: float, settle: float,
                record=None) -> str | None:
    """Moves to the chosen views and shoots until ``args.views`` are taken (``record(state)``
    after each view detected); why it stopped early, else None."""
    from dqpose import dq, handeye
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
            if record is not None:
                record(state)
        else:
            misses += 1
            if misses >= MAX_MISSES:
                return (f"the board was not detected in {misses} views in a row (the camera, "
                        f"the board or the lighting?)")
    return None



def _move(arm, target, speed: float) -> None:
    """A straight tool move to ``target`` at up to ``speed`` m/s, slowed so that the tool's turn
    stays within the arm's angular speed limit (UR turns the tool in step with the line)."""
    from dqpose.drivers.base import pose_delta
    L = arm.limits
    _, here = arm.tool_pose()
    dist, angle = pose_delta(here, target)
    v = min(speed, L.max_linear_velocity)
    if angle > 1e-9 and dist > 1e-9:
        v = min(v, 0.95 * L.max_angular_velocity * dist / angle)
    arm.move(target, v, min(1.0, L.max_linear_acceleration))
