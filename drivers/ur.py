"""Universal Robots arms through ``ur_rtde`` (pinned to 1.6.5): :class:`URArm`.

Poses cross the interface as dual quaternions ``T_base_tool``; the controller speaks
``[x, y, z, rx, ry, rz]`` (metres, rotation vector), converted by :mod:`drivers.rotvec`.

Safety, enforced here and not left to the caller: every set-point is checked against a speed,
acceleration and workspace :class:`Limits` and refused (the arm is stopped, :class:`LimitError`
raised) rather than jumped to; a watchdog stops servoing when ``servo()`` calls stall; a monitor
notices a lost controller (``isConnected()`` false, or data timestamps that stopped advancing
while the receive side keeps returning the last pose) and protective or emergency stops, and
every later command raises :class:`~drivers.base.ArmError`.
"""
from __future__ import annotations

import math
import numbers
import socket
import threading
import time
from dataclasses import dataclass
from typing import Optional

import numpy as np

from drivers.base import Arm, ArmError, ArmStatus
from drivers.rotvec import pose_from_rotvec, rotvec_from_pose, rotvec_from_quat
from drivers.rtde import request_version
from service import dq

RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT = 30004, 29999, 30003
CB3_MAJOR = 3
_RECEIVE_VARIABLES = ["timestamp", "actual_TCP_pose", "runtime_state", "robot_mode",
                      "safety_mode", "robot_status_bits", "safety_status_bits"]


class LimitError(ArmError):
    """A command was refused because it breaks a safety limit; the arm was stopped."""


@dataclass(frozen=True)
class Limits:
    """What a command may ask of the arm. The defaults suit a UR5e on an open bench; set the
    workspace box to your cell."""
    max_linear_speed: float = 0.25      # m/s
    max_angular_speed: float = 1.0      # rad/s
    max_linear_accel: float = 2.0       # m/s^2
    max_angular_accel: float = 4.0      # rad/s^2
    workspace_min: tuple = (-1.0, -1.0, -0.2)   # m, base frame
    workspace_max: tuple = (1.0, 1.0, 1.2)

    def __post_init__(self):
        for name in ("max_linear_speed", "max_angular_speed", "max_linear_accel",
                     "max_angular_accel"):
            v = getattr(self, name)
            if not (isinstance(v, numbers.Real) and math.isfinite(v) and v > 0):
                raise ValueError(f"limits.{name}: must be a positive finite number, got {v!r}")
        lo, hi = np.asarray(self.workspace_min, float), np.asarray(self.workspace_max, float)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite(lo) & np.isfinite(hi)):
            raise ValueError("limits.workspace_min/max: expected three finite numbers each")
        if np.any(lo >= hi):
            raise ValueError(f"limits.workspace_min: {lo.tolist()} is not below "
                             f"workspace_max {hi.tolist()}")

    def check_workspace(self, name: str, t: np.ndarray) -> None:
        lo, hi = np.asarray(self.workspace_min), np.asarray(self.workspace_max)
        if np.any(t < lo) or np.any(t > hi):
            raise LimitError(f"{name}: position {np.round(t, 4).tolist()} m is outside the "
                             f"workspace box {list(self.workspace_min)}..{list(self.workspace_max)}")


def _probe(host: str, port: int, timeout: float) -> None:
    try:
        socket.create_connection((host, port), timeout=timeout).close()
    except OSError as e:
        raise ArmError(f"host: cannot reach a UR controller at {host}:{port} within "
                       f"{timeout:g} s ({e})") from None


class URArm(Arm):
    """A UR arm (CB3 or e-series) commanded in tool space through ``ur_rtde``.

    ``frequency`` defaults to the controller's (500 Hz e-series, 125 Hz CB3). ``watchdog_periods``
    is how many periods ``servo()`` may stall before the arm is stopped; ``stale_after`` is how
    long (s) data timestamps may stand still before the controller counts as lost.
    ``connect_timeout`` bounds the reachability probe; ``ur_rtde``'s own constructor has no
    timeout, so the ports are probed first.
    """

    def __init__(self, host: str, frequency: Optional[float] = None, *,
                 limits: Limits = Limits(), watchdog_periods: int = 25, stale_after: float = 0.1,
                 connect_timeout: float = 2.0, lookahead: float = 0.1, gain: float = 300.0,
                 stop_decel: float = 10.0):
        if not isinstance(host, str) or not host:
            raise ValueError(f"host: expected a host name or address, got {host!r}")
        if frequency is not None and not (math.isfinite(frequency) and 0 < frequency <= 500):
            raise ValueError(f"frequency: must be within (0, 500] Hz, got {frequency!r}")
        if not 0.03 <= lookahead <= 0.2:
            raise ValueError(f"lookahead: must be within [0.03, 0.2] s, got {lookahead!r}")
        if not 100 <= gain <= 2000:
            raise ValueError(f"gain: must be within [100, 2000], got {gain!r}")
        for name, v in (("stale_after", stale_after), ("connect_timeout", connect_timeout),
                        ("stop_decel", stop_decel)):
            if not (isinstance(v, numbers.Real) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name}: must be a positive number, got {v!r}")
        if int(watchdog_periods) != watchdog_periods or watchdog_periods < 1:
            raise ValueError(f"watchdog_periods: must be a whole number >= 1, got {watchdog_periods!r}")
        self.host, self.limits = host, limits
        self.lookahead, self.gain, self.stop_decel = float(lookahead), float(gain), float(stop_decel)
        self.watchdog_periods, self.stale_after = int(watchdog_periods), float(stale_after)

        for port in (RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT):
            _probe(host, port, connect_timeout)
        try:
            self.version = tuple(request_version(host, RTDE_PORT, connect_timeout))
        except OSError as e:
            raise ArmError(f"host: {host}:{RTDE_PORT} does not answer as a UR controller ({e})") from None
        self.frequency = float(frequency or (500.0 if self.version[0] > CB3_MAJOR else 125.0))
        self.period = 1.0 / self.frequency

        import rtde_control
        import rtde_receive
        try:
            self._recv = rtde_receive.RTDEReceiveInterface(host, self.frequency, _RECEIVE_VARIABLES)
            self._ctrl = rtde_control.RTDEControlInterface(host, self.frequency)
        except RuntimeError as e:
            if hasattr(self, "_recv"):
                self._recv.disconnect()
            raise ArmError(f"host: ur_rtde could not connect to {host}: {e}") from None

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
                           now - self._last_servo_time > self.watchdog_periods * self.period)
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

    def status(self) -> ArmStatus:
        now = time.monotonic()
        connected = (self._recv.isConnected() and self._ctrl.isConnected() and
                     now - self._ts_changed <= self.stale_after and not self._closed.is_set())
        return ArmStatus(
            connected=connected,
            protective_stop=bool(self._recv.isProtectiveStopped()),
            emergency_stop=bool(self._recv.isEmergencyStopped()),
            error=self._error or self._fault(now),
            extra={"controller_time": self._ts, "data_age": now - self._ts_changed,
                   "runtime_state": self._recv.getRuntimeState(),
                   "version": ".".join(map(str, self.version)), "frequency": self.frequency,
                   "watchdog_stops": self.watchdog_stops})

    # ------------------------------------------------------------------ commands
    def tool_pose(self) -> tuple[float, np.ndarray]:
        self._check()
        return time.monotonic(), pose_from_rotvec(self._recv.getActualTCPPose())

    @staticmethod
    def _validate(pose) -> np.ndarray:
        a = np.asarray(pose, dtype=np.float64)
        if a.shape != (8,):
            raise ValueError(f"pose: expected a dual quaternion of shape (8,), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError("pose: contains NaN or infinity")
        return rotvec_from_pose(a)      # raises ValueError for a non-unit pose

    def servo(self, pose: np.ndarray) -> None:
        """Send one set-point and wait out the period (``initPeriod``/``servoL``/``waitPeriod``).

        A set-point farther than one period at the speed limit from the previous one, or whose
        step changes faster than the acceleration limit allows, or outside the workspace, stops
        the arm and raises :class:`LimitError`. The first set-point is measured from the
        actual pose, with the arm at rest.
        """
        t0 = self._ctrl.initPeriod()        # the checks below count towards the period
        p6 = self._validate(pose)
        self._check()
        target = pose_from_rotvec(p6)
        if self._last_setpoint is None:
            prev, prev_step = pose_from_rotvec(self._recv.getActualTCPPose()), np.zeros(6)
        else:
            prev, prev_step = self._last_setpoint, self._last_step
        # displacement from the previous set-point: translation, then rotation vector (base frame)
        step = np.concatenate([p6[:3] - rotvec_from_pose(prev)[:3],
                               rotvec_from_quat(dq.mul(target, dq.conj(prev))[:4])])
        lin, ang = float(np.linalg.norm(step[:3])), float(np.linalg.norm(step[3:]))
        dt, L = self.period, self.limits
        problem = ""
        try:
            L.check_workspace("pose", p6[:3])
        except LimitError as e:
            problem = str(e)
        if not problem and lin > L.max_linear_speed * dt * (1 + 1e-9):
            problem = (f"pose: set-point is {lin * 1e3:.3f} mm from the last one, more than one "
                       f"period at {L.max_linear_speed} m/s ({L.max_linear_speed * dt * 1e3:.3f} mm)")
        elif not problem and ang > L.max_angular_speed * dt * (1 + 1e-9):
            problem = (f"pose: set-point turns {math.degrees(ang):.4f} deg from the last one, more "
                       f"than one period at {L.max_angular_speed} rad/s")
        elif not problem:
            dv = float(np.linalg.norm(step[:3] - prev_step[:3])) / dt ** 2
            dw = float(np.linalg.norm(step[3:] - prev_step[3:])) / dt ** 2
            if dv > L.max_linear_accel * (1 + 1e-6):
                problem = (f"pose: set-point needs {dv:.2f} m/s^2, above the "
                           f"{L.max_linear_accel} m/s^2 limit")
            elif dw > L.max_angular_accel * (1 + 1e-6):
                problem = (f"pose: set-point needs {dw:.2f} rad/s^2, above the "
                           f"{L.max_angular_accel} rad/s^2 limit")
        if problem:
            with self._state_lock:
                was = self._servoing
                self._servoing = False
            if was:
                self._stop_servo()
            self._last_setpoint = None
            raise LimitError(problem + "; the arm was stopped")
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
        self._ctrl.waitPeriod(t0)

    def move(self, pose: np.ndarray, speed: float, accel: float) -> None:
        """Blocking straight-line move (``moveL``) at ``speed`` m/s and ``accel`` m/s^2, both
        within the limits; the target must lie in the workspace box (so does the whole line).

        The move is sent asynchronously and watched from here: a blocking ``moveL`` in ur_rtde
        does not return when the controller disappears mid-move. A lost controller or a safety
        stop raises :class:`ArmError` within ``stale_after`` plus a poll; ``stop()`` from another
        thread ends the move (and ``move`` raises)."""
        p6 = self._validate(pose)
        L = self.limits
        for name, v, hi in (("speed", speed, L.max_linear_speed), ("accel", accel, L.max_linear_accel)):
            if not (isinstance(v, numbers.Real) and math.isfinite(v) and 0 < v <= hi):
                raise ValueError(f"{name}: must be within (0, {hi}], got {v!r}")
        L.check_workspace("pose", p6[:3])
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
