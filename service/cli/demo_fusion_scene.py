"""The scene of ``dqpose demo fusion`` (:mod:`dqpose.cli.demo_fusion` describes it): the arm's
loop and its clock, the threads that read the arm and render and detect the cameras' frames, the
order the stream carries them in, and the controller cycles a busy machine left without a
set-point."""
from __future__ import annotations

import bisect
import math
import queue
import threading
import time

import numpy as np

from dqpose import dq, lie

# flange -> board: the board 5 cm out along the tool z axis (its centre near the axis)
BOARD_OFFSET = ((1.0, 0.0, 0.0, 0.0), (-0.14, -0.10, 0.05))
# the UR's tool at the start, rotation vector (UR convention) and position in the base frame
HOME = (0.45, -0.10, 0.35, math.pi, 0.0, 0.0)

# The path lasts at least this many 0.1 s steps, so it stays within the arm's default limits.
MIN_PATH_STEPS = 40
# The tool's top speed (m/s) along the loop: a shorter loop is a smaller one. A machine busy
# enough to starve the simulator leaves the arm's pose as old as the stall, and the control loop
# stops the arm once that pose is max_tracking (5 mm) behind its set-points: at 14 mm/s (the
# full loop over 20 s) runs beside two CPU hogs ended TRACKING (5.007 mm) or on a pose 0.44 and
# 0.72 s old; at 3.5 mm/s a stall of 1.4 s is needed.
GENTLE_SPEED = 0.0035
STEP = 0.1                 # s: one frame of each camera
ARM_RATE = 50.0            # arm reads per second
CAMERA_LATENCY = 0.040     # capture to stamp (the simulated truth)


def wobble(k, n: int, size: float = 1.0) -> np.ndarray:
    """Offsets of set-points ``k`` of ``n`` from home, rotation-vector poses ``(..., 6)``: a loop
    starting and ending at rest (the phase follows 1 - cos, so speed and acceleration start at
    zero), ``size`` times the full one (2 cm along x, 1 cm along y and z, 0.05 rad)."""
    k = np.minimum(np.asarray(k, dtype=np.float64), n)
    phase = math.pi * (1.0 - np.cos(math.pi * k / n))
    z = np.zeros_like(phase)
    return size * np.stack([0.02 * np.sin(phase), 0.01 * np.sin(2 * phase),
                            0.01 * (np.cos(phase) - 1.0), z, 0.05 * np.sin(phase), z], axis=-1)


def loop_path(n: int, period: float, hold: int = 0):
    """The loop's set-points ``(times, T_base_flange)`` over ``n`` periods, as large as
    :data:`GENTLE_SPEED` allows (at most the full loop), then held at its end ``hold`` periods,
    and the board's poses along it."""
    from dqpose.drivers.rotvec import pose_from_rotvec
    k = np.arange(n + hold + 1)
    full = wobble(k, n)
    peak = float(np.max(np.linalg.norm(np.diff(full[:, :3], axis=0), axis=1))) / period
    flange = pose_from_rotvec(np.array(HOME) + min(1.0, GENTLE_SPEED / peak) * full)
    board = dq.mul(flange, dq.from_pose(np.array(BOARD_OFFSET[0]), np.array(BOARD_OFFSET[1])))
    return k * period, flange, board


def pose_error(est: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    xi = lie.se3_log(dq.mul(dq.inv(truth), est))
    _, t = dq.to_pose(est)
    _, tt = dq.to_pose(truth)
    return math.degrees(float(np.linalg.norm(xi[:3]))), 1e3 * float(np.linalg.norm(t - tt))


def nees_of(est: np.ndarray, covariance: np.ndarray, truth: np.ndarray) -> float:
    """``xi^T P^-1 xi`` with ``truth = est * Exp(xi)`` (the covariance's convention)."""
    xi = lie.se3_log(dq.mul(dq.inv(est), truth))
    return float(xi @ np.linalg.solve(covariance, xi))


def cameras(T_world_board0: np.ndarray, board, intrinsics):
    """Two extrinsics ``T_world_camera`` looking at the board's start pose from either side."""
    from dqpose.drivers.sim.camera import look_at
    w, h = board.extent
    centre = np.array([w / 2, h / 2, 0.0])
    out = []
    for side in (-1.0, 1.0):
        eye = centre + np.array([side * 0.18, 0.06, -0.42])   # on the board's -z side
        T_cam_board = look_at(eye, centre, (0.2 * side, -1.0, 0.0))
        out.append(dq.mul(T_world_board0, dq.inv(T_cam_board)))
    return out


class Track:
    """Poses over time (taken, and stamped when they reached the stream), appended by one thread
    and read by others. ``hold``: what a user of the source has at a time is its newest pose
    (:meth:`at`)."""

    def __init__(self, hold: bool = False):
        self.hold = hold
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
        fewer than two. With ``hold`` and ``known_by``, the newest pose stamped by then. The
        truth: the path moves a few mm/s, so between reads 20 ms apart this is exact to well
        below a micrometre. A source alone: what a user of it does (a camera's two newest
        frames are a step apart; two reads of a busy arm may be microseconds apart, and
        extrapolated along them a millimetre of noise became hundreds of metres)."""
        n = len(self.stamps) if known_by is None else bisect.bisect_right(self.stamps, known_by)
        if self.hold and known_by is not None:
            return self.poses[n - 1] if n else None
        if n < 2:
            return None
        j = min(max(bisect.bisect_left(self.taken, t, 0, n), 1), n - 1)
        t0, t1 = self.taken[j - 1], self.taken[j]
        return dq.sclerp(self.poses[j - 1], self.poses[j], (t - t0) / (t1 - t0))


class LoopClock:
    """The time of each read of the arm on the loop's own clock: the simulated arm follows each
    set-point exactly, so the pose read is one of the loop's set-points (to ~1e-15 m), and its
    time is that set-point's. A busy machine delays the set-points (the loop took 23.5 s of wall
    time for 20 s of plan on a quiet machine, 3 times as long beside two CPU hogs, with pauses of
    0.1-0.7 s) and the reads' arrival (the arm stamps its data when it arrives): against the wall
    clock the board stops and jumps, a motion no real arm makes and no smooth motion model
    follows. On this clock its motion is the loop, whatever the load; a simulation's time, as a
    ROS simulation's ``/clock``. ``start``: the wall time of the loop's first set-point (the
    first read's arrival less its time on the loop), so stamps read as Unix times."""

    #: m: the largest distance between a read and its set-point (reads matched 6e-16 m)
    MATCH = 1e-9

    def __init__(self, times: np.ndarray, flange: np.ndarray):
        self.times = np.asarray(times, dtype=np.float64)
        self.positions = dq.to_pose(np.asarray(flange, dtype=np.float64))[1]
        self.next = 0               # no read is of a set-point before the previous read's
        self.start: float | None = None

    def __call__(self, plan_time: float, stamp: float, actual: np.ndarray) -> float:
        """The loop-clock stamp of a read of ``actual`` (``T_base_flange``) that arrived at wall
        time ``stamp`` while the set-point of ``plan_time`` was sent."""
        last = int(np.searchsorted(self.times, plan_time + 1e-9, side="right"))
        gap = np.linalg.norm(self.positions[self.next:last] - dq.to_pose(actual)[1], axis=1)
        if not gap.size or gap.min() > self.MATCH:
            raise RuntimeError(
                f"the simulated arm's pose read at {plan_time:.3f} s of the loop is none of its "
                f"set-points since the previous read (nearest "
                f"{gap.min() if gap.size else math.inf:.3g} m): the demo's clock needs an arm "
                f"that follows each set-point exactly")
        self.next += int(np.argmin(gap))
        if self.start is None:
            self.start = stamp - float(self.times[self.next])
        return self.start + float(self.times[self.next])


class Scene:
    """What measures: :meth:`read` (the arm's pose, as the control loop read it after a
    set-point: the truth and the UR's readings, onto ``reads``), :meth:`capture` (a thread: each
    camera frame at its instant, from the truth, into ``frames`` in capture order), and the
    order of the stream (:meth:`batches`)."""

    def __init__(self, offset, cams, extrinsics, renderer, rng, arm_sigma, duration, noise,
                 blur, clock: LoopClock | None = None):
        from dqpose.drivers.base import pose_covariance
        self.offset, self.rng = offset, rng
        self.covariance = pose_covariance(*arm_sigma)
        self.cams, self.extrinsics, self.renderer = cams, extrinsics, renderer
        self.arm_sigma, self.duration, self.noise, self.blur = arm_sigma, duration, noise, blur
        self.clock = clock                 # None: the reads' own (wall) stamps
        self.truth = Track()
        # each source alone as its user has it at an instant: the arm's newest read (stamped
        # exactly, 20 ms apart: extrapolating reads adds to their noise), a camera's two newest
        # frames (40-140 ms old by then) extrapolated to it
        self.alone = {"ur": Track(hold=True), **{c.name: Track() for c in cams}}
        self.accuracy: dict[str, list] = {n: [] for n in self.alone}
        self.rejected = {c.name: 0 for c in cams}
        self.reads: queue.Queue = queue.Queue()
        self.frames: list = []             # (stamp, name, T_cam_board, covariance, taken, world)
        self.rendered = 0                  # captures done (detected or not)
        self.start: float | None = None    # the first read's time
        self.read_gap = 0.0
        self.behind = 0.0
        self.cond = threading.Condition()
        self.stop = threading.Event()
        self.aborted = False
        self.failed: list[BaseException] = []

    def capture_time(self, j: int) -> float:
        """Capture ``j``: camera ``j % 2`` at ``start + j * STEP / 2``."""
        return self.start + j * STEP / len(self.cams)

    def read(self, fb) -> None:
        """An executor's feedback record (:class:`dqpose.drivers.executor.Feedback`, on its thread):
        the arm's pose as the control loop read it, in the arm's own process where it runs
        there, so a busy interpreter here delays the record, not the read; the run's last
        record ends the reads, and one that is not ``FINISHED`` fails the demo."""
        from dqpose.drivers.executor import Result
        if self.stop.is_set():
            return
        try:
            if fb.result != Result.OK:
                if fb.result != Result.FINISHED:
                    raise RuntimeError(f"the arm's loop ended {fb.result.name}: {fb.message}")
                self.end()
                return
            if fb.actual is None:
                return
            stamp = fb.stamp if self.clock is None else self.clock(fb.time, fb.stamp, fb.actual)
            with self.cond:
                if self.start is None:
                    self.start = stamp
                elif stamp <= self.truth.taken[-1]:
                    return          # the set-point of the read before
                else:
                    self.read_gap = max(self.read_gap, stamp - self.truth.taken[-1])
                T_true = dq.mul(fb.actual, self.offset)
                self.truth.add(stamp, T_true)
                self.cond.notify_all()
            eps = self.rng.normal(0.0, 1.0, 6) * np.repeat(self.arm_sigma, 3)
            reading = dq.mul(fb.actual, lie.se3_exp(-eps))
            self.accuracy["ur"].append((*pose_error(dq.mul(reading, self.offset), T_true),
                                        nees_of(reading, self.covariance, fb.actual)))
            self.reads.put((stamp, reading, self.covariance))
            if stamp - self.start >= self.duration:
                self.end()
        except BaseException as e:      # raised to the caller by batches()
            with self.cond:
                self.failed.append(e)
            self.end()

    def abort(self) -> None:
        """Stop rendering (a Ctrl-C, an error): the captures still due are not waited for."""
        with self.cond:
            self.aborted = True
            self.cond.notify_all()
        self.end()

    def end(self) -> None:
        """No more reads: the stream ends after the last."""
        with self.cond:
            if self.stop.is_set():
                return
            self.stop.set()
            self.cond.notify_all()
        self.reads.put(None)

    def capture(self, rng) -> None:
        """Renders and detects each capture once the truth around its instant is read."""
        try:
            j = 0
            while True:
                with self.cond:
                    # the truth around the instant: two reads, one of them at or after it
                    # (j bound as a default: wait_for calls the predicate within this iteration)
                    self.cond.wait_for(lambda j=j: self.failed or self.stop.is_set() or (
                        len(self.truth.taken) > 1
                        and self.truth.taken[-1] >= self.capture_time(j)))
                    if self.failed or self.aborted or len(self.truth.taken) < 2 or \
                            self.capture_time(j) > self.truth.taken[-1]:
                        return
                    t = self.capture_time(j)
                    T_true = self.truth.at(t)
                cam, E = self.cams[j % len(self.cams)], self.extrinsics[j % len(self.cams)]
                d = cam.detect(self.renderer.render(dq.mul(dq.inv(E), T_true), blur=self.blur,
                                                    noise=self.noise, rng=rng))
                with self.cond:
                    if d.ok:
                        world = dq.mul(E, d.pose)
                        self.frames.append((t + CAMERA_LATENCY, cam.name, d.pose, d.covariance,
                                            t, world))
                        self.accuracy[cam.name].append((
                            *pose_error(world, T_true),
                            nees_of(d.pose, d.covariance, dq.mul(dq.inv(E), T_true))))
                    else:
                        self.rejected[cam.name] += 1
                    self.rendered = j = j + 1
                    self.cond.notify_all()
        except BaseException as e:
            with self.cond:
                self.failed.append(e)
                self.cond.notify_all()

    def batches(self):
        """The measurements in the order of their stamps, as the devices would send them,
        however long the rendering takes: each arm read once every capture that could be
        stamped by then is rendered, after the camera frames stamped since the read before it;
        one measurement a batch."""
        from dqpose.rpc.client import Batch
        sent = 0                            # frames sent
        while True:
            item = self.reads.get()
            if item is None or self.failed:
                return
            stamp, reading, covariance = item
            with self.cond:
                # captures taken by stamp - latency are due with this read
                due = int(math.floor((stamp - CAMERA_LATENCY - self.start)
                                     / (STEP / len(self.cams)) + 1e-9)) + 1
                self.cond.wait_for(lambda due=due: (
                    self.failed or self.aborted or self.rendered >= due
                    or (self.stop.is_set()
                        and self.capture_time(self.rendered) > self.truth.taken[-1])))
                if self.failed or self.aborted:
                    return
                arrived = [f for f in self.frames[sent:] if f[0] <= stamp]
                sent += len(arrived)
            self.behind = max(self.behind, time.time() - stamp)
            for f in arrived:
                self.alone[f[1]].add(f[4], f[5], f[0])
            self.alone["ur"].add(stamp, dq.mul(reading, self.offset))
            # a message each, as each device sends it: a batch of frames spanning more than a
            # window (reads a busy machine took 0.2-0.5 s apart) left the ticks before its
            # window unanswered (197 answers of 202)
            for stamp_, name, pose, cov in [f[:4] for f in arrived] + [
                    (stamp, "ur", reading, covariance)]:
                yield Batch(pose[None], cov[None], names=[name], bodies=["board"],
                            times=np.array([stamp_]))


def missed_cycles(sim, mark: int, period: float) -> int:
    """Controller cycles without a set-point since the hook log's entry ``mark``."""
    from dqpose.cli.demo_trajectory import missed_cycles, servo_arrivals
    return missed_cycles(np.diff(servo_arrivals(sim, mark)), period)
