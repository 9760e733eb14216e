"""AgileX PiPER arm over CAN (any ``python-can`` bus), commanded in tool space; the frames are
:mod:`dqpose.drivers.piper_can` (whose names this module re-exports).

By name: ``drivers.open_arm("piper:socketcan:can0")`` (``piper:<python-can interface>:<channel>``;
``piper:udp_multicast:239.74.163.2`` reaches ``dqpose sim piper`` in another process).

``PiperArm`` runs a receive thread that assembles feedback poses, decodes the arm status, counts
and skips malformed frames, and watches the command stream: if ``servo`` set-points stop arriving
the arm is told to hold where it is. While the arm reports a stop or fault, ``servo`` and
``move`` refuse to command it. Poses cross the interface as dual quaternions ``T_base_tool``.
"""
from __future__ import annotations

import math
import threading
import time
from collections import Counter
from typing import Optional, Sequence

import can
import numpy as np

from dqpose.drivers import piper_can
from dqpose.drivers.base import (
    Arm,
    ArmError,
    ArmState,
    Limits,
    Pacer,
    ServoStream,
    pose_delta,
    servo_step,
    tool_line,
    unit_pose,
)
from dqpose.drivers.piper_can import *  # noqa: F401,F403 (re-exported)
from dqpose.drivers.piper_can import (
    ARM_STATUS_FEEDBACK,
    CTRL_MODE_CAN,
    END_POSE_CTRL,
    END_POSE_FEEDBACK,
    FEEDBACK_BLOCK,
    KNOWN_FEEDBACK,
    MOVE_P,
    EndPoseAssembler,
    FrameError,
    MotionMode,
    StatusReport,
    decode_arm_status,
    describe_status,
    encode_end_pose,
    encode_motion_mode,
    pose_to_units,
    units_to_pose,
)
from dqpose.profile import Trapezoid

__all__ = [*piper_can.__all__, "PiperArm"]


class PiperArm(Arm):
    """A PiPER on ``bus`` (``can.Bus`` of any interface), in end-pose (MOVE P) mode.

    Safety, as every :class:`~drivers.base.Arm`: ``servo`` set-points are checked against
    ``limits`` (:meth:`Limits.check_servo`, one ``period`` apart) and one that breaks a limit is
    not sent: the arm is told to hold its measured pose and :class:`LimitError` is raised;
    ``move`` checks its arguments with :meth:`Limits.check_move`. If no servo set-point arrives
    for ``watchdog`` seconds the arm is told to hold its measured pose. The arm counts as
    connected while both end-pose feedback and arm status (0x2A1) are younger than
    ``stale_after``: when not given, the larger of its default (0.35 s) and
    :data:`STALE_PERIODS` times the feedback's period as measured (the median of the last
    intervals of each kind, the slower kind's; at most :data:`STALE_MAX`, 1 s), the measure
    started again after feedback that
    went stale resumes (a gap is no period). ``watchdog``, ``stale_after`` and the other keys of
    :data:`dqpose.drivers.spec.ARM_KEYS` are ``options``. ``own_bus`` shuts the bus down on
    ``close()`` (``open_arm`` does, and waits up to ``connect_timeout`` for the arm's first
    feedback).

    Arm status: ``status()`` sets ``emergency_stop`` for arm_status 0x01 and ``protective_stop``
    for the states where the arm has stopped itself and an operator must clear the cause
    (``PROTECTIVE_STATES``: joint communication error, brake not released, collision, overspeed
    in teach drag, joint status abnormal, other error, over-temperature; also any err_code bit and
    any arm_status code the protocol does not define). Every non-normal report -- including the
    arm refusing a target (no solution, singularity, target angle over limit) and hand teaching --
    puts its text in ``error``, and while one stands ``servo`` and ``move`` raise ``ArmError``
    with that text instead of sending anything; a running ``move`` ends with that error at its
    next tick. ``stop`` still sends the measured pose as the target: a target the arm can reach,
    which should end a refusal state (our reading of the protocol, not tried on hardware; the
    simulator keeps an injected state until it is cleared). When a report first goes bad the
    servo stream is ended, and
    the next command re-sends the 0x151 motion mode, so nothing resumes on its own once the
    cause is cleared.
    """

    name = "piper"
    #: PiPER pose repeatability +-0.1 mm (AgileX; 3 sigma): 3.3e-5 m, and 3.3e-4 rad, the same
    #: displacement at a 0.1 m tool lever. See :attr:`Arm.pose_sigma`.
    pose_sigma = (3.3e-4, 3.3e-5)

    #: the PiPER reaches about 0.63 m
    DEFAULT_LIMITS = Limits(max_angular_velocity=math.radians(90),
                            workspace_min=(-0.7, -0.7, -0.2), workspace_max=(0.7, 0.7, 0.8))

    @classmethod
    def process_problem(cls, channel: str) -> Optional[str]:
        if channel.partition(":")[0] == "virtual":
            return "python-can's virtual bus does not reach across processes"
        return None

    @classmethod
    def open(cls, channel: str, **kwargs) -> "PiperArm":
        """``drivers.open_arm("piper:<interface>:<channel>")``: a python-can bus of that
        interface and channel (``virtual:can0``, ``socketcan:can0``,
        ``udp_multicast:239.74.163.2``), owned and shut down by the arm."""
        interface, sep, chan = channel.partition(":")
        if not sep or not interface or not chan:
            raise ValueError(f"channel: expected '<python-can interface>:<channel>' such as "
                             f"'virtual:can0' or 'udp_multicast:239.74.163.2', got {channel!r}")
        try:
            bus = can.Bus(interface=interface, channel=chan)
        except (can.CanError, OSError, ValueError, ImportError) as e:
            raise ArmError(f"channel: cannot open python-can {interface} channel {chan!r}: "
                           f"{e}") from None
        try:
            arm = cls(bus, own_bus=True, **kwargs)
        except BaseException:
            bus.shutdown()
            raise
        try:
            arm.wait_for_feedback(arm.connect_timeout)
        except BaseException as e:
            arm.close()
            if isinstance(e, ArmError):
                raise ArmError(f"{e} on python-can {interface} channel {chan!r}; is the arm "
                               "powered and on this bus?") from None
            raise
        return arm

    def __init__(self, bus: can.BusABC, *, period: float = 0.005, limits: Optional[Limits] = None,
                 position_tolerance: float = 5e-4, angle_tolerance: float = math.radians(0.2),
                 own_bus: bool = False, **options):
        for name, v in (("period", period), ("position_tolerance", position_tolerance),
                        ("angle_tolerance", angle_tolerance)):
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name}: must be a positive number, got {v!r}")
        if limits is not None and not isinstance(limits, Limits):
            raise ValueError(f"limits: expected a drivers.base.Limits, got {type(limits).__name__}")
        # stale_after not given: at least STALE_PERIODS feedback periods (the stale_after
        # property); given: as given
        self._stale_given = options.get("stale_after") is not None
        self._periods = {"status": _Period(), "pose": _Period()}
        self._set_options("piper", options)
        self.bus = bus
        self._own_bus = bool(own_bus)
        self.period = float(period)
        self._pacer = Pacer(self.period)
        self.limits = limits or self.DEFAULT_LIMITS
        self.position_tolerance = float(position_tolerance)
        self.angle_tolerance = float(angle_tolerance)

        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        # Serialises everything that decides a set-point (servo, move ticks, holds), so a
        # watchdog or stop() hold can never be overtaken by a set-point decided before it.
        self._cmd_lock = threading.RLock()
        self._assembler = EndPoseAssembler(END_POSE_FEEDBACK)
        self._pose: Optional[np.ndarray] = None
        self._pose_time = 0.0        # bus timestamp of the last complete feedback
        self._pose_mono = -math.inf  # our monotonic clock at that moment
        self._prev: tuple = (None, 0.0)  # the feedback before it (pose, stamp): velocity()
        self._first_mono = time.monotonic()
        self.frames = 0
        self.poses = 0
        self.malformed: Counter = Counter()
        self.watchdog_stops = 0
        self._report: Optional[StatusReport] = None
        self._report_mono = -math.inf
        self._fault = (False, False, "")   # describe_status of the last report
        self.reports = 0
        self._mode_sent: Optional[MotionMode] = None
        self._stream = ServoStream()
        self._held: Optional[np.ndarray] = None     # the pose the last hold commanded
        self._abort = threading.Event()
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._receive, name="piper-rx", daemon=True)
        self._thread.start()

    @property
    def stale_after(self) -> float:
        """Feedback older than this is a fault (s): as given, else the larger of the default and
        :data:`STALE_PERIODS` times the slower feedback's measured period, at most
        :data:`STALE_MAX`."""
        if self._stale_given:
            return self._stale
        measured = min(STALE_MAX, STALE_PERIODS * max(p.period for p in self._periods.values()))
        return max(self._stale, measured)

    @stale_after.setter
    def stale_after(self, value: float) -> None:      # _set_options: given or the default
        self._stale = float(value)

    # ---- receive side -------------------------------------------------------------------------
    def _receive(self) -> None:
        while not self._closed.is_set():
            try:
                msg = self.bus.recv(timeout=min(0.02, self.watchdog / 2))
            except (can.CanError, OSError, ValueError):
                if self._closed.is_set():
                    return
                time.sleep(0.01)
                continue
            if msg is not None:
                self._handle(msg)
            self._check_watchdog()

    def _handle(self, msg: can.Message) -> None:
        i = msg.arbitration_id
        if i not in FEEDBACK_BLOCK:
            return  # other devices and the arm's other reports are not ours to judge
        with self._lock:
            self.frames += 1
        if i not in KNOWN_FEEDBACK:
            self._count("unknown_id")
            return
        if i == ARM_STATUS_FEEDBACK:
            self._handle_status(msg)
            return
        if i not in END_POSE_FEEDBACK:
            return
        try:
            ep = self._assembler.feed(msg)
        except FrameError as e:
            self._count(e.reason)
            return
        if ep is None:
            return
        pose = units_to_pose(ep)
        stamp = msg.timestamp if msg.timestamp else time.time()
        now = time.monotonic()
        with self._lock:
            self._periods["pose"].arrived(now - self._pose_mono, self.stale_after)
            self._prev = (self._pose, self._pose_time)
            self._pose, self._pose_time, self._pose_mono = pose, stamp, now
            self.poses += 1

    def _handle_status(self, msg: can.Message) -> None:
        try:
            report = decode_arm_status(msg)
        except FrameError as e:
            self._count(e.reason)
            return
        fault = describe_status(report)
        now = time.monotonic()
        with self._lock:
            self._periods["status"].arrived(now - self._report_mono, self.stale_after)
            prev, was_bad = self._report, bool(self._fault[2])
            self._report, self._report_mono, self._fault = report, now, fault
            self.reports += 1
        went_bad = bool(fault[2]) and not was_bad
        left_can = (prev is not None and prev.ctrl_mode == CTRL_MODE_CAN
                    and report.ctrl_mode != CTRL_MODE_CAN)
        if went_bad or left_can or (was_bad and not fault[2]):
            # Under the command lock so no set-point decided before this report goes out after
            # it. The arm may have left CAN command mode while stopped, hence the 0x151 re-send.
            with self._cmd_lock:
                if went_bad:
                    self._stream.end()
                self._mode_sent = None

    def _count(self, reason: str) -> None:
        with self._lock:
            self.malformed[reason] += 1

    def _check_watchdog(self) -> None:
        if not self._stream.active:   # unlocked peek; decided again under the lock
            return
        with self._cmd_lock:
            if self._stream.stalled(self.watchdog):
                self.watchdog_stops += 1
                try:
                    self._hold()
                except ArmError:
                    pass  # no feedback to hold at; status() already reports the loss

    # ---- helpers -------------------------------------------------------------------------------
    def _send(self, msgs: Sequence[can.Message]) -> None:
        with self._send_lock:
            try:
                for m in msgs:
                    self.bus.send(m, timeout=0.05)
            except (can.CanError, OSError) as e:
                raise ArmError(f"PiPER: CAN send failed: {e}") from e

    def _command(self, pose: np.ndarray, speed_percent: int = 100) -> None:
        mode = MotionMode(CTRL_MODE_CAN, MOVE_P, speed_percent)
        msgs = encode_end_pose(pose_to_units(pose), END_POSE_CTRL)
        if mode != self._mode_sent or not self._in_mode(mode):
            # again with every command until the arm reports the mode: one lost 0x151 frame
            # (or an arm that restarted in standby) must not leave it deaf to every target
            msgs = [encode_motion_mode(mode)] + msgs
            self._mode_sent = mode
        self._send(msgs)

    def _in_mode(self, mode: MotionMode) -> bool:
        """The arm's last status report says it is in ``mode`` (CAN command, that move mode)."""
        with self._lock:
            report = self._report
        return report is not None and report.ctrl_mode == mode.ctrl_mode \
            and report.mode_feed == mode.move_mode

    def _fresh_pose(self) -> tuple[float, np.ndarray]:
        with self._lock:
            pose, stamp, mono = self._pose, self._pose_time, self._pose_mono
        age = time.monotonic() - mono
        if pose is None:
            raise ArmError(f"PiPER: no end-pose feedback received yet (waited "
                           f"{time.monotonic() - self._first_mono:.2f} s)")
        if age > self.stale_after:
            raise ArmError(f"PiPER: end-pose feedback is stale ({age:.2f} s old, limit "
                           f"{self.stale_after:.2f} s)")
        return stamp, pose.copy()

    def _fresh_status(self) -> tuple[StatusReport, tuple[bool, bool, str]]:
        with self._lock:
            report, mono, fault = self._report, self._report_mono, self._fault
        if report is None:
            raise ArmError(f"PiPER: no arm status feedback (0x2A1) received yet (waited "
                           f"{time.monotonic() - self._first_mono:.2f} s)")
        age = time.monotonic() - mono
        if age > self.stale_after:
            raise ArmError(f"PiPER: arm status feedback (0x2A1) is stale ({age:.2f} s old, limit "
                           f"{self.stale_after:.2f} s)")
        return report, fault

    def _check_commandable(self, what: str) -> None:
        """Raise ``ArmError`` unless the arm's latest status says it may be commanded."""
        error = self._fresh_status()[1][2]
        if error:
            raise ArmError(f"{what}: not sent, the PiPER reports {error}")

    def _hold(self) -> None:
        """The measured pose commanded: the stream under way ends (the next set-point starts
        from rest)."""
        self._stream.end()
        _, pose = self._fresh_pose()
        self._held = pose
        self._command(pose)

    def _refused(self, streaming: bool) -> None:
        try:
            self._hold()
        except ArmError:
            pass  # no feedback to hold at; status() reports the loss

    def wait_for_feedback(self, timeout: float = 1.0) -> tuple[float, np.ndarray]:
        """Block until fresh end-pose and arm status feedback arrive (or raise ``ArmError``
        after ``timeout``); returns the pose."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                pose = self._fresh_pose()
                self._fresh_status()
                return pose
            except ArmError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.005)

    # ---- Arm interface -----------------------------------------------------------------------
    def tool_pose(self) -> tuple[float, np.ndarray]:
        return self._fresh_pose()

    def velocity(self) -> tuple[np.ndarray, np.ndarray]:
        """The PiPER reports no velocity: the difference of its last two end-pose reports over
        their bus time stamps."""
        stamp, pose = self._fresh_pose()
        with self._lock:
            prev, prev_stamp = self._prev
        dt = stamp - prev_stamp
        if prev is None or not dt > 0:
            return np.zeros(3), np.zeros(3)
        step = servo_step(pose, prev) / dt
        return step[:3], step[3:]

    def servo_nowait(self, pose) -> float:
        """Send one set-point and return the end of its cycle (:class:`~drivers.base.Pacer`
        schedule), which ``servo()`` waits for. A set-point that
        breaks a limit is not sent: the arm holds its measured pose and :class:`LimitError` is
        raised. The first set-point of a stream is measured from the measured pose, at rest."""
        t0 = time.monotonic()
        target = unit_pose(pose)
        with self._cmd_lock:
            self._servo(target)
        return self._pacer.cycle(t0) + self.period

    def _servo(self, target: np.ndarray) -> None:
        self._check_commandable("servo")
        here = self._fresh_pose()[1]        # stale feedback refuses the set-point
        step = self._checked_setpoint(target, lambda: here)
        self._stream.sent(target, step)
        self._command(target)

    def move(self, pose, speed: float, accel: float, timeout: Optional[float] = None) -> None:
        """Trapezoidal straight-line move streamed at ``period``; returns once the feedback is
        within tolerance of ``pose`` (``ArmError`` on ``timeout``, loss of feedback or stop).
        ``speed`` and ``accel`` are m/s and m/s^2; the rotation runs on the same profile, scaled
        so it stays within the angular limits."""
        target = unit_pose(pose)
        L = self.limits
        L.check_move(target, speed, accel)
        self._stream.end()
        self._abort.clear()
        _, start = self._fresh_pose()
        self._check_commandable("move")
        dist, ang = pose_delta(start, target)
        # radians per translation-equivalent metre, within both angular limits
        scale = min(L.max_angular_velocity / L.max_linear_velocity,
                    L.max_angular_acceleration / L.max_linear_acceleration)
        profile = Trapezoid(max(dist, ang / scale), speed, accel)
        if timeout is None:
            timeout = profile.duration + 2.0
        t0 = time.monotonic()
        deadline = t0 + timeout
        next_tick = t0
        while True:
            now = time.monotonic()
            el = now - t0
            sp = tool_line(start, target, profile.fraction(el)) if el < profile.duration \
                else target
            with self._cmd_lock:
                if self._abort.is_set():
                    raise ArmError("move: stopped before reaching the target")
                self._check_commandable("move")
                self._command(sp)
            _, cur = self._fresh_pose()
            if el >= profile.duration:
                d, a = pose_delta(cur, target)
                if d <= self.position_tolerance and a <= self.angle_tolerance:
                    return
            if now > deadline:
                d, a = pose_delta(cur, target)
                raise ArmError(f"move: target not reached within {timeout:.2f} s (still "
                               f"{d * 1000:.2f} mm / {math.degrees(a):.3f} deg away)")
            next_tick += self.period
            time.sleep(max(0.0, next_tick - time.monotonic()))

    def stop(self) -> None:
        """Command the measured pose as the target, ending any servo stream or move."""
        with self._cmd_lock:
            self._abort.set()
            self._hold()

    def status(self) -> ArmState:
        """The stop flags are those of the last status report even when it is stale (then
        ``connected`` is False and ``error`` says so): the last thing the arm said."""
        with self._lock:
            mono, poses, frames = self._pose_mono, self.poses, self.frames
            report, report_mono, reports = self._report, self._report_mono, self.reports
            emergency, protective, fault = self._fault
            malformed = dict(self.malformed)
        now = time.monotonic()
        age, report_age = now - mono, now - report_mono
        connected = (age <= self.stale_after and report_age <= self.stale_after
                     and not self._closed.is_set())
        if self._closed.is_set():
            error = "closed"
        elif poses == 0:
            error = "no end-pose feedback received yet"
        elif age > self.stale_after:
            error = f"end-pose feedback is stale ({age:.2f} s old)"
        elif reports == 0:
            error = "no arm status feedback (0x2A1) received yet"
        elif report_age > self.stale_after:
            error = f"arm status feedback (0x2A1) is stale ({report_age:.2f} s old)"
        else:
            error = fault
        extra = {"feedback_age": age, "poses": poses, "frames": frames, "malformed": malformed,
                 "watchdog_stops": self.watchdog_stops, "status_age": report_age,
                 "reports": reports, "stale_after": self.stale_after}
        if report is not None:
            extra.update(ctrl_mode=report.ctrl_mode, arm_status=report.arm_status,
                         mode_feed=report.mode_feed, teach_status=report.teach_status,
                         motion_status=report.motion_status,
                         trajectory_num=report.trajectory_num, err_code=report.err_code)
        return ArmState(connected=connected, protective_stop=protective,
                        emergency_stop=emergency, faults=(error,) if error else (), extra=extra)

    def close(self) -> None:
        if self._closed.is_set():
            return
        try:
            if self._stream.active:
                self.stop()
        except ArmError:
            pass
        self._closed.set()
        self._thread.join(timeout=1.0)
        if self._own_bus:
            self.bus.shutdown()


#: stale_after, when not given, is at least this many feedback periods
STALE_PERIODS = 3
#: ... and at most this (s): feedback slower than a third of it is a fault, not a period, so a
#: bus that slows down by degrees cannot stretch the arm's trust in old feedback without end
STALE_MAX = 1.0


class _Period:
    """One kind of feedback's period: the median of its last intervals (0 until there are a
    few), measured again from scratch after a gap longer than stale_after (a recovery)."""

    KEEP, EVERY = 32, 8         # intervals kept; the median taken again every EVERY of them

    def __init__(self):
        self.intervals: list[float] = []
        self.period = 0.0
        self._new = 0

    def arrived(self, interval: float, stale_after: float) -> None:
        if not math.isfinite(interval):
            return                  # the first one
        if interval > stale_after:
            self.intervals, self.period, self._new = [], 0.0, 0
            return
        self.intervals.append(interval)
        if len(self.intervals) > self.KEEP:
            del self.intervals[0]
        self._new += 1
        if self._new >= self.EVERY:
            self._new = 0
            self.period = float(np.median(self.intervals))
