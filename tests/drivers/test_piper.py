"""PiPER simulator and driver against each other and against the real ``piper_sdk``, all on
python-can's in-process ``virtual`` bus."""
import math
import struct
import time
import uuid

import can
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dqpose import dq
from dqpose.drivers.base import ArmError, LimitError
from dqpose.drivers.base import pose_delta as _delta
from dqpose.drivers.euler import dq_from_xyz_sxyz
from dqpose.drivers.piper import PiperArm
from dqpose.drivers.piper_can import (
    END_POSE_CTRL,
    MOVE_L,
    MOVE_P,
    EndPose,
    EndPoseAssembler,
    MotionMode,
    decode_arm_status,
    decode_motion_mode,
    encode_arm_status,
    encode_end_pose,
    encode_motion_mode,
    pose_to_units,
    units_to_pose,
)
from dqpose.drivers.sim.piper import PiperSim
from dqpose.profile import Trapezoid
from tests._polling import wait_until
from tests.drivers._piper import ANG_Q, POS_Q, random_poses

# piper_sdk 0.6.2 still passes python-can's deprecated ``bustype``.
pytestmark = pytest.mark.filterwarnings("ignore:The 'bustype' argument is deprecated")


def _servo_along_x(arm, steps: int, step: float):
    """Streams ``steps`` set-points along x from the current pose, speeding up at 1 m/s^2 from
    rest to ``step`` metres per period; returns the start pose and its (q, t)."""
    start = arm.tool_pose()[1]
    q0, t0 = dq.to_pose(start)
    profile = Trapezoid(1.0, step / arm.period, 1.0)
    for k in range(1, steps + 1):
        arm.servo(dq.from_pose(q0, t0 + [profile(k * arm.period), 0, 0]))
    return start, q0, t0


def sdk_pose(ints):
    """Reference conversion of piper_sdk integers: SciPy static-axes 'xyz' = Rz Ry Rx."""
    x, y, z, rx, ry, rz = ints
    R = Rotation.from_euler("xyz", np.array([rx, ry, rz]) / 1000.0, degrees=True).as_matrix()
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = np.array([x, y, z]) / 1e6
    return dq.from_matrix(M)


def near(a, b, pos, ang):
    d, r = _delta(a, b)
    return d <= pos and r <= ang


@pytest.fixture
def channel():
    return f"piper-{uuid.uuid4().hex[:8]}"


@pytest.fixture
def bus_factory(channel):
    buses = []

    def make():
        b = can.Bus(interface="virtual", channel=channel)
        buses.append(b)
        return b
    yield make
    for b in buses:
        b.shutdown()


@pytest.fixture
def sim(bus_factory):
    s = PiperSim(bus_factory()).start()
    yield s
    s.close()


@pytest.fixture
def arm(sim, bus_factory):
    # generous timeouts: the test machine is shared and Python threads get starved
    a = PiperArm(bus_factory(), watchdog=0.2, stale_after=0.5)
    a.wait_for_feedback(2.0)
    yield a
    a.close()


@pytest.fixture
def sdk(channel):
    from piper_sdk import C_PiperInterface_V2
    p = C_PiperInterface_V2(channel, judge_flag=False, can_auto_init=False)
    p.CreateCanBus(channel, bustype="virtual", judge_flag=False)
    p.ConnectPort(can_init=False, piper_init=False, start_thread=True)
    yield p
    p.DisconnectPort()


# ---- against piper_sdk -------------------------------------------------------------------------
def test_our_frames_equal_piper_sdk_frames(sdk, bus_factory):
    listener = bus_factory()
    rng = np.random.default_rng(2)
    for _ in range(5):
        ints = [int(v) for v in rng.integers(-600_000, 600_000, 3)] + \
               [int(v) for v in rng.integers(-180_000, 180_001, 3)]
        speed = int(rng.integers(0, 101))
        sdk.MotionCtrl_2(0x01, 0x00, speed, 0x00)
        sdk.EndPoseCtrl(*ints)
        got = []
        while len(got) < 4:
            m = listener.recv(1.0)
            assert m is not None, "piper_sdk sent fewer frames than expected"
            got.append(m)
        assert bytes(got[0].data) == bytes(encode_motion_mode(MotionMode(1, 0, speed)).data)
        assert decode_motion_mode(got[0]) == MotionMode(1, 0, speed)
        ours = encode_end_pose(EndPose(*ints), END_POSE_CTRL)
        assert [(m.arbitration_id, bytes(m.data)) for m in got[1:]] == \
               [(m.arbitration_id, bytes(m.data)) for m in ours]
        asm = EndPoseAssembler(END_POSE_CTRL)
        assert [asm.feed(m) for m in got[1:]][-1] == EndPose(*ints)


def test_piper_sdk_reads_sim_end_pose(sdk, sim):
    rng = np.random.default_rng(3)
    for T in random_poses(rng, 5):
        sim.set_pose(T)
        want = pose_to_units(T).as_tuple()

        def read():
            e = sdk.GetArmEndPoseMsgs().end_pose
            got = (e.X_axis, e.Y_axis, e.Z_axis, e.RX_axis, e.RY_axis, e.RZ_axis)
            return got if got == want else None
        got = wait_until(read)
        assert got == want
        # The integers piper_sdk reports, read with SciPy's Rz Ry Rx, are the simulated pose.
        d, a = _delta(sdk_pose(got), T)
        assert d <= POS_Q and a <= ANG_Q


def test_sim_follows_piper_sdk_end_pose_ctrl(sdk, sim):
    target_ints = (250_000, -50_000, 200_000, 170_000, 10_000, -30_000)
    sdk.EndPoseCtrl(*target_ints)           # not in CAN command mode yet: ignored
    time.sleep(0.05)
    assert sim.target is None
    sdk.MotionCtrl_2(0x01, 0x00, 100, 0x00)
    sdk.EndPoseCtrl(*target_ints)
    target = sdk_pose(target_ints)
    assert wait_until(lambda: sim.target is not None)
    d, a = _delta(sim.target, target)
    assert d < 1e-9 and a < 1e-9
    assert wait_until(lambda: near(sim.pose, target, 1e-9, 1e-9), timeout=5.0)

    def sdk_sees_target():
        e = sdk.GetArmEndPoseMsgs().end_pose
        return (e.X_axis, e.Y_axis, e.Z_axis, e.RX_axis, e.RY_axis, e.RZ_axis) == target_ints
    assert wait_until(sdk_sees_target)


def test_sim_motion_is_rate_limited(sdk, sim):
    start = sim.pose
    sdk.MotionCtrl_2(0x01, 0x00, 20, 0x00)     # 20 % of 0.5 m/s
    target = dq.mul(dq.from_pose([1, 0, 0, 0], [0.0, 0.1, 0.0]), start)
    sdk.EndPoseCtrl(*pose_to_units(target).as_tuple())
    assert wait_until(lambda: sim.target is not None)
    t0 = time.monotonic()
    assert wait_until(lambda: _delta(sim.pose, target)[0] < 1e-6, timeout=5.0)
    # 0.1 m at 0.1 m/s cannot take less than a second (no upper bound: the machine may be slow)
    assert time.monotonic() - t0 > 0.8


def sdk_status(sdk):
    s = sdk.GetArmStatus().arm_status
    return (int(s.ctrl_mode), int(s.arm_status), int(s.mode_feed), int(s.teach_status),
            int(s.motion_status), int(s.trajectory_num), int(s.err_code))


def test_our_status_decoder_matches_piper_sdk(sdk, bus_factory):
    tx = bus_factory()
    rng = np.random.default_rng(6)
    for k in range(1, 9):
        # bytes piper_sdk has names for (it maps other values to UNKNOWN), err_code anything
        raw = bytes([rng.integers(0, 8), rng.integers(0, 16), rng.integers(0, 6),
                     rng.integers(0, 8), rng.integers(0, 2), k]) + \
            int(rng.integers(0, 1 << 16)).to_bytes(2, "big")
        msg = can.Message(arbitration_id=0x2A1, data=raw, is_extended_id=False)
        tx.send(msg)
        assert wait_until(lambda: sdk_status(sdk)[5] == k)
        ours = decode_arm_status(msg)
        assert sdk_status(sdk) == (ours.ctrl_mode, ours.arm_status, ours.mode_feed,
                                   ours.teach_status, ours.motion_status, ours.trajectory_num,
                                   ours.err_code)
        err = sdk.GetArmStatus().arm_status.err_status
        assert tuple(j for j in range(1, 7) if getattr(err, f"joint_{j}_angle_limit")) == \
            ours.angle_limit_joints
        assert tuple(j for j in range(1, 7)
                     if getattr(err, f"communication_status_joint_{j}")) == ours.comm_error_joints
        assert bytes(encode_arm_status(ours).data) == raw


def test_piper_sdk_reads_sim_status(sdk, sim):
    assert wait_until(lambda: sdk.GetArmStatus().time_stamp != 0)
    assert sdk_status(sdk)[:2] == (0x00, 0x00)      # standby, normal: no 0x151 yet
    # MOVE L at 20 % of 0.5 m/s: 0.05 m takes about half a second
    sdk.MotionCtrl_2(0x01, MOVE_L, 20, 0x00)
    target = dq.mul(dq.from_pose([1, 0, 0, 0], [0.0, 0.05, 0.0]), sim.pose)
    sdk.EndPoseCtrl(*pose_to_units(target).as_tuple())
    assert wait_until(lambda: sdk_status(sdk)[:5] == (0x01, 0x00, MOVE_L, 0x00, 0x01))
    assert wait_until(lambda: sdk_status(sdk)[4] == 0x00, timeout=5.0)
    assert _delta(sim.pose, target)[0] < 1e-6

    sim.collide()
    sim.set_joint_errors(angle_limit=(3,), communication=(5, 6))
    assert wait_until(lambda: sdk_status(sdk)[1] == 0x07)
    assert wait_until(lambda: sdk_status(sdk)[6] == 0x0430)
    err = sdk.GetArmStatus().arm_status.err_status
    assert err.joint_3_angle_limit and not err.joint_2_angle_limit
    assert err.communication_status_joint_5 and err.communication_status_joint_6
    assert not err.communication_status_joint_3
    sim.emergency_stop()
    assert wait_until(lambda: sdk_status(sdk)[1] == 0x01)
    sim.clear_faults()
    assert wait_until(lambda: sdk_status(sdk)[1] == 0x00 and sdk_status(sdk)[6] == 0)


def test_arm_and_piper_sdk_decode_the_same_feedback(sdk, arm, sim):
    rng = np.random.default_rng(4)
    for T in random_poses(rng, 3):
        sim.set_pose(T)
        want = pose_to_units(T).as_tuple()
        wait_until(lambda: (lambda e: (e.X_axis, e.Y_axis, e.Z_axis, e.RX_axis, e.RY_axis,
                                       e.RZ_axis))(sdk.GetArmEndPoseMsgs().end_pose) == want)
        assert wait_until(lambda: near(arm.tool_pose()[1], sdk_pose(want), 1e-12, 1e-9))


def test_arm_commands_are_what_piper_sdk_decodes(sdk, arm, sim):
    before = sdk.GetArmCtrlCode151().time_stamp
    T = dq.mul(dq.from_pose([1, 0, 0, 0], [0.00001, 0, 0]), sim.pose)   # within the limits
    arm.servo(T)
    assert wait_until(lambda: sdk.GetArmCtrlCode151().time_stamp != before)
    ctrl = sdk.GetArmCtrlCode151().ctrl_151
    assert (ctrl.ctrl_mode, ctrl.move_mode, ctrl.move_spd_rate_ctrl, ctrl.mit_mode) == \
        (0x01, 0x00, 100, 0x00)


# ---- our driver against our simulator ----------------------------------------------------------
def test_tool_pose_matches_sim(arm, sim):
    t, T = arm.tool_pose()
    assert abs(t - time.time()) < 5.0
    d, a = _delta(T, sim.pose)
    assert d <= POS_Q and a <= ANG_Q
    assert arm.status().ok


def test_move_reaches_target_and_blocks(arm, sim):
    target = dq_from_xyz_sxyz([0.25, 0.05, 0.25], [math.pi - 0.3, 0.15, 0.4])
    arm.move(target, speed=0.2, accel=1.0)
    d, a = _delta(arm.tool_pose()[1], target)
    assert d <= arm.position_tolerance and a <= arm.angle_tolerance
    d, a = _delta(sim.pose, target)
    assert d <= arm.position_tolerance + 1e-6 and a <= arm.angle_tolerance + 1e-6


def test_servo_follows_path(arm, sim):
    start = arm.tool_pose()[1]
    q0, t0 = dq.to_pose(start)
    profile = Trapezoid(0.04, 0.06, 0.5)     # ~0.8 s at 200 Hz, 0.06 m/s along y
    lags = []
    n = int(math.ceil(profile.duration / arm.period))
    for k in range(1, n + 1):
        sp = dq.from_pose(q0, t0 + [0.0, profile(k * arm.period), 0.0])
        arm.servo(sp)                         # returns once the period is over
        lags.append(_delta(sim.pose, sp)[0])
    final = dq.from_pose(q0, t0 + [0.0, 0.04, 0.0])
    assert wait_until(lambda: _delta(sim.pose, final)[0] < 1e-5)
    # The sim never strays from the straight line it was asked to follow.
    assert max(lags) < 0.01


def test_servo_refuses_jumps_and_bad_input(arm, sim):
    # the over-limit policy itself is tested against both arms in test_arm_limits.py
    start = arm.tool_pose()[1]
    q0, t0 = dq.to_pose(start)
    with pytest.raises(LimitError, match="limits.max_linear_step"):
        arm.servo(dq.from_pose(q0, t0 + [0.1, 0, 0]))
    with pytest.raises(LimitError, match="outside limits.workspace"):
        arm.servo(dq.from_pose(q0, [2.0, 0, 0]))
    assert not any(k == "end_pose" and _delta(units_to_pose(v), start)[0] > 1e-5
                   for _, k, v in sim.log)
    with pytest.raises(ValueError, match="pose: quaternion norm"):
        arm.servo(np.array([2.0, 0, 0, 0, 0, 0, 0, 0]))
    with pytest.raises(ValueError, match="pose: expected"):
        arm.servo(np.zeros(6))
    with pytest.raises(ValueError, match="speed"):
        arm.move(start, speed=10.0, accel=1.0)
    with pytest.raises(ValueError, match="accel"):
        arm.move(start, speed=0.1, accel=-1.0)


def test_watchdog_holds_on_stalled_stream(arm, sim):
    start, q0, t0 = _servo_along_x(arm, 19, 0.0004)
    # the caller stalls: no more set-points
    assert wait_until(lambda: arm.status().extra["watchdog_stops"] >= 1)
    held = sim.target
    measured = sim.pose
    assert held is not None and _delta(held, measured)[0] < 0.005
    time.sleep(0.05)
    assert _delta(sim.target, held) == (0.0, 0.0)


def test_move_times_out_and_can_be_stopped(arm, sim):
    sim.max_speed = 0.01            # a sluggish arm
    start = arm.tool_pose()[1]
    q0, t0 = dq.to_pose(start)
    far = dq.from_pose(q0, t0 + [0.05, 0, 0])
    with pytest.raises(ArmError, match="not reached within 0.30 s"):
        arm.move(far, speed=0.2, accel=1.0, timeout=0.3)
    import threading
    threading.Timer(0.1, arm.stop).start()
    with pytest.raises(ArmError, match="stopped"):
        arm.move(start, speed=0.2, accel=1.0, timeout=5.0)


def test_stop_ends_motion(arm, sim):
    start, q0, t0 = _servo_along_x(arm, 9, 0.0005)
    arm.stop()
    held = arm._held                # the measured pose stop() commanded
    # wait for the hold command itself, not merely for the arm to reach the last servo target
    assert wait_until(lambda: _delta(sim.target, held)[0] < 1e-5)
    assert wait_until(lambda: _delta(sim.pose, sim.target)[0] < 1e-6)
    p = sim.pose
    time.sleep(0.05)
    assert _delta(sim.pose, p)[0] < 1e-6


def test_stale_feedback_is_reported(arm, sim):
    sim.pause_feedback()
    assert wait_until(lambda: not arm.status().connected)
    st = arm.status()
    assert not st.ok and "stale" in st.error
    with pytest.raises(ArmError, match="stale"):
        arm.tool_pose()
    with pytest.raises(ArmError, match="stale"):
        arm.servo(sim.pose)
    sim.pause_feedback(False)
    assert wait_until(lambda: arm.status().connected)


def test_no_feedback_fails_fast(bus_factory):
    with PiperArm(bus_factory()) as arm:
        with pytest.raises(ArmError, match="no end-pose feedback"):
            arm.wait_for_feedback(0.2)
        assert "no end-pose feedback" in arm.status().error


def test_malformed_frames_counted_and_skipped(arm, sim, bus_factory):
    rogue = bus_factory()
    bad = [
        can.Message(arbitration_id=0x2A2, data=b"\x01\x02", is_extended_id=False),
        can.Message(arbitration_id=0x2A3, data=b"\x00" * 8, is_extended_id=True),
        can.Message(arbitration_id=0x2AB, data=b"\x00" * 8, is_extended_id=False),
        can.Message(arbitration_id=0x2A4, data=struct.pack(">ii", 500_000, 0),
                    is_extended_id=False),
        can.Message(arbitration_id=0x2A2, is_remote_frame=True, dlc=8, is_extended_id=False),
        # commands for the sim
        can.Message(arbitration_id=0x152, data=b"\x00" * 3, is_extended_id=False),
        can.Message(arbitration_id=0x151, data=bytes([1, 0, 200, 0, 0, 0, 0, 0]),
                    is_extended_id=False),
    ]
    for m in bad:
        rogue.send(m)
    want = {"dlc": 1, "extended_id": 1, "unknown_id": 1, "value": 1, "remote_frame": 1}
    assert wait_until(lambda: arm.status().extra["malformed"] == want)
    assert wait_until(lambda: dict(sim.malformed) == {"dlc": 1, "value": 1})
    assert sim.target is None and sim.mode is None
    # and the driver keeps decoding good feedback
    T = random_poses(np.random.default_rng(5), 1)[0]
    sim.set_pose(T)
    assert wait_until(lambda: near(arm.tool_pose()[1], T, POS_Q, ANG_Q))
    assert arm.status().ok


# ---- arm status (0x2A1) through the driver -----------------------------------------------------
def end_poses(sim):
    return [v for _, k, v in sim.log if k == "end_pose"]


def test_status_extra_follows_the_arm(arm, sim):
    st = arm.status()
    assert st.ok and st.extra["arm_status"] == 0 and st.extra["err_code"] == 0
    start = arm.tool_pose()[1]
    target = dq.mul(dq.from_pose([1, 0, 0, 0], [0.0, 0.0, 0.01]), start)
    arm.move(target, speed=0.1, accel=1.0)
    assert wait_until(lambda: arm.status().extra["motion_status"] == 0x00)
    st = arm.status()
    assert (st.extra["ctrl_mode"], st.extra["mode_feed"]) == (0x01, MOVE_P)


def test_emergency_stop_reported_and_commands_refused(arm, sim):
    start, q0, t0 = _servo_along_x(arm, 4, 0.0004)
    sim.emergency_stop()
    assert wait_until(lambda: arm.status().emergency_stop, timeout=0.5)
    st = arm.status()
    assert st.connected and not st.ok and not st.protective_stop
    assert st.error == "emergency stop (arm_status 0x01)"
    sent = len(end_poses(sim))
    here = arm.tool_pose()[1]
    with pytest.raises(ArmError, match=r"servo: not sent, the PiPER reports emergency stop"):
        arm.servo(here)
    time.sleep(arm.watchdog + 0.05)   # the stop ended the stream: no watchdog hold either
    assert len(end_poses(sim)) == sent and arm.status().extra["watchdog_stops"] == 0
    with pytest.raises(ArmError, match=r"move: not sent, the PiPER reports emergency stop"):
        arm.move(dq.from_pose(q0, t0), speed=0.1, accel=1.0)
    assert len(end_poses(sim)) == sent

    sim.clear_faults()
    assert wait_until(lambda: arm.status().ok)
    modes = sum(1 for _, k, _ in sim.log if k == "mode")
    arm.move(dq.from_pose(q0, t0), speed=0.1, accel=1.0)
    assert _delta(sim.pose, dq.from_pose(q0, t0))[0] <= arm.position_tolerance + 1e-6
    # the motion mode is selected again after a stop
    assert sum(1 for _, k, _ in sim.log if k == "mode") == modes + 1


def test_collision_and_joint_errors_reported(arm, sim):
    sim.collide()
    sim.set_joint_errors(angle_limit=(3,))
    assert wait_until(lambda: arm.status().extra.get("err_code") == 0x0400, timeout=0.5)
    st = arm.status()
    assert st.protective_stop and not st.emergency_stop and not st.ok
    assert st.error == "collision (arm_status 0x07); joint 3 angle over limit (err_code 0x0400)"
    with pytest.raises(ArmError, match="collision.*joint 3 angle over limit"):
        arm.servo(arm.tool_pose()[1])
    sim.inject_status(0x00, 0x0010)    # joint errors alone are a protective stop too
    assert wait_until(lambda: arm.status().error == "joint 5 communication error "
                      "(err_code 0x0010)")
    assert arm.status().protective_stop
    sim.clear_faults()
    assert wait_until(lambda: arm.status().ok)
    q0, t0 = dq.to_pose(arm.tool_pose()[1])
    arm.servo(dq.from_pose(q0, t0 + [0.00001, 0, 0]))
    assert wait_until(lambda: sim.target is not None)


def test_running_move_ends_on_collision(arm, sim):
    sim.max_speed = 0.02            # a 0.05 m move takes a few seconds
    q0, t0 = dq.to_pose(arm.tool_pose()[1])
    import threading
    threading.Timer(0.15, sim.collide).start()
    with pytest.raises(ArmError, match=r"move: not sent, the PiPER reports collision"):
        arm.move(dq.from_pose(q0, t0 + [0.05, 0, 0]), speed=0.2, accel=1.0, timeout=5.0)
    # a frame sent just before the collision was seen may still be on the (multicast) bus: let
    # the count settle, then nothing more may arrive; a driver still streaming never settles
    def settled(quiet=0.1):
        before = len(end_poses(sim))
        time.sleep(quiet)
        return len(end_poses(sim)) == before
    assert wait_until(settled, timeout=2.0)
    sent = len(end_poses(sim))
    time.sleep(0.2)
    assert len(end_poses(sim)) == sent
    assert sim.target is None


def test_stale_status_counts_as_disconnected(arm, sim):
    sim.pause_status()
    assert wait_until(lambda: not arm.status().connected)
    st = arm.status()
    assert "arm status feedback (0x2A1) is stale" in st.error
    arm.tool_pose()     # the pose itself is still fresh
    with pytest.raises(ArmError, match=r"0x2A1\) is stale"):
        arm.servo(sim.pose)
    sim.pause_status(False)
    assert wait_until(lambda: arm.status().ok)


def test_no_status_fails_fast(sim, bus_factory):
    sim.pause_status()
    with PiperArm(bus_factory()) as arm:
        with pytest.raises(ArmError, match=r"no arm status feedback \(0x2A1\)"):
            arm.wait_for_feedback(0.2)
        assert "no arm status feedback" in arm.status().error


def test_malformed_status_frames_counted_and_skipped(arm, sim, bus_factory):
    rogue = bus_factory()
    # an emergency stop in a 7-byte frame is not a frame, and must not read as one
    rogue.send(can.Message(arbitration_id=0x2A1, data=bytes([1, 1, 0, 0, 0, 0, 0]),
                           is_extended_id=False))
    rogue.send(can.Message(arbitration_id=0x2A1, data=bytes([1, 1, 0, 0, 0, 0, 0, 0]),
                           is_extended_id=True))
    assert wait_until(lambda: arm.status().extra["malformed"] == {"dlc": 1, "extended_id": 1})
    assert arm.status().ok and not arm.status().emergency_stop
    sim.emergency_stop()            # and well-formed reports still get through
    assert wait_until(lambda: arm.status().emergency_stop)


def test_measure_is_the_tool_pose_with_its_time_and_covariance(arm, sim):
    m = arm.measure()
    assert m.source == "piper"
    assert abs(m.time - time.time()) < 5.0
    d, a = _delta(m.pose, sim.pose)
    assert d <= POS_Q and a <= ANG_Q
    rs, ts = PiperArm.pose_sigma
    assert np.allclose(m.covariance, np.diag([rs * rs] * 3 + [ts * ts] * 3))
