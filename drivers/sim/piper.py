"""A simulated AgileX PiPER on any ``python-can`` bus.

Publishes end-pose feedback (0x2A2-0x2A4) and arm status (0x2A1) at ``rate`` and follows
end-pose commands
(0x152-0x154, applied when the 0x154 frame of a complete set arrives) while the last 0x151 frame
selected CAN command mode with MOVE P or MOVE L. The motion model moves the tool straight towards
the target at ``max_speed * speed_percent / 100`` (rotation by slerp at the same fraction of
``max_angular_speed``), so it lags like the real arm instead of jumping. Malformed frames are
counted and skipped.

The status frame reports the control and move mode of the last 0x151 (standby and MOVE P before
any), motion status "not reached" while the tool is short of its target, and whatever stop or
fault a test injected (``emergency_stop``, ``collide``, ``set_joint_errors``, ``inject_status``).
While a stop or fault stands the arm halts where it is, drops its target and ignores end-pose
commands; ``clear_faults`` ends it, and the arm then waits for a new target.

From the shell: ``dqpose sim piper`` (or ``python -m dqpose.drivers.sim.piper``) serves on
python-can's ``udp_multicast`` interface, group ``239.74.163.2``: a bus that crosses processes on
one machine without root or a CAN adapter (hop limit 1, so frames stay on the local link), reached
with ``drivers.open_arm("piper:udp_multicast:239.74.163.2")``. On a CAN adapter or a ``vcan``
device: ``--interface socketcan --channel can0``. :class:`PiperSimProcess` runs it from Python.
"""
from __future__ import annotations

import argparse
import math
import signal
import sys
import threading
import time
from collections import Counter
from typing import Optional, Sequence

import can
import numpy as np

from dqpose import dq
from dqpose.drivers.base import pose_delta, tool_line
from dqpose.drivers.euler import dq_from_xyz_sxyz
from dqpose.drivers.piper_can import (
    ARM_COLLISION,
    ARM_EMERGENCY_STOP,
    ARM_NORMAL,
    COMMAND_BLOCK,
    CTRL_MODE_CAN,
    END_POSE_CTRL,
    END_POSE_FEEDBACK,
    MOTION_CTRL_2,
    MOVE_L,
    MOVE_P,
    EndPoseAssembler,
    FrameError,
    MotionMode,
    StatusReport,
    decode_motion_mode,
    encode_arm_status,
    encode_end_pose,
    pose_to_units,
    units_to_pose,
)
from dqpose.drivers.sim import end_process, start_process, stop_when_orphaned

__all__ = ["PiperSim", "PiperSimProcess", "HOME", "DEFAULT_INTERFACE", "DEFAULT_CHANNEL", "main",
           "add_arguments", "run"]

#: python-can's multicast-over-UDP bus: reaches every process on this machine, needs no root
DEFAULT_INTERFACE, DEFAULT_CHANNEL = "udp_multicast", "239.74.163.2"

#: a reachable tool pose, pointing down: 0.2 m forward, 0.3 m up
HOME = dq_from_xyz_sxyz([0.2, 0.0, 0.3], [math.pi, 0.0, 0.0])


class PiperSim:
    """The simulated arm; ``start()`` runs it in a thread, ``close()`` stops it.

    Test hooks: ``set_pose``, ``pose``, ``target``, ``mode``, ``pause_feedback``, ``log`` (the
    decoded commands, newest last), ``malformed`` (counts by reason), ``status_report`` (what the
    next 0x2A1 will say), ``pause_status``, ``drop`` (command frames lost on the way, counted in
    ``dropped``), ``restart`` (the arm powered off and on), ``max_speed`` (slow it down: an arm
    that falls behind) and the fault injectors ``emergency_stop``, ``collide``,
    ``set_joint_errors``, ``inject_status`` and ``clear_faults``.
    """

    def __init__(self, bus: can.BusABC, *, rate: float = 200.0, pose=HOME,
                 max_speed: float = 0.5, max_angular_speed: float = math.radians(180)):
        if not (math.isfinite(rate) and 0 < rate <= 2000):
            raise ValueError(f"rate: must be within (0, 2000] Hz, got {rate!r}")
        self.bus = bus
        self.rate = float(rate)
        self.max_speed = float(max_speed)
        self.max_angular_speed = float(max_angular_speed)
        self._lock = threading.Lock()
        self._pose = dq.normalize(np.asarray(pose, dtype=float))
        self._target: Optional[np.ndarray] = None
        self.mode: Optional[MotionMode] = None
        self._arm_status = ARM_NORMAL
        self._err_code = 0
        self._assembler = EndPoseAssembler(END_POSE_CTRL)
        self.malformed: Counter = Counter()
        self.log: list[tuple[float, str, object]] = []
        #: CLOCK_MONOTONIC when each complete end-pose command arrived (its 0x154 frame), to
        #: measure a command stream's period at the arm's side
        self.arrivals: list[float] = []
        self.dropped: Counter = Counter()      # command frames lost (drop), by id
        self._drops: list[list] = []           # [ids, until (monotonic), frames left]
        self.feedback_enabled = threading.Event()
        self.feedback_enabled.set()
        self.status_enabled = threading.Event()
        self.status_enabled.set()
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None

    # ---- test hooks ------------------------------------------------------------------------------
    @property
    def pose(self) -> np.ndarray:
        with self._lock:
            return self._pose.copy()

    @property
    def target(self) -> Optional[np.ndarray]:
        with self._lock:
            return None if self._target is None else self._target.copy()

    def set_pose(self, pose) -> None:
        """Teleport the tool (and drop any target), as if moved by hand."""
        with self._lock:
            self._pose = dq.normalize(np.asarray(pose, dtype=float))
            self._target = None

    def pause_feedback(self, paused: bool = True) -> None:
        """Stop (or resume) publishing feedback, like an arm whose bus link died."""
        if paused:
            self.feedback_enabled.clear()
        else:
            self.feedback_enabled.set()

    def drop(self, ids=None, seconds: Optional[float] = None,
             count: Optional[int] = None) -> None:
        """Lose the command frames with these ids (default: every command frame) that arrive
        within ``seconds`` from now, or the next ``count`` of them (either or both; neither:
        until ``undrop()``), as a bus that corrupts or loses frames would."""
        ids = frozenset(COMMAND_BLOCK if ids is None else
                        ([ids] if isinstance(ids, int) else ids))
        until = math.inf if seconds is None else time.monotonic() + float(seconds)
        left = math.inf if count is None else int(count)
        with self._lock:
            self._drops = [r for r in self._drops if r[1] > time.monotonic() and r[2] > 0]
            self._drops.append([ids, until, left])

    def undrop(self) -> None:
        """Frames arrive again."""
        with self._lock:
            self._drops = []

    def _lost(self, i: int) -> bool:
        with self._lock:
            now = time.monotonic()
            for rule in self._drops:
                if i in rule[0] and now < rule[1] and rule[2] > 0:
                    rule[2] -= 1
                    self.dropped[i] += 1
                    return True
        return False

    def restart(self) -> None:
        """Power cycle: the arm forgets its motion mode (standby) and its target, and stays
        where it is."""
        with self._lock:
            self.mode = None
            self._target = None
            self._assembler = EndPoseAssembler(END_POSE_CTRL)

    def pause_status(self, paused: bool = True) -> None:
        """Stop (or resume) publishing 0x2A1 only, the pose feedback going on."""
        if paused:
            self.status_enabled.clear()
        else:
            self.status_enabled.set()

    def inject_status(self, arm_status: int, err_code: int = 0) -> None:
        """Report ``arm_status`` and ``err_code`` from now on (any non-zero value halts the arm)."""
        if not 0 <= int(arm_status) <= 255:
            raise ValueError(f"arm_status: {arm_status} does not fit in one byte")
        if not 0 <= int(err_code) <= 0xFFFF:
            raise ValueError(f"err_code: {err_code} does not fit in 16 bits")
        with self._lock:
            self._arm_status, self._err_code = int(arm_status), int(err_code)
            if self._stopped():
                self._target = None

    def emergency_stop(self) -> None:
        self.inject_status(ARM_EMERGENCY_STOP, self._err_code)

    def collide(self) -> None:
        self.inject_status(ARM_COLLISION, self._err_code)

    def set_joint_errors(self, angle_limit: Sequence[int] = (),
                         communication: Sequence[int] = ()) -> None:
        """Flag joints (1-6) beyond their angle limit and joints with a communication error."""
        code = 0
        for name, joints, shift in (("angle_limit", angle_limit, 8),
                                    ("communication", communication, 0)):
            for j in joints:
                if not 1 <= int(j) <= 6:
                    raise ValueError(f"{name}: joint {j} is not one of 1..6")
                code |= 1 << (shift + int(j) - 1)
        self.inject_status(self._arm_status, code)

    def clear_faults(self) -> None:
        self.inject_status(ARM_NORMAL, 0)

    def _stopped(self) -> bool:
        return self._arm_status != ARM_NORMAL or self._err_code != 0

    @property
    def status_report(self) -> StatusReport:
        with self._lock:
            m = self.mode
            # step() lands exactly on the target, so equality is "reached"
            moving = self._target is not None and not np.array_equal(self._pose, self._target)
            return StatusReport(ctrl_mode=m.ctrl_mode if m else 0x00,
                                arm_status=self._arm_status,
                                mode_feed=m.move_mode if m else MOVE_P,
                                motion_status=0x01 if moving else 0x00,
                                err_code=self._err_code)

    # ---- protocol --------------------------------------------------------------------------------
    def handle(self, msg: can.Message, arrived: Optional[float] = None) -> None:
        """Apply one frame; ``arrived`` is when it was received (monotonic; default now)."""
        i = msg.arbitration_id
        if i not in COMMAND_BLOCK or (self._drops and self._lost(i)):
            return
        try:
            if i == MOTION_CTRL_2:
                mode = decode_motion_mode(msg)
                with self._lock:
                    self.mode = mode
                self.log.append((time.time(), "mode", mode))
            elif i in END_POSE_CTRL:
                ep = self._assembler.feed(msg)
                if ep is not None:
                    self.arrivals.append(time.monotonic() if arrived is None else arrived)
                    self.log.append((time.time(), "end_pose", ep))
                    with self._lock:
                        if self._following() and not self._stopped():
                            self._target = units_to_pose(ep)
        except FrameError as e:
            self.malformed[e.reason] += 1

    def _following(self) -> bool:
        m = self.mode
        return m is not None and m.ctrl_mode == CTRL_MODE_CAN and m.move_mode in (MOVE_P, MOVE_L)

    def step(self, dt: float) -> None:
        """Advance the motion model by ``dt`` seconds."""
        with self._lock:
            if self._target is None or not self._following() or self._stopped():
                return
            frac = self.mode.speed_percent / 100.0
            dist, ang = pose_delta(self._pose, self._target)
            f = 1.0
            if dist > 0:
                f = min(f, self.max_speed * frac * dt / dist)
            if ang > 0:
                f = min(f, self.max_angular_speed * frac * dt / ang)
            self._pose = self._target.copy() if f >= 1.0 else \
                dq.normalize(tool_line(self._pose, self._target, f))

    def publish(self) -> None:
        for m in encode_end_pose(pose_to_units(self.pose), END_POSE_FEEDBACK):
            self.bus.send(m)
        if self.status_enabled.is_set():
            self.bus.send(encode_arm_status(self.status_report))

    def _run(self) -> None:
        next_tick = time.monotonic()
        last = next_tick
        while not self._stop.is_set():
            period = 1.0 / self.rate    # read each tick: a test slows the bus down by degrees
            now = time.monotonic()
            self.step(now - last)
            last = now
            if self.feedback_enabled.is_set():
                try:
                    self.publish()
                except (can.CanError, OSError):
                    pass  # a full or closed bus drops feedback, as on hardware
            next_tick += period
            if next_tick - time.monotonic() < -period:   # fell behind (loaded machine): no burst
                next_tick = time.monotonic()
            # Wait for the next tick on the bus, so a command is taken (and stamped) when it
            # arrives rather than up to a period late.
            while not self._stop.is_set():
                delay = next_tick - time.monotonic()
                try:
                    msg = self.bus.recv(timeout=max(0.0, delay))
                except (can.CanError, OSError):
                    msg = None
                if msg is not None:
                    self.handle(msg, time.monotonic())
                elif delay <= 0:
                    break

    def start(self) -> "PiperSim":
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="piper-sim", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            self._thread = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--interface", default=DEFAULT_INTERFACE,
                   help="python-can interface: udp_multicast (crosses processes on this machine), "
                        "socketcan (a CAN adapter or vcan), virtual (this process only), ... "
                        "(default %(default)s)")
    p.add_argument("--channel", default=DEFAULT_CHANNEL,
                   help="the interface's channel: a multicast group for udp_multicast, a device "
                        "such as can0 for socketcan (default %(default)s)")
    p.add_argument("--rate", type=float, default=200.0, help="feedback rate in Hz (default 200)")
    p.add_argument("--duration", type=float, default=None,
                   help="stop after this many seconds (default: until Ctrl-C)")
    p.add_argument("--exit-with-parent", action="store_true",
                   help="stop when the process that started this one ends (even if killed)")


def _hint(interface: str) -> str:
    if interface == "socketcan":
        return ("; a CAN adapter must be up (ip link set can0 up type can bitrate 1000000), or "
                "make a virtual one as root: modprobe vcan && ip link add dev vcan0 type vcan && "
                "ip link set up vcan0; without root use the default --interface udp_multicast")
    if interface == "udp_multicast":
        return "; python-can's udp_multicast needs the msgpack package (pip install msgpack)"
    return ""


def run(args: argparse.Namespace) -> int:
    try:
        bus = can.Bus(interface=args.interface, channel=args.channel)
    except (can.CanError, OSError, ValueError, ImportError) as e:
        print(f"dqpose sim piper: cannot open python-can {args.interface} channel "
              f"{args.channel!r}: {e}{_hint(args.interface)}", file=sys.stderr)
        return 2
    sim = PiperSim(bus, rate=args.rate)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    if args.exit_with_parent:
        stop_when_orphaned(stop)
    print(f"simulated PiPER on {args.interface}:{args.channel}, feedback at {args.rate:g} Hz; "
          f"drivers.open_arm('piper:{args.interface}:{args.channel}')", flush=True)
    try:
        sim.start()
        end = math.inf if args.duration is None else time.monotonic() + args.duration
        while time.monotonic() < end and not stop.is_set():
            stop.wait(min(0.2, max(0.0, end - time.monotonic())))
    except KeyboardInterrupt:
        pass
    finally:
        sim.close()
        bus.shutdown()
    return 0


class PiperSimProcess:
    """``dqpose sim piper`` in its own process (so another process, e.g. the server, shares its
    bus), stopped by ``close()`` or when this process ends. ``spec`` is its ``open_arm`` name."""

    def __init__(self, interface: str = DEFAULT_INTERFACE, channel: str = DEFAULT_CHANNEL, *,
                 args: tuple = (), timeout: float = 10.0):
        self.interface, self.channel = interface, channel
        self.spec = f"piper:{interface}:{channel}"
        self.proc = start_process("dqpose.drivers.sim.piper", "--interface", interface, "--channel",
                                  channel, *args)
        self.pid = self.proc.pid
        # The first line is printed once the bus is open; a failure ends the process instead.
        if self.proc.first_line(timeout) is None:
            if self.proc.poll() is None:
                self.proc.kill()
            self.proc.wait()
            err = self.proc.stderr_tail()
            end_process(self.proc)
            raise RuntimeError(f"could not start the PiPER simulator on {interface}:{channel}: "
                               f"{err or f'no answer within {timeout:g} s'}")

    def close(self) -> None:
        end_process(self.proc)

    def __enter__(self) -> "PiperSimProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def main(argv: Optional[Sequence[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="dqpose sim piper", description=__doc__.split("\n\n")[0])
    add_arguments(p)
    return run(p.parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
