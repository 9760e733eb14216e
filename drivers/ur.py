"""Universal Robots arms through ``ur_rtde`` (pinned to 1.6.5): :class:`URArm`.

Poses cross the interface as dual quaternions ``T_base_tool``; the controller speaks
``[x, y, z, rx, ry, rz]`` (metres, rotation vector), converted by :mod:`dqpose.drivers.rotvec`.

Safety, enforced here and not left to the caller: every set-point is checked against the
:class:`~drivers.base.Limits` as every arm checks them and refused (the arm is stopped,
:class:`~drivers.base.LimitError` raised) rather than jumped to; a watchdog stops servoing
when ``servo()`` calls stall; a monitor notices a lost controller (``isConnected()`` false),
stale data (timestamps that stopped advancing while the receive side keeps returning the last
pose) and protective or emergency stops, and stops servoing. While one stands every command
raises :class:`~drivers.base.ArmError` saying which. Lost connections and stale data clear by
themselves: the monitor reconnects to a controller that comes back (a restart), and data that
flows again is a healthy arm again; a safety stop needs :meth:`URArm.recover` once the operator
has released it.

By name: ``drivers.open_arm("ur:192.168.1.10", limits=...)``.
"""
from __future__ import annotations

import datetime
import math
import numbers
import threading
import time
from typing import Optional

import numpy as np

from dqpose import dq
from dqpose.drivers.base import Arm, ArmError, ArmState, Limits, Pacer, ServoStream, unit_pose
from dqpose.drivers.rotvec import pose_from_rotvec, rotvec_from_pose, rotvec_from_quat
from dqpose.drivers.rtde import DASHBOARD_PORT, RTDE_PORT, SCRIPT_PORT, request_version
from dqpose.drivers.ur_connection import (
    CLOSE_WAIT,
    Closed,
    disconnect,
    end_script,
    keep_to_exit,
    probe,
    restore_nodelay,
    within,
)

CB3_MAJOR = 3
_SAFETY_STOPS = ("emergency stop", "protective stop")
#: s between attempts to reconnect to a lost controller (and before the first)
RECONNECT_INTERVAL = 0.5
RUNTIME_PLAYING = 2             # runtime_state: the control script runs
_RECEIVE_VARIABLES = ["timestamp", "actual_TCP_pose", "actual_TCP_speed", "runtime_state",
                      "robot_mode",
                      "safety_mode", "robot_status_bits", "safety_status_bits"]


def _check_arguments(host, frequency, lookahead, gain, stop_decel, watchdog_periods,
                     limits) -> None:
    """:class:`URArm`'s arguments, each a ``ValueError`` naming it."""
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
        raise ValueError("watchdog_periods: must be a whole number >= 1, "
                         f"got {watchdog_periods!r}")
    if limits is not None and not isinstance(limits, Limits):
        raise ValueError(f"limits: expected a drivers.base.Limits, got {type(limits).__name__}")


class URArm(Arm):
    """A UR arm (CB3 or e-series) commanded in tool space through ``ur_rtde``.

    ``frequency`` defaults to the controller's (500 Hz e-series, 125 Hz CB3). The keys of
    :data:`dqpose.drivers.spec.ARM_KEYS` (``options``): ``watchdog`` is how long ``servo()`` may
    stall
    before the arm is stopped (``watchdog_periods``, the older way, counts it in periods);
    ``stale_after`` is how long (s) data timestamps may stand still before the controller counts
    as lost; ``connect_timeout`` bounds the reachability probe (``ur_rtde``'s own constructor
    has no timeout, so the ports are probed first) and the wait for the first data.

    ``disconnect`` (:attr:`disconnect_on_close`): whether :meth:`close` ends ur_rtde's
    connections, which takes it 0.5 s (both at once) and its destructors 0.5 s more each, holding
    the interpreter lock. False is for an arm closed only as its process ends (the arm's own
    process, a command on its way out, with a controller that outlives it): :meth:`close` then
    stops the arm and ends the control script as ever, and leaves the connections to the
    process's end, which closes them. Such a process ends with ``os._exit`` once its output is
    flushed (``dqpose``'s commands do: :func:`~dqpose.drivers.ur_connection.kept_to_exit`):
    ur_rtde's threads still run while the interpreter tears itself down, which now and then
    crashes it after the clean stop.
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
                 stop_decel: float = 10.0, watchdog_periods: Optional[int] = None,
                 disconnect: bool = True, **options):
        _check_arguments(host, frequency, lookahead, gain, stop_decel, watchdog_periods, limits)
        self._set_options("ur", options)
        connect_timeout = self.connect_timeout
        self.host, self.limits = host, limits or Limits()
        self.lookahead, self.gain = float(lookahead), float(gain)
        self.stop_decel = float(stop_decel)
        self.disconnect_on_close = bool(disconnect)

        for port in (RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT):
            probe(host, port, connect_timeout)
        try:
            self.version = tuple(request_version(host, RTDE_PORT, connect_timeout))
        except OSError as e:
            raise ArmError(f"host: {host}:{RTDE_PORT} does not answer as a UR controller "
                           f"({e})") from None
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
        self.nodelay_sockets = restore_nodelay(host)

        self._lock = threading.Lock()           # one control call at a time
        self._recv_lock = threading.RLock()     # no read while the receive side reconnects
        self._state_lock = threading.Lock()
        self._error = ""                        # a safety stop, until recover()
        self._reconnecting = False
        self._was_lost = False                  # lost since the last healthy moment
        self._next_heal = 0.0                   # monotonic: the next attempt to reconnect
        self._interrupted = False               # a servo stream cut by a lost connection
        self._stopping = threading.Event()      # a servoStop under way in its own thread
        self.reconnects = 0
        self._stream = ServoStream()
        self._moving = False
        self.watchdog_stops = 0
        self._ts, self._ts_changed = self._recv.getTimestamp(), time.monotonic()
        deadline = time.monotonic() + connect_timeout
        # the first data package (a state to report), with the control script playing
        while self._recv.getTimestamp() <= 0 or self._recv.getRuntimeState() != RUNTIME_PLAYING:
            if time.monotonic() > deadline:
                self._ctrl.disconnect()
                self._recv.disconnect()
                what = "sent no data" if self._recv.getTimestamp() <= 0 else \
                    "did not start the control script"
                raise ArmError(f"host: the controller at {host} {what} within "
                               f"{connect_timeout:g} s")
            time.sleep(0.001)
        self._closed = threading.Event()
        self._monitor = threading.Thread(target=self._watch, name=f"URArm({host}) monitor",
                                         daemon=True)
        self._monitor.start()

    # ------------------------------------------------------------------ monitoring
    def _watch(self):
        interval = min(0.01, self.stale_after / 4)
        while not self._closed.wait(interval):
            now = time.monotonic()
            with self._recv_lock:
                fault = self._fault(now)
            with self._state_lock:
                if fault in _SAFETY_STOPS:
                    self._error = self._error or fault
                faulted = bool(fault or self._error)
            # a faulted controller is not sent a stop (it would wait for data that does not
            # come, or on a halted program): the next command raises instead
            if faulted:
                self._stream.end(forget=False)
            stalled = not faulted and self._stream.stalled(self.watchdog)
            if stalled:
                self._stop_servo()
                self.watchdog_stops += 1
            self._heal_when_due(fault, now)

    def _lost(self) -> str:
        return f"connection to the controller at {self.host} lost"

    def _not_running(self) -> str:
        return f"the control script is not running on the controller at {self.host}"

    def _heal_when_due(self, fault: str, now: float) -> None:
        """After a lost connection: reconnect to the controller once it is back, and restart
        the control script if it did not come back with it. Not at once: ur_rtde's control
        side first tries once by itself, and two reconnects at a time crash it."""
        if fault == self._lost():
            self._was_lost = True
            if self._stream.forget():       # the stream under way is cut: say so
                self._interrupted = True
        if not (self._was_lost and fault in (self._lost(), self._not_running())):
            self._next_heal = 0.0
            self._was_lost = self._was_lost and bool(fault)
        elif not self._next_heal:
            self._next_heal = now + RECONNECT_INTERVAL
        elif now >= self._next_heal:
            self._next_heal = now + RECONNECT_INTERVAL
            if self._heal(fault):
                self.reconnects += 1

    def _heal(self, fault: str) -> bool:
        """One attempt; False while the controller is still away."""
        try:
            for port in (DASHBOARD_PORT, SCRIPT_PORT):
                probe(self.host, port, 0.2)
            # a controller that answers RTDE: a booting one may accept and close connections,
            # and ur_rtde, connected to that, would wait for data that never comes
            request_version(self.host, RTDE_PORT, 0.5)
        except (ArmError, OSError):
            return False
        self._reconnecting = True
        try:
            # both locks: no other call may touch an interface while it is rebuilt
            with self._lock, self._recv_lock:
                if fault == self._lost():
                    if not self._recv.isConnected():
                        self._recv.reconnect()
                    if not self._ctrl.isConnected():    # its own attempt failed and ended
                        self._ctrl.reconnect()
                else:
                    self._ctrl.reuploadScript()
            self.nodelay_sockets = restore_nodelay(self.host)
            return True
        except RuntimeError:
            return False
        finally:
            with self._recv_lock:
                self._ts, self._ts_changed = self._recv.getTimestamp(), time.monotonic()
                self._reconnecting = False

    def _data_age(self, now: float) -> float:
        """Seconds since the controller's data last changed (its timestamp advanced)."""
        ts = self._recv.getTimestamp()
        if ts != self._ts:
            self._ts, self._ts_changed = ts, now
        return now - self._ts_changed

    def _fault(self, now: float) -> str:
        """What is wrong now ("" if nothing); under ``_recv_lock``."""
        if self._reconnecting or not self._recv.isConnected() or not self._ctrl.isConnected():
            return self._lost()
        age = self._data_age(now)
        if age > self.stale_after:
            return (f"controller at {self.host} stopped sending data "
                    f"({age:.2f} s without a new sample, stale_after {self.stale_after:g} s)")
        if self._recv.isEmergencyStopped():
            return "emergency stop"
        if self._recv.isProtectiveStopped():
            return "protective stop"
        if self._recv.getRuntimeState() != RUNTIME_PLAYING:
            return self._not_running()
        return ""

    def _call(self, name: str, *args):
        """A control call; ur_rtde's own failure (its reconnect attempts to the dashboard
        server of a controller that is gone) is the lost connection it is."""
        try:
            return getattr(self._ctrl, name)(*args)
        except RuntimeError:
            raise ArmError(self._lost()) from None

    def _stop_servo(self):
        """``servoStop``. ur_rtde waits for the controller to report it done, in its data: from
        a controller whose data has stopped that wait lasts until the data comes back (or
        minutes), so then the stop goes out from a thread of its own and this returns."""
        with self._recv_lock:
            age = self._data_age(time.monotonic())
        if age > self.tracking_lag:         # (what the control loop calls stale feedback)
            if not self._stopping.is_set():
                self._stopping.set()
                threading.Thread(target=self._servo_stop, name=f"URArm({self.host}) stop",
                                 daemon=True).start()
            return
        self._servo_stop()

    def _servo_stop(self):
        try:
            with self._lock:
                if self._ctrl.isConnected():
                    try:
                        self._ctrl.servoStop(self.stop_decel)
                    except RuntimeError:
                        pass    # gone meanwhile: a controller that loses its client stops
                self._stream.forget()
                self._interrupted = False
        finally:
            self._stopping.clear()

    def _check(self):
        if self._closed.is_set():
            raise ArmError("arm: closed")
        with self._recv_lock:
            fault = self._error or self._fault(time.monotonic())
        if fault:
            if fault in _SAFETY_STOPS:
                with self._state_lock:
                    self._error = self._error or fault
            raise ArmError(fault)

    def recover(self) -> None:
        """After a protective stop was released on the controller: clear the error and restart
        the control script. (A lost connection or stale data need nothing: they clear once the
        controller is back.)"""
        self._check_open()
        with self._recv_lock:
            fault = self._fault(time.monotonic())
        if fault and fault != self._not_running():
            raise ArmError(f"cannot recover: {fault}")
        with self._lock:
            if not self._call("isProgramRunning"):
                self._call("reuploadScript")
                deadline = time.monotonic() + 2.0
                while not self._call("isProgramRunning"):
                    if time.monotonic() > deadline:
                        raise ArmError("cannot recover: the control script did not start "
                                       "within 2 s")
                    time.sleep(0.01)
            self._stream.forget()
            with self._state_lock:
                self._error = ""

    def _check_open(self):
        if self._closed.is_set():
            raise ArmError("arm: closed")

    def status(self) -> ArmState:
        if self._closed.is_set():
            return ArmState(connected=False, faults=("arm: closed",))
        with self._recv_lock:
            now = time.monotonic()
            fault = self._fault(now)
            error = self._error or fault
            lost = fault == self._lost()
            return ArmState(
                connected=not lost and now - self._ts_changed <= self.stale_after
                and not self._closed.is_set(),
                protective_stop=bool(self._recv.isProtectiveStopped()),
                emergency_stop=bool(self._recv.isEmergencyStopped()),
                faults=(error,) if error else (),
                extra={"controller_time": self._ts, "data_age": now - self._ts_changed,
                       "runtime_state": self._recv.getRuntimeState(),
                       "version": ".".join(map(str, self.version)),
                       "frequency": self.frequency, "watchdog_stops": self.watchdog_stops,
                       "reconnects": self.reconnects})

    # ------------------------------------------------------------------ commands
    def tool_pose(self) -> tuple[float, np.ndarray]:
        """The actual TCP pose, stamped with when its data arrived."""
        with self._recv_lock:
            self._check()
            p6 = self._recv.getActualTCPPose()
            age = time.monotonic() - self._ts_changed
        return time.time() - age, pose_from_rotvec(p6)

    def velocity(self) -> tuple[np.ndarray, np.ndarray]:
        """``actual_TCP_speed``: the tool point's velocity and the tool's angular velocity,
        base frame."""
        with self._recv_lock:
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
        if self._interrupted:
            self._interrupted = False
            raise ArmError(f"{self._lost()} during this servo stream (and connected again); "
                           "a new stream starts from rest")
        step = self._checked_setpoint(target, lambda: self.tool_pose()[1])
        with self._lock:
            ok = self._call("servoL", p6.tolist(), 0.0, 0.0, self.period, self.lookahead,
                            self.gain)
            self._stream.sent(target, step, ok)
        if not ok:
            self._check()
            raise ArmError("servoL was refused by the controller")
        # ur_rtde's clock comes back as a timedelta of steady_clock, which is CLOCK_MONOTONIC
        # on Linux, as time.monotonic() is
        return self._pacer.cycle(t0.total_seconds()) + self.period

    def _refused(self, streaming: bool) -> None:
        if streaming:
            self._stop_servo()

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
        here = rotvec_from_pose(self.tool_pose()[1])
        rel = dq.mul(pose_from_rotvec(p6), dq.conj(pose_from_rotvec(here)))
        angle = float(np.linalg.norm(rotvec_from_quat(rel[:4])))
        if angle > 1e-9 and np.linalg.norm(p6[:3] - here[:3]) > 1e-9:
            # UR turns the tool in step with the translation: keep that turn within the limit
            dist = float(np.linalg.norm(p6[:3] - here[:3]))
            if angle / dist * speed > L.max_angular_velocity:
                raise ValueError(f"speed: {speed} m/s over {dist:.4f} m turns the tool at "
                                 f"{angle / dist * speed:.3f} rad/s, above the "
                                 f"{L.max_angular_velocity} rad/s limit")
        length = max(float(np.linalg.norm(p6[:3] - here[:3])), angle)
        timeout = 2.0 * (length / speed + speed / accel) + 2.0
        self._stream.end(forget=False)
        with self._state_lock:
            self._moving = True
        try:
            with self._lock:
                self._stream.forget()
                op = self._call("getAsyncOperationProgressEx").operationId()
                if not self._call("moveL", p6.tolist(), float(speed), float(accel), True):
                    self._check()
                    raise ArmError("moveL was refused by the controller")
            started = False
            deadline = time.monotonic() + timeout
            while True:
                self._check()
                if not self._moving:
                    raise ArmError("move: stopped before reaching the target")
                with self._lock:
                    status = self._call("getAsyncOperationProgressEx")
                started = started or status.operationId() != op
                if started and not status.isAsyncOperationRunning():
                    return
                if time.monotonic() > deadline:
                    self.stop()
                    raise ArmError(f"move: not finished within {timeout:.1f} s; "
                                   "the arm was stopped")
                time.sleep(min(0.005, self.period))
        finally:
            self._moving = False

    def stop(self) -> None:
        """Stop servoing or a move and decelerate at ``stop_decel`` m/s^2."""
        servoing = self._stream.end(forget=False)
        with self._state_lock:
            moving, self._moving = self._moving, False
        if moving and not servoing:
            with self._lock:
                if self._ctrl.isConnected():
                    self._call("stopL", self.stop_decel)
        else:
            self._stop_servo()

    def close(self) -> None:
        """Stop, end the control script and, unless :attr:`disconnect_on_close` is False,
        disconnect (about 1.5 s: ur_rtde waits 0.5 s in its disconnects, run at once, and as long
        in each destructor). Each step waits at most :data:`CLOSE_WAIT`: ur_rtde's stopScript
        waits for the controller to report its program ended, for minutes when the controller
        has stopped answering; interfaces that did not finish are left to the process's end."""
        if self._closed.is_set():
            return
        self._closed.set()
        self._monitor.join()
        with self._lock:
            ctrl = self._ctrl
            ended = True
            if ctrl.isConnected() and not self._error:
                ended = within(CLOSE_WAIT, end_script, ctrl, self.stop_decel)
            interfaces = (self._ctrl, self._recv)
            with self._recv_lock:
                self._ctrl = self._recv = Closed()
            if not (self.disconnect_on_close and ended):
                keep_to_exit(interfaces)
                return
            # each disconnect sleeps 0.5 s without the interpreter lock: both at once
            ends = [threading.Thread(target=disconnect, args=(i,), daemon=True)
                    for i in interfaces]
            for t in ends:
                t.start()
            deadline = time.monotonic() + CLOSE_WAIT
            for t in ends:
                t.join(max(0.0, deadline - time.monotonic()))
            if any(t.is_alive() for t in ends):
                keep_to_exit(interfaces)   # their destructors would wait as long
                return
            # ur_rtde's destructors sleep 0.5 s each holding the interpreter lock: here, in the
            # close that is expected to take that long, not whenever a garbage collection finds
            # this arm later (every thread of the process would stop then)
            del interfaces
