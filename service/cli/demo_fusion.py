"""``dqpose demo fusion``: two simulated cameras and a simulated UR watch one moving body; their
measurements are fused live through the Fusion service and each source's error, and the fused
one's, is printed against the ground truth and plotted over time.

The scene: the body is a ChArUco board held by a UR (the UR simulator, driven through the real
``ur_rtde`` by ``drivers.open_arm``), its base the world frame, the board ``body_offset`` from the
flange. The arm moves it slowly (small sinusoids in position and angle). Each step, the arm's
``measure()`` gives ``T_base_tool``; the true tool pose differs from it by the arm's absolute
accuracy, drawn as ``T_true = T_read * Exp(eps)``, ``eps ~ N(0, diag(pose_sigma^2))`` (the
simulator itself is exact; a real arm's kinematic model is not). Two cameras with known
extrinsics render the board at its true pose (with blur and pixel noise) and detect it with
:class:`drivers.camera.CharucoCamera`, covariance from PnP. The three measurements of the
instant go to ``Client.fuse`` with each source's frames (:class:`service.fusion.Source`).
"""
from __future__ import annotations

import argparse
import asyncio
import contextlib
import math
import sys
import threading
from dataclasses import dataclass

import numpy as np

from service import dq, lie

# flange -> board: the board 5 cm out along the tool z axis (its centre near the axis)
_BOARD_OFFSET = ((1.0, 0.0, 0.0, 0.0), (-0.14, -0.10, 0.05))
# the UR's tool at the start, rotation vector (UR convention) and position in the base frame
_HOME = (0.45, -0.10, 0.35, math.pi, 0.0, 0.0)


# The path takes at least this many 0.1 s set-points, so it stays within the arm's default limits.
_MIN_PATH_STEPS = 40


def _wobble(k: int, n: int) -> np.ndarray:
    """Offset of set-point ``k`` of ``n`` from home, rotation-vector pose: a loop starting and
    ending at rest (the phase follows 1 - cos, so speed and acceleration start at zero)."""
    phase = math.pi * (1.0 - math.cos(math.pi * min(k, n) / n))
    return np.array([0.02 * math.sin(phase), 0.01 * math.sin(2 * phase),
                     0.01 * (math.cos(phase) - 1.0), 0.0, 0.05 * math.sin(phase), 0.0])


@dataclass
class Result:
    """Per step: time since the start (s) and the rotation (deg) and translation (mm) errors of
    each source (NaN where a camera rejected its view) and of the fused pose."""
    names: tuple[str, ...]
    t: np.ndarray
    rotation_deg: np.ndarray      # (steps, len(names))
    translation_mm: np.ndarray


def _error(est: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    xi = lie.se3_log(dq.mul(dq.inv(truth), est))
    _, t = dq.to_pose(est)
    _, tt = dq.to_pose(truth)
    return math.degrees(float(np.linalg.norm(xi[:3]))), 1e3 * float(np.linalg.norm(t - tt))


@contextlib.contextmanager
def _server():
    """A Fusion server in this process on a free loopback port (its own event loop thread)."""
    from service.rpc.server import ServerConfig, start
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    running = asyncio.run_coroutine_threadsafe(start(ServerConfig(port=0)), loop).result(30)
    try:
        yield f"127.0.0.1:{running.port}"
    finally:
        asyncio.run_coroutine_threadsafe(running.stop(0), loop).result(30)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10)


def _cameras(T_world_board0: np.ndarray, board, intrinsics):
    """Two extrinsics ``T_world_camera`` looking at the board's start pose from either side."""
    from drivers.sim.camera import look_at
    w, h = board.extent
    centre = np.array([w / 2, h / 2, 0.0])
    out = []
    for side in (-1.0, 1.0):
        eye = centre + np.array([side * 0.18, 0.06, -0.42])   # on the board's -z side
        T_cam_board = look_at(eye, centre, (0.2 * side, -1.0, 0.0))
        out.append(dq.mul(T_world_board0, dq.inv(T_cam_board)))
    return out


def run(steps: int = 60, *, seed: int = 0, arm_sigma=(2e-3, 1e-3), noise: float = 6.0,
        blur: float = 0.8, target: str | None = None, progress: bool = True) -> Result:
    """The demo's loop; returns the errors (see :class:`Result`)."""
    import drivers
    from drivers.camera import CharucoCamera, Intrinsics
    from drivers.rotvec import pose_from_rotvec
    from drivers.sim.camera import BoardRenderer
    from drivers.sim.ursim import URSimProcess
    from service.fusion import Source
    from service.rpc.client import Client

    rng = np.random.default_rng(seed)
    intr = Intrinsics(K=np.array([[400.0, 0, 199.5], [0, 400.0, 149.5], [0, 0, 1]]),
                      size=(400, 300))
    renderer = BoardRenderer(intrinsics=intr, pixels_per_metre=5000.0)
    offset = dq.from_pose(np.array(_BOARD_OFFSET[0]), np.array(_BOARD_OFFSET[1]))
    home = np.array(_HOME)
    T_world_board0 = dq.mul(pose_from_rotvec(home), offset)
    extrinsics = _cameras(T_world_board0, renderer.board, intr)
    cams = [CharucoCamera(intr, renderer.board, name=f"camera{k + 1}") for k in range(2)]
    names = ("ur",) + tuple(c.name for c in cams)
    sources = [Source("ur", body_offset=offset)] + [
        Source(c.name, extrinsic=E) for c, E in zip(cams, extrinsics)]

    rot = np.full((steps, len(names) + 1), np.nan)
    trans = np.full_like(rot, np.nan)
    times = np.zeros(steps)
    with contextlib.ExitStack() as stack:
        sim = stack.enter_context(URSimProcess())
        sim.set_pose(home)
        # 10 Hz servo: one set-point per step, the renders, detections and fusion in between
        # (data then comes at 10 Hz too, so it may stand still longer than the default 0.1 s)
        arm = stack.enter_context(drivers.open_arm(f"ur:{sim.host}", frequency=10.0,
                                                   stale_after=0.5, watchdog_periods=20))
        arm.pose_sigma = tuple(arm_sigma)
        if target is None:
            target = stack.enter_context(_server())
        client = stack.enter_context(Client(target))
        bar = range(steps)
        if progress:
            try:
                from tqdm import tqdm
                bar = tqdm(bar, desc="fusing", unit="step", leave=False, file=sys.stderr)
            except ImportError:
                pass
        t0 = None
        for k in bar:
            goal = home + _wobble(k, max(steps, _MIN_PATH_STEPS))
            arm.servo(pose_from_rotvec(goal))
            m_arm = arm.measure()
            t0 = m_arm.time if t0 is None else t0
            eps = rng.normal(0.0, 1.0, 6) * np.repeat(arm_sigma, 3)
            truth = dq.mul(dq.mul(m_arm.pose, lie.se3_exp(eps)), offset)
            poses, covs, who = [m_arm.pose], [m_arm.covariance], ["ur"]
            world = {"ur": dq.mul(m_arm.pose, offset)}     # each source's own T_world_body
            for cam, E in zip(cams, extrinsics):
                T_cam_board = dq.mul(dq.inv(E), truth)
                d = cam.detect(renderer.render(T_cam_board, blur=blur, noise=noise, rng=rng))
                if d.ok:
                    poses.append(d.pose)
                    covs.append(d.covariance)
                    who.append(cam.name)
                    world[cam.name] = dq.mul(E, d.pose)
            fused = client.fuse(np.array(poses), np.array(covs), names=who, sources=sources,
                                body="board", times=[m_arm.time] * len(who), time=m_arm.time)
            times[k] = m_arm.time - t0
            for j, n in enumerate(names):
                if n in world:
                    rot[k, j], trans[k, j] = _error(world[n], truth)
            rot[k, -1], trans[k, -1] = _error(fused.mean, truth)
    return Result(names + ("fused",), times, rot, trans)


def report(result: Result, out=None) -> None:
    out = out or sys.stdout       # looked up now: the caller may have redirected it
    print(f"{'source':10s} {'views':>5s}  {'rotation error (deg)':>24s}  "
          f"{'translation error (mm)':>24s}", file=out)
    print(f"{'':10s} {'':5s}  {'median':>11s} {'RMS':>12s}  {'median':>11s} {'RMS':>12s}",
          file=out)
    for j, n in enumerate(result.names):
        r, t = result.rotation_deg[:, j], result.translation_mm[:, j]
        ok = ~np.isnan(r)
        if not ok.any():
            print(f"{n:10s} {0:5d}  (no accepted view)", file=out)
            continue
        print(f"{n:10s} {int(ok.sum()):5d}  {np.median(r[ok]):11.4f} "
              f"{math.sqrt(np.mean(r[ok] ** 2)):12.4f}  {np.median(t[ok]):11.3f} "
              f"{math.sqrt(np.mean(t[ok] ** 2)):12.3f}", file=out)


def plot(result: Result, path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, (a, b) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    for j, n in enumerate(result.names):
        style = dict(lw=2.2, color="k") if n == "fused" else dict(lw=1.0, alpha=0.8)
        a.plot(result.t, result.rotation_deg[:, j], label=n, **style)
        b.plot(result.t, result.translation_mm[:, j], label=n, **style)
    a.set_ylabel("rotation error (deg)")
    b.set_ylabel("translation error (mm)")
    b.set_xlabel("time (s)")
    a.set_yscale("log")
    b.set_yscale("log")
    a.legend(loc="upper right", ncol=len(result.names), fontsize="small")
    a.set_title("dqpose demo fusion: each source and the fused pose against the ground truth")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def add_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("fusion mode")
    g.add_argument("--steps", type=int, default=100,
                   help="fusion steps, one UR set-point and two camera frames each (default 100, "
                        "about 10 s)")
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--plot", default="fusion_demo.png", metavar="PATH",
                   help="where to write the PNG plot (default fusion_demo.png; needs matplotlib)")
    g.add_argument("--target", default=None,
                   help="a running dqpose server (host:port); default: start one in process")


def main(args: argparse.Namespace) -> int:
    if args.steps < 1:
        print("dqpose demo fusion: --steps must be at least 1", file=sys.stderr)
        return 2
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        matplotlib = None
    try:
        result = run(args.steps, seed=args.seed, target=args.target,
                     progress=sys.stderr.isatty())
    except ImportError as e:
        print(f"dqpose demo fusion: needs the device extras ({e}); "
              "pip install 'dqpose[devices]'", file=sys.stderr)
        return 1
    except (OSError, RuntimeError) as e:
        print(f"dqpose demo fusion: {e}", file=sys.stderr)
        return 1
    print(f"{args.steps} steps: a simulated UR holding a ChArUco board and two simulated "
          "cameras, fused through the Fusion service; errors against the ground truth:")
    report(result)
    if matplotlib is None:
        print("no plot: matplotlib is not installed (pip install matplotlib)")
    else:
        plot(result, args.plot)
        print(f"plot: {args.plot}")
    return 0
