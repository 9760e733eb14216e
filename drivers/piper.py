"""AgileX PiPER arm over CAN (any ``python-can`` bus), commanded in tool space.

Our own codec for the frames we use (standard 11-bit ids, 8 data bytes, big-endian):

* ``0x151`` motion mode: control mode, move mode, speed percent, MIT mode, residence time,
  installation position (one byte each);
* ``0x152``/``0x153``/``0x154`` end-pose command and ``0x2A2``/``0x2A3``/``0x2A4`` end-pose
  feedback: signed int32 pairs (X, Y), (Z, RX), (RY, RZ); positions in 0.001 mm, angles in
  0.001 degree, static-axes ``sxyz`` Euler angles (``R = Rz(RZ) Ry(RY) Rx(RX)``);
* ``0x2A1`` arm status: control mode, arm status, mode feedback, teach status, motion status,
  trajectory number (one byte each), then a big-endian uint16 error code whose high byte flags
  joints 1-6 beyond their angle limit and whose low byte flags joints 1-6 with a communication
  error (bits 0-5).

By name: ``drivers.open_arm("piper:socketcan:can0")`` (``piper:<python-can interface>:<channel>``;
``piper:udp_multicast:239.74.163.2`` reaches ``dqpose sim piper`` in another process).

``PiperArm`` runs a receive thread that assembles feedback poses, decodes the arm status, counts
and skips malformed frames, and watches the command stream: if ``servo`` set-points stop arriving
the arm is told to hold where it is. While the arm reports a stop or fault, ``servo`` and
``move`` refuse to command it. Poses cross the interface as dual quaternions ``T_base_tool``.
"""
from __future__ import annotations

import math
import struct
import threading
import time
from collections import Counter
from dataclasses import dataclass
from typing import Optional, Sequence

import can
import numpy as np

from dqpose.drivers.base import (Arm, ArmError, ArmState, LimitError, Limits, Pacer, pose_delta,
                          servo_step, tool_line, unit_pose)
from dqpose.drivers.euler import quat_from_sxyz, sxyz_from_quat
from dqpose import dq
from dqpose.profile import Trapezoid

__all__ = [
    "MOTION_CTRL_2", "END_POSE_CTRL", "END_POSE_FEEDBACK", "CTRL_MODE_CAN", "MOVE_P", "MOVE_J",
    "MOVE_L", "MotionMode", "EndPose", "FrameError", "EndPoseAssembler",
    "encode_motion_mode", "decode_motion_mode", "encode_end_pose", "decode_pair",
    "pose_to_units", "units_to_pose", "ARM_STATUS_FEEDBACK", "ARM_STATUS_NAMES",
    "ARM_NORMAL", "ARM_EMERGENCY_STOP", "ARM_COLLISION", "EMERGENCY_STATES",
    "PROTECTIVE_STATES", "REJECTION_STATES", "TEACH_STATES", "StatusReport",
    "encode_arm_status", "decode_arm_status", "describe_status", "COMMAND_BLOCK",
    "FEEDBACK_BLOCK", "KNOWN_FEEDBACK", "PiperArm",
]

MOTION_CTRL_2 = 0x151
END_POSE_CTRL = (0x152, 0x153, 0x154)
END_POSE_FEEDBACK = (0x2A2, 0x2A3, 0x2A4)
CTRL_MODE_CAN = 0x01
MOVE_P, MOVE_J, MOVE_L = 0x00, 0x01, 0x02
ARM_STATUS_FEEDBACK = 0x2A1

#: arm_status (byte 1 of 0x2A1) as piper_sdk 0.6.2 documents it
ARM_STATUS_NAMES = {
    0x00: "normal", 0x01: "emergency stop", 0x02: "no solution for the target",
    0x03: "singularity", 0x04: "target angle over limit", 0x05: "joint communication error",
    0x06: "joint brake not released", 0x07: "collision", 0x08: "overspeed during teach drag",
    0x09: "joint status abnormal", 0x0A: "other error", 0x0B: "teach recording",
    0x0C: "teach trajectory executing", 0x0D: "teach trajectory paused",
    0x0E: "main controller over temperature", 0x0F: "release resistor over temperature",
}
ARM_NORMAL, ARM_EMERGENCY_STOP, ARM_COLLISION = 0x00, 0x01, 0x07
EMERGENCY_STATES = frozenset({0x01})
# The arm has stopped itself (hardware fault, collision, overheating, brakes holding) and will not
# follow commands until an operator clears the cause: a protective stop in UR's sense.
PROTECTIVE_STATES = frozenset({0x05, 0x06, 0x07, 0x08, 0x09, 0x0A, 0x0E, 0x0F})
# The arm refused the last target (its own planner); it stays where it is, which is safe, but it
# is not following us. Not a safety stop.
REJECTION_STATES = frozenset({0x02, 0x03, 0x04})
# Someone is teaching or replaying by hand; not ours to command.
TEACH_STATES = frozenset({0x0B, 0x0C, 0x0D})

# Feedback block of the arm; ids here that the protocol does not define are malformed.
FEEDBACK_BLOCK = range(0x2A0, 0x2B0)
KNOWN_FEEDBACK = frozenset({0x2A1, *END_POSE_FEEDBACK, 0x2A5, 0x2A6, 0x2A7, 0x2A8})
# Command block (0x150-0x15F are all defined by the protocol).
COMMAND_BLOCK = range(0x150, 0x160)

_UNITS_PER_M = 1e6            # 0.001 mm
_UNITS_PER_RAD = 180e3 / math.pi  # 0.001 degree
# The PiPER reaches ~0.63 m; anything beyond this is a corrupted frame, not a pose.
MAX_ABS_POSITION_M = 2.0
MAX_ABS_ANGLE_UNITS = 180_000
_INT32 = struct.Struct(">ii")
_STATUS = struct.Struct(">6BH")


class FrameError(ValueError):
    """A frame that is not a valid PiPER frame; ``reason`` is a short key for counting."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class MotionMode:
    ctrl_mode: int = CTRL_MODE_CAN
    move_mode: int = MOVE_P
    speed_percent: int = 100
    mit_mode: int = 0x00
    residence_time: int = 0
    installation_pos: int = 0x00


@dataclass(frozen=True)
class EndPose:
    """One end pose in protocol units: X, Y, Z in 0.001 mm and RX, RY, RZ in 0.001 degree."""
    x: int
    y: int
    z: int
    rx: int
    ry: int
    rz: int

    def as_tuple(self) -> tuple[int, int, int, int, int, int]:
        return (self.x, self.y, self.z, self.rx, self.ry, self.rz)


def _check_frame(msg: can.Message) -> None:
    if msg.is_error_frame:
        raise FrameError("error_frame", f"frame 0x{msg.arbitration_id:X}: CAN error frame")
    if msg.is_remote_frame:
        raise FrameError("remote_frame", f"frame 0x{msg.arbitration_id:X}: remote frame")
    if msg.is_extended_id:
        raise FrameError("extended_id", f"frame 0x{msg.arbitration_id:X}: extended id, "
                         "PiPER uses standard 11-bit ids")
    if msg.dlc != 8 or len(msg.data) != 8:
        raise FrameError("dlc", f"frame 0x{msg.arbitration_id:X}: DLC {msg.dlc}, expected 8")


def encode_motion_mode(mode: MotionMode = MotionMode()) -> can.Message:
    fields = (mode.ctrl_mode, mode.move_mode, mode.speed_percent, mode.mit_mode,
              mode.residence_time, mode.installation_pos)
    for name, v in zip(("ctrl_mode", "move_mode", "speed_percent", "mit_mode",
                        "residence_time", "installation_pos"), fields):
        if not 0 <= int(v) <= 255:
            raise ValueError(f"mode.{name}: {v} does not fit in one byte")
    if not 0 <= mode.speed_percent <= 100:
        raise ValueError(f"mode.speed_percent: {mode.speed_percent} is outside 0..100")
    return can.Message(arbitration_id=MOTION_CTRL_2, is_extended_id=False,
                       data=bytes(int(v) for v in fields) + b"\x00\x00")


def decode_motion_mode(msg: can.Message) -> MotionMode:
    _check_frame(msg)
    if msg.arbitration_id != MOTION_CTRL_2:
        raise FrameError("unknown_id", f"frame 0x{msg.arbitration_id:X}: not a 0x151 frame")
    d = msg.data
    if d[2] > 100:
        raise FrameError("value", f"frame 0x151: speed percent {d[2]} is outside 0..100")
    return MotionMode(d[0], d[1], d[2], d[3], d[4], d[5])


def encode_end_pose(p: EndPose, ids: Sequence[int] = END_POSE_CTRL) -> list[can.Message]:
    """Three frames (X, Y), (Z, RX), (RY, RZ); ``ids`` picks command or feedback ids."""
    vals = p.as_tuple()
    return [can.Message(arbitration_id=i, is_extended_id=False,
                        data=_INT32.pack(vals[2 * k], vals[2 * k + 1]))
            for k, i in enumerate(ids)]


def decode_pair(msg: can.Message, ids: Sequence[int]) -> tuple[int, int, int]:
    """``(index 0..2 of the frame within ids, first value, second value)``; values checked."""
    _check_frame(msg)
    try:
        k = list(ids).index(msg.arbitration_id)
    except ValueError:
        raise FrameError("unknown_id", f"frame 0x{msg.arbitration_id:X}: not an end-pose frame") \
            from None
    a, b = _INT32.unpack(bytes(msg.data))
    names = (("X", "Y"), ("Z", "RX"), ("RY", "RZ"))[k]
    for name, v in zip(names, (a, b)):
        if name.startswith("R"):
            ok = abs(v) <= MAX_ABS_ANGLE_UNITS
        else:
            ok = abs(v) <= MAX_ABS_POSITION_M * _UNITS_PER_M
        if not ok:
            raise FrameError("value", f"frame 0x{msg.arbitration_id:X}: {name} = {v} is not a "
                             "possible end-pose value")
    return k, a, b


def _round_units(v: float) -> int:
    return int(round(v))


def pose_to_units(pose) -> EndPose:
    """A dual quaternion to the nearest protocol integers (0.001 mm, 0.001 deg, sxyz)."""
    q, t = dq.to_pose(dq.normalize(np.asarray(pose, dtype=float)))
    r = sxyz_from_quat(q)
    xyz = [_round_units(v * _UNITS_PER_M) for v in t]
    rxyz = [_round_units(v * _UNITS_PER_RAD) for v in r]
    # Rounding can push +-180 deg one unit past the range; the same angle is on the other side.
    rxyz = [v - 360_000 if v > MAX_ABS_ANGLE_UNITS else v + 360_000 if v < -MAX_ABS_ANGLE_UNITS
            else v for v in rxyz]
    return EndPose(*xyz, *rxyz)


def units_to_pose(p: EndPose) -> np.ndarray:
    """Protocol integers to a dual quaternion (exact conversion, no rounding)."""
    rx, ry, rz = (v / _UNITS_PER_RAD for v in (p.rx, p.ry, p.rz))
    t = np.array([p.x, p.y, p.z], dtype=float) / _UNITS_PER_M
    return dq.from_pose(quat_from_sxyz(rx, ry, rz), t)


@dataclass(frozen=True)
class StatusReport:
    """One 0x2A1 arm status frame, fields as the protocol names them."""
    ctrl_mode: int = 0x00
    arm_status: int = ARM_NORMAL
    mode_feed: int = MOVE_P
    teach_status: int = 0x00
    motion_status: int = 0x00
    trajectory_num: int = 0
    err_code: int = 0

    @property
    def angle_limit_joints(self) -> tuple[int, ...]:
        """Joints (1-6) the arm reports beyond their angle limit (high byte of err_code)."""
        return tuple(j for j in range(1, 7) if self.err_code >> (8 + j - 1) & 1)

    @property
    def comm_error_joints(self) -> tuple[int, ...]:
        """Joints (1-6) the arm reports a communication error for (low byte of err_code)."""
        return tuple(j for j in range(1, 7) if self.err_code >> (j - 1) & 1)


def encode_arm_status(s: StatusReport) -> can.Message:
    names = ("ctrl_mode", "arm_status", "mode_feed", "teach_status", "motion_status",
             "trajectory_num")
    for name in names:
        v = getattr(s, name)
        if not 0 <= int(v) <= 255:
            raise ValueError(f"status.{name}: {v} does not fit in one byte")
    if not 0 <= int(s.err_code) <= 0xFFFF:
        raise ValueError(f"status.err_code: {s.err_code} does not fit in 16 bits")
    return can.Message(arbitration_id=ARM_STATUS_FEEDBACK, is_extended_id=False,
                       data=_STATUS.pack(*(int(getattr(s, n)) for n in names), int(s.err_code)))


def decode_arm_status(msg: can.Message) -> StatusReport:
    """Values are passed through unchecked: an arm_status this codec does not know is judged by
    ``describe_status`` (as a fault), so a newer firmware's stop is never dropped as noise."""
    _check_frame(msg)
    if msg.arbitration_id != ARM_STATUS_FEEDBACK:
        raise FrameError("unknown_id", f"frame 0x{msg.arbitration_id:X}: not a 0x2A1 frame")
    return StatusReport(*_STATUS.unpack(bytes(msg.data)))


def describe_status(s: StatusReport) -> tuple[bool, bool, str]:
    """``(emergency_stop, protective_stop, error)`` for one report; ``error`` is empty when the
    arm is fit to command. ``EMERGENCY_STATES`` and ``PROTECTIVE_STATES`` set the flags;
    ``REJECTION_STATES`` and ``TEACH_STATES`` only give the error text. Any err_code bit (a joint
    beyond its limit or not talking) is a protective stop, and so is an arm_status code the
    protocol does not define."""
    code = s.arm_status
    emergency = code in EMERGENCY_STATES
    known = code in ARM_STATUS_NAMES
    protective = code in PROTECTIVE_STATES or not known
    parts = []
    if code != ARM_NORMAL:
        name = ARM_STATUS_NAMES.get(code, "unknown arm status")
        parts.append(f"{name} (arm_status 0x{code:02X})")
    joints = [f"joint {j} angle over limit" for j in s.angle_limit_joints] + \
             [f"joint {j} communication error" for j in s.comm_error_joints]
    if joints:
        protective = True
        parts.append(", ".join(joints) + f" (err_code 0x{s.err_code:04X})")
    elif s.err_code:
        # only reserved bits: nothing we can name, but not nothing either
        protective = True
        parts.append(f"reserved error bits (err_code 0x{s.err_code:04X})")
    return emergency, protective, "; ".join(parts)


class EndPoseAssembler:
    """Collects the three frames of one end pose. A pose is complete when the last frame of a
    set arrives and the other two arrived since the previous complete pose, so a pose never
    mixes two cycles once a set is torn."""

    def __init__(self, ids: Sequence[int]):
        self.ids = tuple(ids)
        self._parts: list[Optional[tuple[int, int]]] = [None, None, None]

    def feed(self, msg: can.Message) -> Optional[EndPose]:
        k, a, b = decode_pair(msg, self.ids)
        self._parts[k] = (a, b)
        if k != 2:
            return None
        parts, self._parts = self._parts, [None, None, None]
        if parts[0] is None or parts[1] is None:
            return None
        return EndPose(*parts[0], *parts[1], *parts[2])


class PiperArm(Arm):
    """A PiPER on ``bus`` (``can.Bus`` of any interface), in end-pose (MOVE P) mode.

    Safety, as every :class:`~drivers.base.Arm`: ``servo`` set-points are checked against
    ``limits`` (:meth:`Limits.check_servo`, one ``period`` apart) and one that breaks a limit is
    not sent: the arm is told to hold its measured pose and :class:`LimitError` is raised;
    ``move`` checks its arguments with :meth:`Limits.check_move`. If no servo set-point arrives
    for ``watchdog`` seconds the arm is told to hold its measured pose. The arm counts as
    connected while both end-pose feedback and arm status (0x2A1) are younger than
    ``stale_after``. ``watchdog``, ``stale_after`` and the other keys of
    :data:`dqpose.drivers.spec.ARM_KEYS` are ``options``. ``own_bus`` shuts the bus down on ``close()``
    (``open_arm`` does, and waits up to ``connect_timeout`` for the arm's first feedback).

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
        # servo stream state
        self._setpoint: Optional[np.ndarray] = None
        self._step = np.zeros(6)       # the last servo step (Limits.check_servo)
        self._last_servo = -math.inf
        self._servo_active = False
        self._abort = threading.Event()
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._receive, name="piper-rx", daemon=True)
        self._thread.start()

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
        with self._lock:
            self._prev = (self._pose, self._pose_time)
            self._pose, self._pose_time, self._pose_mono = pose, stamp, time.monotonic()
            self.poses += 1

    def _handle_status(self, msg: can.Message) -> None:
        try:
            report = decode_arm_status(msg)
        except FrameError as e:
            self._count(e.reason)
            return
        fault = describe_status(report)
        with self._lock:
            prev, was_bad = self._report, bool(self._fault[2])
            self._report, self._report_mono, self._fault = report, time.monotonic(), fault
            self.reports += 1
        went_bad = bool(fault[2]) and not was_bad
        left_can = (prev is not None and prev.ctrl_mode == CTRL_MODE_CAN
                    and report.ctrl_mode != CTRL_MODE_CAN)
        if went_bad or left_can or (was_bad and not fault[2]):
            # Under the command lock so no set-point decided before this report goes out after
            # it. The arm may have left CAN command mode while stopped, hence the 0x151 re-send.
            with self._cmd_lock:
                if went_bad:
                    with self._lock:
                        self._servo_active = False
                self._mode_sent = None

    def _count(self, reason: str) -> None:
        with self._lock:
            self.malformed[reason] += 1

    def _check_watchdog(self) -> None:
        if not self._servo_active:   # unlocked peek; decided again under the lock
            return
        with self._cmd_lock:
            with self._lock:
                stalled = (self._servo_active
                           and time.monotonic() - self._last_servo > self.watchdog)
                if stalled:
                    self._servo_active = False
            if stalled:
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
        _, pose = self._fresh_pose()
        with self._lock:
            self._setpoint = pose
            self._step = np.zeros(6)
        self._command(pose)

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
        with self._lock:
            active = self._servo_active
            prev, prev_step = (self._setpoint, self._step.copy()) if active else (None, np.zeros(6))
        if prev is None:
            prev = self._fresh_pose()[1]
        else:
            self._fresh_pose()
        try:
            step = self.limits.check_servo(target, prev, prev_step, self.period)
        except LimitError:
            with self._lock:
                self._servo_active = False
            try:
                self._hold()
            except ArmError:
                pass  # no feedback to hold at; status() reports the loss
            raise
        with self._lock:
            self._setpoint = target
            self._step = step
            self._last_servo = time.monotonic()
            self._servo_active = True
        self._command(target)

    def move(self, pose, speed: float, accel: float, timeout: Optional[float] = None) -> None:
        """Trapezoidal straight-line move streamed at ``period``; returns once the feedback is
        within tolerance of ``pose`` (``ArmError`` on ``timeout``, loss of feedback or stop).
        ``speed`` and ``accel`` are m/s and m/s^2; the rotation runs on the same profile, scaled
        so it stays within the angular limits."""
        target = unit_pose(pose)
        L = self.limits
        L.check_move(target, speed, accel)
        with self._lock:
            self._servo_active = False
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
                    with self._lock:
                        self._setpoint = target
                        self._step = np.zeros(6)
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
            with self._lock:
                self._servo_active = False
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
                 "reports": reports}
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
            with self._lock:
                active = self._servo_active
            if active:
                self.stop()
        except ArmError:
            pass
        self._closed.set()
        self._thread.join(timeout=1.0)
        if self._own_bus:
            self.bus.shutdown()
