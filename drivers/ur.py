"""Universal Robots arms through ``ur_rtde`` (pinned to 1.6.5): :class:`URArm`.

Poses cross the interface as dual quaternions ``T_base_tool``; the controller speaks
``[x, y, z, rx, ry, rz]`` (metres, rotation vector), converted by :mod:`drivers.rotvec`.

Safety, enforced here and not left to the caller: every set-point is checked against the
:class:`~drivers.base.Limits` as every arm checks them and refused (the arm is stopped,
:class:`~drivers.base.LimitError` raised) rather than jumped to; a watchdog stops servoing
when ``servo()`` calls stall; a monitor notices a lost controller (``isConnected()`` false, or
data timestamps that stopped advancing while the receive side keeps returning the last pose) and
protective or emergency stops, and every later command raises :class:`~drivers.base.ArmError`.

By name: ``drivers.open_arm("ur:192.168.1.10", limits=...)``.
"""
from __future__ import annotations

import datetime
import math
import numbers
import os
import socket
import threading
import time
from typing import Optional

import numpy as np

from drivers.base import Arm, ArmError, ArmState, LimitError, Limits, Pacer, unit_pose
from drivers.rotvec import pose_from_rotvec, rotvec_from_pose, rotvec_from_quat
from drivers.rtde import DASHBOARD_PORT, RTDE_PORT, SCRIPT_PORT, request_version
from service import dq

CB3_MAJOR = 3
_RECEIVE_VARIABLES = ["timestamp", "actual_TCP_pose", "actual_TCP_speed", "runtime_state",
                      "robot_mode",
                      "safety_mode", "robot_status_bits", "safety_status_bits"]


def _probe(host: str, port: int, timeout: float) -> None:
    try:
        socket.create_connection((host, port), timeout=timeout).close()
    except OSError as e:
        raise ArmError(f"host: cannot reach a UR controller at {host}:{port} within "
                       f"{timeout:g} s ({e})") from None


def _rtde_connections(host: str) -> list[socket.socket]:
    """This process's TCP sockets connected to ``host``'s RTDE port, each on a duplicate of its
    descriptor (the caller closes them); empty where /proc/self/fd does not exist (Linux only)."""
    try:
        fds = os.listdir("/proc/self/fd")
        addresses = {a[4][0] for a in socket.getaddrinfo(host, RTDE_PORT, type=socket.SOCK_STREAM)}
    except OSError:
        return []
    out = []
    for fd in fds:
        try:
            if not os.readlink(f"/proc/self/fd/{fd}").startswith("socket:"):
                continue
            dup = os.dup(int(fd))
        except (OSError, ValueError):
            continue                            # gone meanwhile
        try:
            s = socket.socket(fileno=dup)
        except OSError:
            os.close(dup)                       # closed and reused by something else meanwhile
            continue
        try:
            if s.type == socket.SOCK_STREAM and s.family in (socket.AF_INET, socket.AF_INET6):
                peer = s.getpeername()
                if peer[1] == RTDE_PORT and peer[0] in addresses:
                    out.append(s)
                    continue
        except OSError:
            pass                                # not connected
        s.close()
    return out


def _restore_nodelay(host: str) -> int:
    """Turn Nagle's algorithm off again on this process's RTDE connections to ``host``; returns
    how many sockets were set.

    ur_rtde 1.6.5 sets ``TCP_NODELAY`` (and ``TCP_QUICKACK``) on each socket and then lets
    ``boost::asio::connect`` close it and open a new one, which has neither. With Nagle on, a
    command written while the previous one is not yet acknowledged waits for the controller's
    acknowledgement, which rides on its next data package: measured on the simulator, a
    ``servoStop`` issued mid-period left 0-2 ms later (one data cycle), and a set-point could
    wait the same way. Socket options belong to the socket, so setting them through a
    duplicate of the descriptor reaches ur_rtde's. Linux only; elsewhere nothing is changed."""
    socks = _rtde_connections(host)
    for s in socks:
        with s:
            s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return len(socks)


class URArm(Arm):
    """A UR arm (CB3 or e-series) commanded in tool space through ``ur_rtde``.

    ``frequency`` defaults to the controller's (500 Hz e-series, 125 Hz CB3). The keys of
    :data:`drivers.spec.ARM_KEYS` (``options``): ``watchdog`` is how long ``servo()`` may stall
    before the arm is stopped (``watchdog_periods``, the older way, counts it in periods);
    ``stale_after`` is how long (s) data timestamps may stand still before the controller counts
    as lost; ``connect_timeout`` bounds the reachability probe (``ur_rtde``'s own constructor
    has no timeout, so the ports are probed first) and the wait for the first data.
    """

    name = "ur"
    #: UR e-series pose repeatability +-0.03 mm (UR3e/5e; 3 sigma): 1e-5 m, and 1e-4 rad, the
    #: same displacement at a 0.1 m tool lever. See :attr:`Arm.pose_sigma`.
    pose_sigma = (1e-4, 1e-5)

    @classmethod
    def open(cls, channel: str, **kwargs) -> "URArm":
        """``drivers.open_arm("ur:<channel>")``: the channel is the controller's host."""
        return cls(channel, **kwargs)

    def __init__(self, host: str, frequency: Optional[float] = None, *,
                 limits: Optional[Limits] = None, lookahead: float = 0.1, gain: float = 300.0,
                 stop_decel: float = 10.0, watchdog_periods: Optional[int] = None, **options):
        if not isinstance(host, str) or not host:
            raise ValueError(f"host: expected a host name or address, got {host!r}")
        if frequency is not None and not (math.isfinite(frequency) and 0 < frequency <= 500):
            raise ValueError(f"frequency: must be within (0, 500] Hz, got {frequency!r}")
        if not 0.03 <= lookahead <= 0.2:
            raise ValueError(f"lookahead: must be within [0.03, 0.2] s, got {lookahead!r}")
        if not 100 <= gain <= 2000:
            raise ValueError(f"gain: must be within [100, 2000], got {gain!r}")
        if not (isinstance(stop_decel, numbers.Real) and math.isfinite(stop_decel)
                and stop_decel > 0):
            raise ValueError(f"stop_decel: must be a positive number, got {stop_decel!r}")
        if watchdog_periods is not None and (int(watchdog_periods) != watchdog_periods
                                             or watchdog_periods < 1):
            raise ValueError(f"watchdog_periods: must be a whole number >= 1, got {watchdog_periods!r}")
        if limits is not None and not isinstance(limits, Limits):
            raise ValueError(f"limits: expected a drivers.base.Limits, got {type(limits).__name__}")
        self._set_options("ur", options)
        connect_timeout = self.connect_timeout
        self.host, self.limits = host, limits or Limits()
        self.lookahead, self.gain, self.stop_decel = float(lookahead), float(gain), float(stop_decel)

        for port in (RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT):
            _probe(host, port, connect_timeout)
        try:
            self.version = tuple(request_version(host, RTDE_PORT, connect_timeout))
        except OSError as e:
            raise ArmError(f"host: {host}:{RTDE_PORT} does not answer as a UR controller ({e})") from None
        self.frequency = float(frequency or (500.0 if self.version[0] > CB3_MAJOR else 125.0))
        self.period = 1.0 / self.frequency
        if watchdog_periods is not None:
            self.watchdog = self.options["watchdog"] = watchdog_periods * self.period
        self._pacer = Pacer(self.period)

        import rtde_control
        import rtde_receive
        try:
            self._recv = rtde_receive.RTDEReceiveInterface(host, self.frequency, _RECEIVE_VARIABLES)
            self._ctrl = rtde_control.RTDEControlInterface(host, self.frequency)
        except RuntimeError as e:
            if hasattr(self, "_recv"):
                self._recv.disconnect()
            raise ArmError(f"host: ur_rtde could not connect to {host}: {e}") from None
        self.nodelay_sockets = _restore_nodelay(host)

        self._lock = threading.Lock()           # one control call at a time
        self._state_lock = threading.Lock()
        self._error = ""
        self._last_setpoint = None              # the last servo set-point (dual quaternion)
        self._last_step = np.zeros(6)           # its displacement from the one before
        self._last_servo_time = 0.0
        self._servoing = False
        self._moving = False
        self.watchdog_stops = 0
        self._ts, self._ts_changed = self._recv.getTimestamp(), time.monotonic()
        self._closed = threading.Event()
        self._monitor = threading.Thread(target=self._watch, name=f"URArm({host}) monitor",
                                         daemon=True)
        self._monitor.start()

    # ------------------------------------------------------------------ monitoring
    def _watch(self):
        interval = min(0.01, self.stale_after / 4)
        while not self._closed.wait(interval):
            now = time.monotonic()
            ts = self._recv.getTimestamp()
            if ts != self._ts:
                self._ts, self._ts_changed = ts, now
            fault = self._fault(now)
            with self._state_lock:
                if fault and not self._error:
                    self._error = fault
                    self._servoing = False
                stalled = (self._servoing and not self._error and
                           now - self._last_servo_time > self.watchdog)
                if stalled:
                    self._servoing = False
            if stalled:
                self._stop_servo()
                self.watchdog_stops += 1

    def _fault(self, now: float) -> str:
        if not self._recv.isConnected() or not self._ctrl.isConnected():
            return f"connection to the controller at {self.host} lost"
        if now - self._ts_changed > self.stale_after:
            return (f"controller at {self.host} stopped sending data "
                    f"({now - self._ts_changed:.2f} s without a new sample)")
        if self._recv.isEmergencyStopped():
            return "emergency stop"
        if self._recv.isProtectiveStopped():
            return "protective stop"
        return ""

    def _stop_servo(self):
        with self._lock:
            if self._ctrl.isConnected():
                self._ctrl.servoStop(self.stop_decel)
            self._last_setpoint = None

    def _check(self):
        if self._closed.is_set():
            raise ArmError("arm: closed")
        fault = self._error or self._fault(time.monotonic())
        if fault:
            with self._state_lock:
                self._error = self._error or fault
            raise ArmError(fault)

    def recover(self) -> None:
        """After a protective stop was released on the controller: clear the error and restart
        the control script. A lost controller cannot be recovered; make a new ``URArm``."""
        self._check_open()
        fault = self._fault(time.monotonic())
        if fault:
            raise ArmError(f"cannot recover: {fault}")
        with self._lock:
            if not self._ctrl.isProgramRunning():
                self._ctrl.reuploadScript()
                deadline = time.monotonic() + 2.0
                while not self._ctrl.isProgramRunning():
                    if time.monotonic() > deadline:
                        raise ArmError("cannot recover: the control script did not start within 2 s")
                    time.sleep(0.01)
            self._last_setpoint = None
            with self._state_lock:
                self._error = ""

    def _check_open(self):
        if self._closed.is_set():
            raise ArmError("arm: closed")

    def status(self) -> ArmState:
        now = time.monotonic()
        connected = (self._recv.isConnected() and self._ctrl.isConnected() and
                     now - self._ts_changed <= self.stale_after and not self._closed.is_set())
        error = self._error or self._fault(now)
        return ArmState(
            connected=connected,
            protective_stop=bool(self._recv.isProtectiveStopped()),
            emergency_stop=bool(self._recv.isEmergencyStopped()),
            faults=(error,) if error else (),
            extra={"controller_time": self._ts, "data_age": now - self._ts_changed,
                   "runtime_state": self._recv.getRuntimeState(),
                   "version": ".".join(map(str, self.version)), "frequency": self.frequency,
                   "watchdog_stops": self.watchdog_stops})

    # ------------------------------------------------------------------ commands
    def tool_pose(self) -> tuple[float, np.ndarray]:
        self._check()
        return time.time(), pose_from_rotvec(self._recv.getActualTCPPose())

    def velocity(self) -> tuple[np.ndarray, np.ndarray]:
        """``actual_TCP_speed``: the tool point's velocity and the tool's angular velocity,
        base frame."""
        self._check()
        v = np.asarray(self._recv.getActualTCPSpeed(), dtype=float)
        return v[:3], v[3:]

    def servo_nowait(self, pose: np.ndarray) -> float:
        """Send one set-point (``servoL``) and return the end of its cycle on the
        :class:`~drivers.base.Pacer` schedule; ``servo()`` then waits for it (``waitPeriod``).

        A set-point that breaks a limit (:meth:`Limits.check_servo`) stops the arm and raises
        :class:`LimitError`. The first set-point is measured from the actual pose, with the arm
        at rest.
        """
        t0 = self._ctrl.initPeriod()        # the checks below count towards the period
        target = unit_pose(pose)
        p6 = rotvec_from_pose(target)
        self._check()
        if self._last_setpoint is None:
            prev, prev_step = pose_from_rotvec(self._recv.getActualTCPPose()), np.zeros(6)
        else:
            prev, prev_step = self._last_setpoint, self._last_step
        dt = self.period
        try:
            step = self.limits.check_servo(target, prev, prev_step, dt)
        except LimitError:
            with self._state_lock:
                was = self._servoing
                self._servoing = False
            if was:
                self._stop_servo()
            self._last_setpoint = None
            raise
        with self._lock:
            ok = self._ctrl.servoL(p6.tolist(), 0.0, 0.0, dt, self.lookahead, self.gain)
            if ok:
                self._last_setpoint, self._last_step = target, step
            with self._state_lock:
                self._servoing = ok
                self._last_servo_time = time.monotonic()
        if not ok:
            self._check()
            raise ArmError("servoL was refused by the controller")
        # ur_rtde's clock comes back as a timedelta of steady_clock, which is CLOCK_MONOTONIC
        # on Linux, as time.monotonic() is
        return self._pacer.cycle(t0.total_seconds()) + self.period

    def wait_cycle(self, end: float) -> None:
        """``waitPeriod``: ends one period after the cycle start it is given (sleeping, then
        spinning, in C++ without the GIL)."""
        self._ctrl.waitPeriod(datetime.timedelta(seconds=end - self.period))

    def move(self, pose: np.ndarray, speed: float, accel: float) -> None:
        """Blocking straight-line move (``moveL``) at ``speed`` m/s and ``accel`` m/s^2
        (:meth:`Limits.check_move`: within the limits, the target in the workspace box, and so
        the whole line).

        The move is sent asynchronously and watched from here: a blocking ``moveL`` in ur_rtde
        does not return when the controller disappears mid-move. A lost controller or a safety
        stop raises :class:`ArmError` within ``stale_after`` plus a poll; ``stop()`` from another
        thread ends the move (and ``move`` raises)."""
        target = unit_pose(pose)
        L = self.limits
        L.check_move(target, speed, accel)
        p6 = rotvec_from_pose(target)
        self._check()
        here = np.asarray(self._recv.getActualTCPPose())
        rel = dq.mul(pose_from_rotvec(p6), dq.conj(pose_from_rotvec(here)))
        angle = float(np.linalg.norm(rotvec_from_quat(rel[:4])))
        if angle > 1e-9 and np.linalg.norm(p6[:3] - here[:3]) > 1e-9:
            # UR turns the tool in step with the translation: keep that turn within the limit
            dist = float(np.linalg.norm(p6[:3] - here[:3]))
            if angle / dist * speed > L.max_angular_speed:
                raise ValueError(f"speed: {speed} m/s over {dist:.4f} m turns the tool at "
                                 f"{angle / dist * speed:.3f} rad/s, above the "
                                 f"{L.max_angular_speed} rad/s limit")
        length = max(float(np.linalg.norm(p6[:3] - here[:3])), angle)
        timeout = 2.0 * (length / speed + speed / accel) + 2.0
        with self._state_lock:
            self._servoing = False
            self._moving = True
        try:
            with self._lock:
                self._last_setpoint = None
                op = self._ctrl.getAsyncOperationProgressEx().operationId()
                if not self._ctrl.moveL(p6.tolist(), float(speed), float(accel), True):
                    self._check()
                    raise ArmError("moveL was refused by the controller")
            started = False
            deadline = time.monotonic() + timeout
            while True:
                self._check()
                if not self._moving:
                    raise ArmError("move: stopped before reaching the target")
                status = self._ctrl.getAsyncOperationProgressEx()
                started = started or status.operationId() != op
                if started and not status.isAsyncOperationRunning():
                    return
                if time.monotonic() > deadline:
                    self.stop()
                    raise ArmError(f"move: not finished within {timeout:.1f} s; the arm was stopped")
                time.sleep(min(0.005, self.period))
        finally:
            self._moving = False

    def stop(self) -> None:
        """Stop servoing or a move and decelerate at ``stop_decel`` m/s^2."""
        with self._state_lock:
            servoing, moving = self._servoing, self._moving
            self._servoing = self._moving = False
        if not self._ctrl.isConnected():
            return
        if moving and not servoing:
            with self._lock:
                self._ctrl.stopL(self.stop_decel)
        else:
            self._stop_servo()

    def close(self) -> None:
        """Stop, end the control script and disconnect (about a second: ur_rtde waits 0.5 s per
        interface)."""
        if self._closed.is_set():
            return
        self._closed.set()
        self._monitor.join()
        with self._lock:
            if self._ctrl.isConnected() and not self._error:
                self._ctrl.servoStop(self.stop_decel)
                self._ctrl.stopScript()
            for iface in (self._ctrl, self._recv):
                try:
                    iface.disconnect()
                except RuntimeError:
                    pass    # the controller is already gone
