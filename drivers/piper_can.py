"""The AgileX PiPER's CAN frames: ids, our own codec for the frames we use, and what an arm
status means (:class:`dqpose.drivers.piper.PiperArm` and the simulator ``dqpose sim piper``
both speak through it).

Frames are standard 11-bit ids, 8 data bytes, big-endian:

* ``0x151`` motion mode: control mode, move mode, speed percent, MIT mode, residence time,
  installation position (one byte each);
* ``0x152``/``0x153``/``0x154`` end-pose command and ``0x2A2``/``0x2A3``/``0x2A4`` end-pose
  feedback: signed int32 pairs (X, Y), (Z, RX), (RY, RZ); positions in 0.001 mm, angles in
  0.001 degree, static-axes ``sxyz`` Euler angles (``R = Rz(RZ) Ry(RY) Rx(RX)``);
* ``0x2A1`` arm status: control mode, arm status, mode feedback, teach status, motion status,
  trajectory number (one byte each), then a big-endian uint16 error code whose high byte flags
  joints 1-6 beyond their angle limit and whose low byte flags joints 1-6 with a communication
  error (bits 0-5).

A frame that is not a valid PiPER frame raises :class:`FrameError` (a ``ValueError`` with a
short ``reason`` for counting). Poses cross this codec as dual quaternions.
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Optional, Sequence

import can
import numpy as np

from dqpose import dq
from dqpose.drivers.euler import quat_from_sxyz, sxyz_from_quat

__all__ = [
    "MOTION_CTRL_2", "END_POSE_CTRL", "END_POSE_FEEDBACK", "CTRL_MODE_CAN", "MOVE_P", "MOVE_J",
    "MOVE_L", "MotionMode", "EndPose", "FrameError", "EndPoseAssembler",
    "encode_motion_mode", "decode_motion_mode", "encode_end_pose", "decode_pair",
    "pose_to_units", "units_to_pose", "ARM_STATUS_FEEDBACK", "ARM_STATUS_NAMES",
    "ARM_NORMAL", "ARM_EMERGENCY_STOP", "ARM_COLLISION", "EMERGENCY_STATES",
    "PROTECTIVE_STATES", "REJECTION_STATES", "TEACH_STATES", "StatusReport",
    "encode_arm_status", "decode_arm_status", "describe_status", "COMMAND_BLOCK",
    "FEEDBACK_BLOCK", "KNOWN_FEEDBACK",
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
