"""The PiPER CAN codec (drivers/piper_can.py) on its own: units, frame layouts, torn sets,
malformed frames, the arm status and what each code means."""
import struct

import can
import numpy as np
import pytest

from dqpose.drivers.base import pose_delta as _delta
from dqpose.drivers.euler import dq_from_xyz_sxyz
from dqpose.drivers.piper_can import (
    ARM_STATUS_FEEDBACK,
    ARM_STATUS_NAMES,
    EMERGENCY_STATES,
    END_POSE_FEEDBACK,
    PROTECTIVE_STATES,
    REJECTION_STATES,
    TEACH_STATES,
    EndPose,
    EndPoseAssembler,
    FrameError,
    MotionMode,
    StatusReport,
    decode_arm_status,
    decode_motion_mode,
    describe_status,
    encode_arm_status,
    encode_end_pose,
    encode_motion_mode,
    pose_to_units,
    units_to_pose,
)
from tests.drivers._piper import ANG_Q, POS_Q, random_poses


def test_units_round_trip_within_quantisation():
    rng = np.random.default_rng(1)
    for T in random_poses(rng, 200):
        back = units_to_pose(pose_to_units(T))
        d, a = _delta(T, back)
        assert d <= POS_Q and a <= ANG_Q


def test_units_are_micrometres_and_millidegrees():
    T = dq_from_xyz_sxyz([0.123456, -0.5, 0.25], np.radians([10.0, -20.5, 179.9]))
    assert pose_to_units(T).as_tuple() == (123456, -500000, 250000, 10000, -20500, 179900)


def test_frames_big_endian_signed_pairs():
    frames = encode_end_pose(EndPose(1, -2, 3, 4, -5, 6), END_POSE_FEEDBACK)
    assert [f.arbitration_id for f in frames] == list(END_POSE_FEEDBACK)
    assert bytes(frames[0].data) == bytes.fromhex("00000001fffffffe")
    asm = EndPoseAssembler(END_POSE_FEEDBACK)
    assert [asm.feed(f) for f in frames][-1] == EndPose(1, -2, 3, 4, -5, 6)


def test_assembler_drops_torn_sets():
    frames = encode_end_pose(EndPose(1, 2, 3, 4, 5, 6), END_POSE_FEEDBACK)
    asm = EndPoseAssembler(END_POSE_FEEDBACK)
    assert asm.feed(frames[0]) is None
    assert asm.feed(frames[2]) is None      # 0x2A3 missing: no pose
    assert asm.feed(frames[1]) is None
    assert asm.feed(frames[2]) is None      # 0x2A2 was consumed by the torn set
    for f in frames:
        out = asm.feed(f)
    assert out == EndPose(1, 2, 3, 4, 5, 6)


@pytest.mark.parametrize("msg,reason", [
    (can.Message(arbitration_id=0x2A2, data=b"\x00" * 6, is_extended_id=False), "dlc"),
    (can.Message(arbitration_id=0x2A2, data=b"\x00" * 8, is_extended_id=True), "extended_id"),
    (can.Message(arbitration_id=0x2A3, data=struct.pack(">ii", 0, 200_000),
                 is_extended_id=False), "value"),
    (can.Message(arbitration_id=0x2A2, data=struct.pack(">ii", 2**31 - 1, 0),
                 is_extended_id=False), "value"),
    (can.Message(arbitration_id=0x2A9, data=b"\x00" * 8, is_extended_id=False), "unknown_id"),
])
def test_decoder_rejects_malformed(msg, reason):
    with pytest.raises(FrameError) as e:
        EndPoseAssembler(END_POSE_FEEDBACK).feed(msg)
    assert e.value.reason == reason


def test_motion_mode_bad_values():
    with pytest.raises(ValueError, match="speed_percent"):
        encode_motion_mode(MotionMode(speed_percent=101))
    bad = can.Message(arbitration_id=0x151, data=bytes([1, 0, 150, 0, 0, 0, 0, 0]),
                      is_extended_id=False)
    with pytest.raises(FrameError):
        decode_motion_mode(bad)


def test_arm_status_frame_layout():
    s = StatusReport(ctrl_mode=0x01, arm_status=0x07, mode_feed=0x02, teach_status=0x00,
                     motion_status=0x01, trajectory_num=5, err_code=0x0410)
    m = encode_arm_status(s)
    assert m.arbitration_id == ARM_STATUS_FEEDBACK and not m.is_extended_id
    assert bytes(m.data) == bytes.fromhex("0107020001050410")
    assert decode_arm_status(m) == s
    # high byte: angle limits, low byte: communication errors
    assert s.angle_limit_joints == (3,) and s.comm_error_joints == (5,)
    assert StatusReport(err_code=0x3F3F).angle_limit_joints == (1, 2, 3, 4, 5, 6)


@pytest.mark.parametrize("report,emergency,protective,words", [
    (StatusReport(), False, False, []),
    (StatusReport(arm_status=0x01), True, False, ["emergency stop", "0x01"]),
    (StatusReport(arm_status=0x07), False, True, ["collision", "0x07"]),
    (StatusReport(arm_status=0x05, err_code=0x0002), False, True,
     ["joint communication error (arm_status 0x05)", "joint 2 communication error"]),
    (StatusReport(err_code=0x0400), False, True, ["joint 3 angle over limit", "0x0400"]),
    (StatusReport(arm_status=0x0E), False, True, ["over temperature"]),
    (StatusReport(arm_status=0x42), False, True, ["unknown arm status", "0x42"]),
    # refusals and hand teaching stop our commands but are no safety stop
    (StatusReport(arm_status=0x02), False, False, ["no solution"]),
    (StatusReport(arm_status=0x0B), False, False, ["teach recording"]),
])
def test_describe_status(report, emergency, protective, words):
    e, p, text = describe_status(report)
    assert (e, p) == (emergency, protective)
    assert bool(text) == bool(words)
    for w in words:
        assert w in text


def test_status_classes_cover_every_code_once():
    classes = [{0x00}, EMERGENCY_STATES, PROTECTIVE_STATES, REJECTION_STATES, TEACH_STATES]
    assert sorted(c for cls in classes for c in cls) == sorted(ARM_STATUS_NAMES)


def test_arm_status_codec_bad_input():
    with pytest.raises(ValueError, match="status.err_code"):
        encode_arm_status(StatusReport(err_code=0x10000))
    with pytest.raises(ValueError, match="status.motion_status"):
        encode_arm_status(StatusReport(motion_status=256))
    with pytest.raises(FrameError) as e:
        decode_arm_status(can.Message(arbitration_id=0x2A1, data=b"\x00" * 7,
                                      is_extended_id=False))
    assert e.value.reason == "dlc"
    with pytest.raises(FrameError) as e:
        decode_arm_status(can.Message(arbitration_id=0x2A2, data=b"\x00" * 8,
                                      is_extended_id=False))
    assert e.value.reason == "unknown_id"
