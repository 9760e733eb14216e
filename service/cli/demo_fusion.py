"""``dqpose demo fusion``: two simulated cameras and a simulated UR watch one moving body; their
measurements are streamed as they come into the Fusion service's ``StreamFuse``, and each
source's error, and the fused one's, is printed against the ground truth as the answers arrive and
plotted over time.

The scene: the body is a ChArUco board held by a UR (the UR simulator, driven through the real
``ur_rtde`` by ``drivers.open_arm``), its base the world frame, the board ``body_offset`` from the
flange. A thread servos the arm at the controller's rate along a slow loop (small sinusoids in
position and angle); the simulator's tool pose is the ground truth. Every 20 ms the arm is read:
its reading is the true pose with the arm's absolute accuracy drawn as noise,
``Z = T_true * Exp(-eps)``, ``eps ~ N(0, diag(pose_sigma^2))`` (the simulator itself is exact; a
real arm's kinematic model is not), stamped with the time it was read. Each of two cameras with
known extrinsics captures at 10 Hz (their frames half a period apart): it renders the board at its
true pose of that instant (with blur and pixel noise) and detects it with
:class:`drivers.camera.CharucoCamera`, covariance from PnP; the detection reaches the stream 40 ms
later, stamped then, as a camera's frame does. The server is told each camera's latency only as a
prior, 30 ± 20 ms, and estimates it online (:class:`service.fusion.Source` ``latency_sigma``);
the UR's stamps are taken as exact. The server answers at 10 Hz of the measurements' time with
the fused pose at that instant. The peers at the same instant: each source alone as its user
would have it then (ScLERP of its two newest measurements delivered by then, latency known; the
bench's single-source rows do the same). The truth there is interpolated between the arm's reads.
"""
from __future__ import annotations

import argparse
import bisect
import contextlib
import math
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np

from service import dq, lie

# flange -> board: the board 5 cm out along the tool z axis (its centre near the axis)
_BOARD_OFFSET = ((1.0, 0.0, 0.0, 0.0), (-0.14, -0.10, 0.05))
# the UR's tool at the start, rotation vector (UR convention) and position in the base frame
_HOME = (0.45, -0.10, 0.35, math.pi, 0.0, 0.0)

# The path lasts at least this many 0.1 s steps, so it stays within the arm's default limits.
_MIN_PATH_STEPS = 40
ARM_RATE = 50.0            # arm reads per second
READS_PER_STEP = 5         # arm reads per 0.1 s step, one frame of each camera
CAMERA_LATENCY = 0.040     # capture to stamp (the simulated truth)
LATENCY_PRIOR = (0.030, 0.020)   # what the server is told of it (a data sheet): estimated online
OUTPUT_RATE = 10.0         # fused answers per second of the measurements' time


def _wobble(k: int, n: int) -> np.ndarray:
    """Offset of set-point ``k`` of ``n`` from home, rotation-vector pose: a loop starting and
    ending at rest (the phase follows 1 - cos, so speed and acceleration start at zero)."""
    phase = math.pi * (1.0 - math.cos(math.pi * min(k, n) / n))
    return np.array([0.02 * math.sin(phase), 0.01 * math.sin(2 * phase),
                     0.01 * (math.cos(phase) - 1.0), 0.0, 0.05 * math.sin(phase), 0.0])


@dataclass
class Series:
    """Errors against the ground truth over time: seconds since the start, rotation (deg) and
    translation (mm)."""
    t: np.ndarray
    rotation_deg: np.ndarray
    translation_mm: np.ndarray


@dataclass
class Result:
    """``series``: the errors at the fused answers' instants (:class:`Series`) of each source
    alone (ScLERP of what it had delivered by then, its latency known) and of the fused pose,
    by name (the sources, then ``"fused"``); ``accuracy``: each source's measurements against
    the truth when they were taken, ``(n, 2)`` degrees and mm; camera views the detector
    rejected; each camera's latency as the server estimated it last, ``(value, sigma)``
    seconds."""
    names: tuple[str, ...]
    series: dict
    accuracy: dict
    rejected: dict
    latencies: dict


def _error(est: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    xi = lie.se3_log(dq.mul(dq.inv(truth), est))
    _, t = dq.to_pose(est)
    _, tt = dq.to_pose(truth)
    return math.degrees(float(np.linalg.norm(xi[:3]))), 1e3 * float(np.linalg.norm(t - tt))


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


class _Track:
    """Poses over time (taken, and stamped when they reached the stream), appended by the
    measuring thread and read by the answering one."""

    def __init__(self):
        self.poses: list[np.ndarray] = []
        self.taken: list[float] = []
        self.stamps: list[float] = []

    def add(self, taken: float, pose: np.ndarray, stamp: float | None = None) -> None:
        self.poses.append(pose)        # stamps last: a reader never sees one without its pose
        self.taken.append(taken)
        self.stamps.append(taken if stamp is None else stamp)

    def at(self, t: float, known_by: float | None = None) -> np.ndarray | None:
        """The pose at ``t`` by ScLERP between the two taken times around it, or along the
        newest two beyond them, among the poses stamped by ``known_by`` (None: all); None with
        fewer than two. The truth: the path moves a few cm/s, so between reads 20 ms apart
        this is exact to well below a micrometre. A source alone: what a user of it does."""
        n = len(self.stamps) if known_by is None else bisect.bisect_right(self.stamps, known_by)
        if n < 2:
            return None
        j = min(max(bisect.bisect_left(self.taken, t, 0, n), 1), n - 1)
        t0, t1 = self.taken[j - 1], self.taken[j]
        return dq.sclerp(self.poses[j - 1], self.poses[j], (t - t0) / (t1 - t0))


def _servo_loop(arm, home: np.ndarray, n: int, stop: threading.Event, failed: list) -> None:
    """The arm's set-points at its rate (``servo`` waits out each period) until ``stop``: the
    loop of :func:`_wobble`, then holding its end."""
    from drivers.rotvec import pose_from_rotvec
    k = 0
    try:
        while not stop.is_set():
            arm.servo(pose_from_rotvec(home + _wobble(k, n)))
            k += 1
    except Exception as e:      # raised to the caller by run()
        failed.append(e)


def run(steps: int = 60, *, seed: int = 0, arm_sigma=(2e-3, 1e-3), noise: float = 6.0,
        blur: float = 0.8, target: str | None = None, out=None) -> Result:
    """The demo: ``steps`` of 0.1 s (five arm reads and one frame of each camera each); prints
    a line per fused answer to ``out`` when given; returns the errors (see :class:`Result`)."""
    import drivers
    from drivers.camera import CharucoCamera, Intrinsics
    from drivers.rotvec import pose_from_rotvec
    from drivers.sim.camera import BoardRenderer
    from drivers.sim.ursim import URSimProcess
    from service.fusion import Source
    from service.cli.common import local_server
    from service.rpc.client import Batch, Client

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
        Source(c.name, extrinsic=E, latency=LATENCY_PRIOR[0], latency_sigma=LATENCY_PRIOR[1])
        for c, E in zip(cams, extrinsics)]
    # camera c captures at read c * READS_PER_STEP // 2 of each step: half a period apart
    capture_at = {c * READS_PER_STEP // len(cams): (cam, E) for c, (cam, E) in
                  enumerate(zip(cams, extrinsics))}

    truth = _Track()
    alone = {n: _Track() for n in names}       # each source's measurements, world frame
    accuracy: dict[str, list] = {n: [] for n in names}   # against the truth when taken
    errors: dict[str, list] = {n: [] for n in names + ("fused",)}   # at the fusion instants
    rejected = {c.name: 0 for c in cams}
    latencies: dict = {}
    start: list[float] = []

    def measurements():
        """The batches in the order they reach the stream: each arm read at once, a camera's
        detection CAMERA_LATENCY after its capture (stamped then)."""
        in_flight = []           # (stamp, name, T_cam_board, covariance) not yet arrived
        period = 1.0 / ARM_RATE
        due = time.monotonic()
        for _ in range(steps * READS_PER_STEP):
            now = time.monotonic()
            if due > now:
                time.sleep(due - now)
            else:           # late (a slow render): go on from now rather than read in a burst
                due = now
            due += period
            m = arm.measure()
            if not start:
                start.append(m.time)
            T_true = dq.mul(m.pose, offset)
            truth.add(m.time, T_true)
            eps = rng.normal(0.0, 1.0, 6) * np.repeat(arm_sigma, 3)
            reading = dq.mul(m.pose, lie.se3_exp(-eps))
            alone["ur"].add(m.time, dq.mul(reading, offset))
            accuracy["ur"].append(_error(alone["ur"].poses[-1], T_true))
            k = (len(truth.taken) - 1) % READS_PER_STEP
            if k in capture_at:
                cam, E = capture_at[k]
                d = cam.detect(renderer.render(dq.mul(dq.inv(E), T_true), blur=blur,
                                               noise=noise, rng=rng))
                if d.ok:
                    in_flight.append((m.time + CAMERA_LATENCY, cam.name, d.pose, d.covariance,
                                      m.time, dq.mul(E, d.pose)))
                    accuracy[cam.name].append(_error(in_flight[-1][-1], T_true))
                else:
                    rejected[cam.name] += 1
            arrived = [f for f in in_flight if f[0] <= m.time]
            in_flight = [f for f in in_flight if f[0] > m.time]
            for stamp, name, _, _, taken, world in arrived:
                alone[name].add(taken, world, stamp)
            batch = [(m.time, "ur", reading, m.covariance)] + [f[:4] for f in arrived]
            yield Batch(np.array([b[2] for b in batch]), np.array([b[3] for b in batch]),
                        names=[b[1] for b in batch], bodies=["board"] * len(batch),
                        times=np.array([b[0] for b in batch]))

    def answer(t: float, fused: np.ndarray) -> str:
        """Record the errors at fusion instant ``t`` of each source alone (with what it has
        delivered by then, latency known) and of the fused pose; the printed line."""
        T_true = truth.at(t)
        cells = [f"{t - start[0]:7.2f}"]
        for n in names + ("fused",):
            pose = fused if n == "fused" else alone[n].at(t, known_by=t)
            if pose is None:
                cells.append(f"{'—':>7s} {'—':>6s}")
                continue
            errors[n].append((t, *_error(pose, T_true)))
            cells.append(f"{errors[n][-1][1]:7.3f} {errors[n][-1][2]:6.2f}")
        cells.append("  ".join(f"{1e3 * latencies[c.name][0]:5.1f}" for c in cams
                               if c.name in latencies))
        return "  ".join(cells)

    with contextlib.ExitStack() as stack:
        sim = stack.enter_context(URSimProcess())
        sim.set_pose(home)
        # the controller's own rate (500 Hz): the pose read is then at most 2 ms old, which
        # at the path's few cm/s keeps the truth, stamped when read, within a tenth of a mm
        arm = stack.enter_context(drivers.open_arm(f"ur:{sim.host}", stale_after=0.5,
                                                   watchdog_periods=100))
        arm.pose_sigma = tuple(arm_sigma)
        if target is None:
            target = stack.enter_context(local_server())
        client = stack.enter_context(Client(target))
        for cam, E in zip(cams, extrinsics):    # the first detection is slow (set-up)
            cam.detect(renderer.render(dq.mul(dq.inv(E), T_world_board0), blur=blur,
                                       noise=noise, rng=rng))
        stop, failed = threading.Event(), []
        servo = threading.Thread(target=_servo_loop, name="demo servo", daemon=True, args=(
            arm, home, round(max(steps, _MIN_PATH_STEPS) * 0.1 / arm.period), stop, failed))
        servo.start()
        stack.callback(servo.join, 10)
        stack.callback(stop.set)
        if out is not None:
            print(f"{'t (s)':>7s}  " + "  ".join(f"{n + ' deg / mm':>14s}" for n in
                                                 names + ("fused",))
                  + "  latency " + " / ".join(c.name for c in cams) + " (ms)", file=out)
        for a in client.stream_fuse(measurements(), sources=sources, output_rate=OUTPUT_RATE):
            if failed:
                break
            if a.fused is None:     # the stream goes on past a measurement it could not use
                print(f"server: {a.error}", file=sys.stderr)
                continue
            for lat in a.fused.latencies:
                latencies[lat.name] = (lat.value, lat.sigma)
            text = answer(a.time, a.fused.mean)
            if out is not None:
                print(text, file=out, flush=True)
        if failed:
            raise failed[0]

    series = {}
    for n, rows in errors.items():
        r = np.array(rows, dtype=np.float64).reshape(-1, 3)
        series[n] = Series(r[:, 0] - (start[0] if start else 0.0), r[:, 1], r[:, 2])
    return Result(names + ("fused",), series, {n: np.array(e).reshape(-1, 2)
                                               for n, e in accuracy.items()},
                  rejected, latencies)


def report(result: Result, out=None) -> None:
    out = out or sys.stdout       # looked up now: the caller may have redirected it
    print(f"{'source':10s} {'count':>5s}  {'rotation error (deg)':>24s}  "
          f"{'translation error (mm)':>24s}", file=out)
    print(f"{'':10s} {'':5s}  {'median':>11s} {'RMS':>12s}  {'median':>11s} {'RMS':>12s}",
          file=out)
    for n in result.names:
        s = result.series[n]
        if not len(s.t):
            print(f"{n:10s} {0:5d}  (none)", file=out)
            continue
        r, t = s.rotation_deg, s.translation_mm
        print(f"{n:10s} {len(s.t):5d}  {np.median(r):11.4f} {math.sqrt(np.mean(r ** 2)):12.4f}  "
              f"{np.median(t):11.3f} {math.sqrt(np.mean(t ** 2)):12.3f}", file=out)
    print("each measurement against the truth when it was taken (RMS): " + ", ".join(
        f"{n} {math.sqrt(np.mean(a[:, 0] ** 2)):.4f} deg / "
        f"{math.sqrt(np.mean(a[:, 1] ** 2)):.3f} mm" for n, a in result.accuracy.items()
        if len(a)), file=out)
    for name, k in result.rejected.items():
        if k:
            print(f"({name}: {k} views not detected)", file=out)
    for name, (value, sigma) in result.latencies.items():
        print(f"latency of {name} as the server estimated it last: {1e3 * value:.1f} ± "
              f"{1e3 * sigma:.1f} ms (simulated {1e3 * CAMERA_LATENCY:.0f} ms, told "
              f"{1e3 * LATENCY_PRIOR[0]:.0f} ± {1e3 * LATENCY_PRIOR[1]:.0f} ms)", file=out)


def plot(result: Result, path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, (a, b) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    for n in result.names:
        s = result.series[n]
        style = dict(lw=2.2, color="k") if n == "fused" else dict(lw=1.0, alpha=0.8)
        a.plot(s.t, s.rotation_deg, label=n, **style)
        b.plot(s.t, s.translation_mm, label=n, **style)
    a.set_ylabel("rotation error (deg)")
    b.set_ylabel("translation error (mm)")
    b.set_xlabel("time (s)")
    a.set_yscale("log")
    b.set_yscale("log")
    a.legend(loc="upper right", ncol=len(result.names), fontsize="small")
    a.set_title("dqpose demo fusion: each source and the fused pose (StreamFuse) against the "
                "ground truth", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def add_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("fusion mode")
    g.add_argument("--steps", type=int, default=100,
                   help="steps of 0.1 s: five UR reads and one frame of each camera each "
                        "(default 100, about 10 s)")
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
    print(f"{args.steps} steps of 0.1 s: a simulated UR holding a ChArUco board (read at "
          f"{ARM_RATE:g} Hz) and two simulated cameras (10 Hz, {1e3 * CAMERA_LATENCY:.0f} ms "
          "latency, estimated online), streamed into StreamFuse. At each fused answer's "
          "instant, the error against the ground truth of each source alone (ScLERP of what it "
          "had delivered by then, its latency known) and of the fused pose:", flush=True)
    result = run(args.steps, seed=args.seed, target=args.target, out=sys.stdout)
    print()
    report(result)
    if matplotlib is None:
        from service.errors import install_hint
        print(f"no plot: {install_hint('plot')}")
    else:
        plot(result, args.plot)
        print(f"plot: {args.plot}")
    return 0
