"""The simulated UR controller's model: its registers, its control program and its arm.

What a controller publishes over RTDE lives in one table (``values``, RTDE variable names);
what clients write lands in the same table. The uploaded ``rtde_control`` script is not
interpreted: its register protocol is modelled instead (the command id in
``input_int_register_0``, arguments in the input registers, ``output_int_register_0`` answering
1, ready, or 2, done). Motion is tool-space only: servoL follows its set-points ``servo_lag``
cycles late under the speed limits, moveL runs a trapezoidal profile (rotation interpolated
along with the translation), stops decelerate at the requested rate. Joint-space commands are
acknowledged and logged but do not move the model. Poses are UR's ``[x, y, z, rx, ry, rz]``
(metres, rotation vector); orientations inside the model are unit quaternions, scalar first.
"""
from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass

import numpy as np

from dqpose.drivers import rtde as rp
from dqpose.drivers.rotvec import quat_from_rotvec, rotvec_from_quat
from dqpose.profile import Trapezoid

RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT = rp.RTDE_PORT, rp.DASHBOARD_PORT, rp.SCRIPT_PORT
HOOK_PORT = 30010

# runtime_state values
STOPPING, STOPPED, PLAYING, PAUSING, PAUSED = 0, 1, 2, 3, 4
# safety_status_bits
NORMAL_MODE, PROTECTIVE_STOP_BIT, EMERGENCY_STOP_BIT = 1 << 0, 1 << 2, 1 << 7
ROBOT_MODE_RUNNING, SAFETY_MODE_NORMAL, SAFETY_MODE_PROTECTIVE, SAFETY_MODE_ROBOT_ESTOP = 7, 1, 3, 7

# Commands the control script answers with "ready" without waiting for a clear (its realtime set).
REALTIME = {24, 11, 9, 10, 6, 25, 26, 27, 38, 58}
SERVOL, MOVEL, SPEED_STOP, SERVO_STOP, STOPL, STOPJ, STOP_SCRIPT = 24, 3, 15, 16, 33, 34, 255


@dataclass
class SimConfig:
    host: str = "127.0.0.1"
    hook_port: int = HOOK_PORT
    version: tuple = (5, 11, 1, 108318)
    serial: str = "20235500001"
    pose: tuple = (0.4, -0.1, 0.3, 2.2, 2.2, 0.0)
    servo_lag: int = 2                  # cycles between reading a set-point and reaching it
    max_linear_speed: float = 1.0       # m/s
    max_angular_speed: float = 3.0      # rad/s
    history: int = 10000                # cycles of pose history kept for the hooks
    log: int = 50000                    # received commands kept for the hooks

    @property
    def period(self) -> float:
        return 0.002 if self.version[0] > 3 else 0.008


def _qmul(a, b):
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def _qconj(a):
    return np.array([a[0], -a[1], -a[2], -a[3]])


def _rel_rotvec(q_from, q_to):
    """Rotation vector (in the moving frame) taking ``q_from`` to ``q_to``, the short way."""
    return rotvec_from_quat(_qmul(_qconj(q_from), q_to))


def _limit(v, vmax):
    n = float(np.linalg.norm(v))
    return v * (vmax / n) if n > vmax else v


class _Move:
    def __init__(self, p0, q0, p1, q1, v, a, cfg: SimConfig):
        self.p0, self.p1, self.q0 = p0, p1, q0
        self.w = _rel_rotvec(q0, q1)
        self.q1 = q1
        dist, angle = float(np.linalg.norm(p1 - p0)), float(np.linalg.norm(self.w))
        if dist > 1e-9:
            v = min(v, cfg.max_linear_speed, cfg.max_angular_speed * dist / angle if angle else v)
            self.length = dist
        else:  # pure rotation: UR reads v and a as rad/s and rad/s^2
            v = min(v, cfg.max_angular_speed)
            self.length = angle
        self.profile = Trapezoid(self.length, v, a)
        self.t = 0.0

    def step(self, dt):
        """Advance and return (p, q, finished)."""
        self.t += dt
        if self.t >= self.profile.duration:
            return self.p1.copy(), self.q1.copy(), True
        f = self.profile.fraction(self.t)
        return (self.p0 + f * (self.p1 - self.p0), _qmul(self.q0, quat_from_rotvec(f * self.w)),
                False)


class Controller:
    """The model: the register table, the control program, the arm; ``step()`` is one
    controller cycle (2 ms e-series, 8 ms CB3). Everything is read and changed under ``lock``."""

    def __init__(self, cfg: SimConfig | None = None):
        self.cfg = cfg = cfg or SimConfig()
        self.dt = cfg.period
        self.lock = threading.RLock()
        self.tick = 0
        self.t0 = time.monotonic()
        self.values: dict = {
            "robot_mode": ROBOT_MODE_RUNNING, "safety_mode": SAFETY_MODE_NORMAL,
            "safety_status": SAFETY_MODE_NORMAL, "joint_mode": [253] * 6,
            "speed_scaling": 1.0, "target_speed_fraction": 1.0, "actual_main_voltage": 48.0,
            "actual_robot_voltage": 48.0, "actual_robot_current": 0.9,
            "joint_temperatures": [32.0] * 6, "actual_joint_voltage": [47.5] * 6,
            "actual_tool_accelerometer": [0.0, 0.0, 9.81], "payload": 0.0,
            "actual_q": [0.0, -1.57, 1.57, -1.57, -1.57, 0.0],
        }
        self.values["target_q"] = self.values["actual_q"]
        p6 = np.asarray(cfg.pose, dtype=float)
        self.p, self.q = p6[:3].copy(), quat_from_rotvec(p6[3:])
        self.v, self.w = np.zeros(3), np.zeros(3)
        self.runtime_state = STOPPED
        self.safety_bits = NORMAL_MODE
        self.executing = False
        self.busy = None             # ("move", _Move) | ("stop", decel) while the script blocks
        self.background = None       # an async move or stop the script does not wait for
        self.async_running = False   # the script's async progress word (output_int_register_2)
        self.async_count = self.async_op = 0
        self.servoing = False
        self.servo_target = None
        self.servo_queue: collections.deque = collections.deque(maxlen=cfg.servo_lag + 1)
        self.scripts: list[str] = []
        self.history: collections.deque = collections.deque(maxlen=cfg.history)
        self._publish()

    # ---------------------------------------------------------------- state published over RTDE
    def _publish(self):
        rv = rotvec_from_quat(self.q)
        pose = [*self.p.tolist(), *rv.tolist()]
        v = self.values
        v["timestamp"] = self.tick * self.dt
        v["actual_execution_time"] = 0.05
        v["actual_TCP_pose"] = pose
        v["target_TCP_pose"] = pose
        v["actual_TCP_speed"] = v["target_TCP_speed"] = [*self.v.tolist(), *self.w.tolist()]
        v["runtime_state"] = self.runtime_state
        v["robot_status_bits"] = 0b1 | (0b10 if self.runtime_state == PLAYING else 0)
        v["safety_status_bits"] = self.safety_bits
        mode = (SAFETY_MODE_ROBOT_ESTOP if self.safety_bits & EMERGENCY_STOP_BIT else
                SAFETY_MODE_PROTECTIVE if self.safety_bits & PROTECTIVE_STOP_BIT else
                SAFETY_MODE_NORMAL)
        v["safety_mode"] = v["safety_status"] = mode
        sample = (self.tick, v["timestamp"], *pose)
        if self.history and self.history[-1][0] == self.tick:
            self.history[-1] = sample       # a hook moved the arm within this cycle
        else:
            self.history.append(sample)

    def reg(self, kind, i):
        return self.values.get(f"input_{kind}_register_{i}", 0)

    def _ready(self, code):
        self.values["output_int_register_0"] = code

    def _write_async(self, value):
        """The control script's async status word: op id in bits 24-30, a change counter in
        16-23, bit 15 while an operation runs, progress below."""
        self.async_count = (self.async_count + 1) % 128
        if value == 0:
            self.async_op = (self.async_op + 1) % 128
        word = self.async_count * 65536 + self.async_op * 16777216
        if value >= 0:
            word += min(value, 32767) + 32768
        self.values["output_int_register_2"] = word

    def _set_background(self, action, tracked=False):
        """Replace the motion the script does not wait for; ``tracked`` ones (async moveL,
        stopL) report start and end in the async status word."""
        if self.async_running:
            self._write_async(-1)
            self.async_running = False
        self.background = action
        if tracked:
            self._write_async(0)
            self.async_running = True

    # ---------------------------------------------------------------- the control script
    def _script_cycle(self):
        if self.runtime_state != PLAYING or self.busy is not None:
            return
        cmd = self.reg("int", 0)
        if cmd in REALTIME:
            self._process(cmd)
            self._ready(1)
        elif cmd == 0:
            self.executing = False
            self._ready(1)
        elif not self.executing:
            self.executing = True
            if self._process(cmd) and self.busy is None:
                self._ready(2)

    def _pose_regs(self):
        r = [self.reg("double", i) for i in range(6)]
        return np.array(r[:3]), quat_from_rotvec(np.array(r[3:]))

    def _process(self, cmd) -> bool:
        """Start a command; False when the program ended (stopScript)."""
        if cmd == SERVOL:
            p, q = self._pose_regs()
            self.servo_target = (p, q)
            if not self.servoing:
                self.servoing = True
                self._set_background(None)
                self.servo_queue.clear()
                self.servo_queue.extend([(self.p.copy(), self.q.copy())] * self.cfg.servo_lag)
        elif cmd == MOVEL:
            p, q = self._pose_regs()
            v, a = self.reg("double", 6), self.reg("double", 7)
            move = _Move(self.p.copy(), self.q.copy(), p, q, max(v, 1e-6), max(a, 1e-6), self.cfg)
            self.servoing = False
            if self.reg("int", 1) == 1:
                self._set_background(("move", move), tracked=True)
            else:
                self._set_background(None)
                self.busy = ("move", move)
        elif cmd in (SERVO_STOP, SPEED_STOP, STOPL, STOPJ):
            self.servoing = False
            decel = self.reg("double", 0) or 10.0
            if cmd in (STOPL, STOPJ) and self.reg("int", 1) == 1:
                self._set_background(("stop", decel), tracked=True)
            else:
                self._set_background(None)
                self.busy = ("stop", decel)
        elif cmd == STOP_SCRIPT:
            self._end_program()
            return False
        return True

    def _end_program(self):
        self.runtime_state = STOPPED
        self.executing = False
        self.busy = None
        if self.servoing or self.background:
            self._set_background(("stop", 10.0))   # a stopped program ramps the arm down
        self.servoing = False

    def start_program(self, text: str):
        with self.lock:
            self.scripts.append(text)
            self.runtime_state = PLAYING
            self.executing = False
            self.busy = None
            self._set_background(None)
            self.servoing = False
            self._ready(1)
            self._write_async(-1)

    # ---------------------------------------------------------------- motion model
    def _motion_cycle(self):
        dt = self.dt
        p_old, q_old = self.p.copy(), self.q.copy()
        finished = False
        action = self.busy or self.background
        if self.safety_bits & (PROTECTIVE_STOP_BIT | EMERGENCY_STOP_BIT):
            action = None
        if self.servoing and self.servo_target is not None:
            self.servo_queue.append(self.servo_target)
            p_ref, q_ref = self.servo_queue[0]
            self.p = self.p + _limit(p_ref - self.p, self.cfg.max_linear_speed * dt)
            w = _limit(_rel_rotvec(self.q, q_ref), self.cfg.max_angular_speed * dt)
            self.q = _qmul(self.q, quat_from_rotvec(w))
        elif action is not None and action[0] == "move":
            self.p, self.q, finished = action[1].step(dt)
        elif action is not None and action[0] == "stop":
            decel = action[1]
            speed, rate = float(np.linalg.norm(self.v)), float(np.linalg.norm(self.w))
            v = self.v * (max(speed - decel * dt, 0.0) / speed) if speed > 0 else self.v
            w = self.w * (max(rate - decel * dt, 0.0) / rate) if rate > 0 else self.w
            self.p = self.p + v * dt
            self.q = _qmul(self.q, quat_from_rotvec(w * dt))
            finished = not (np.any(v) or np.any(w))
        self.q /= np.linalg.norm(self.q)
        self.v = (self.p - p_old) / dt
        self.w = _rel_rotvec(q_old, self.q) / dt
        if finished:
            # a trapezoid or a stop ends at rest; the last step's difference quotient is not it
            self.v, self.w = np.zeros(3), np.zeros(3)
            if self.busy is action and action is not None:
                self.busy = None
                self._ready(2)
            else:
                self._set_background(None)

    def step(self):
        with self.lock:
            self.tick += 1
            self._script_cycle()
            self._motion_cycle()
            self._publish()
            return dict(self.values)

    # ---------------------------------------------------------------- hooks
    def set_pose(self, p6):
        with self.lock:
            p6 = np.asarray(p6, dtype=float)
            self.p, self.q = p6[:3].copy(), quat_from_rotvec(p6[3:])
            self.v, self.w = np.zeros(3), np.zeros(3)
            self.servoing = False
            if self.reg("int", 0) in REALTIME:
                # The script re-reads a realtime command's registers every cycle; point them at
                # the new pose so the arm holds it instead of heading back to the old set-point.
                for i in range(6):
                    self.values[f"input_double_register_{i}"] = float(p6[i])
            self._set_background(None)
            if self.busy:
                self.busy = None
                self._ready(2)
            self._publish()

    def set_safety(self, bit, on):
        with self.lock:
            if on:
                self.safety_bits |= bit
                self.v, self.w = np.zeros(3), np.zeros(3)   # category 1 stop, modelled as instant
                self.servoing = False
                self.busy = None
                self._set_background(None)
                if self.runtime_state == PLAYING:
                    self.runtime_state = PAUSED
            else:
                self.safety_bits &= ~bit
                if self.runtime_state == PAUSED:
                    self.runtime_state = STOPPED

    def _reset_program(self):
        """After a reboot: the program stopped, the registers cleared, the arm at rest where
        it stood."""
        self.values = {k: v for k, v in self.values.items()
                       if not k.startswith(("input_", "output_"))}
        self.runtime_state = STOPPED
        self.safety_bits = NORMAL_MODE
        self.executing = self.servoing = self.async_running = False
        self.busy = self.background = self.servo_target = None
        self.servo_queue.clear()
        self.v, self.w = np.zeros(3), np.zeros(3)
        self._publish()

    def _safety_name(self):
        if self.safety_bits & EMERGENCY_STOP_BIT:
            return "ROBOT_EMERGENCY_STOP"
        return "PROTECTIVE_STOP" if self.safety_bits & PROTECTIVE_STOP_BIT else "NORMAL"
