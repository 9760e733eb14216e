"""A simulated Universal Robots e-series controller that the unmodified ``ur_rtde`` client drives.

It speaks the controller's own protocols on one address (ports are fixed, so run one simulator
per loopback address, e.g. ``127.0.0.2``):

* RTDE on 30004: handshake (``V v O I S P``), data packages at the requested rate, input recipes
  written into one register table;
* the dashboard server on 29999 (banner, version, serial number, program and safety commands);
* the script port 30003: an uploaded program (``def ...: ... end``) starts playing at once.

The uploaded ``rtde_control`` script is not interpreted; its register protocol is modelled
instead: the command id in ``input_int_register_0``, arguments in the input registers,
``output_int_register_0`` answering 1 (ready) or 2 (done). Motion is tool-space only: servoL
follows its set-points ``servo_lag`` cycles late under velocity limits, moveL runs a trapezoidal
profile (rotation interpolated along with the translation), stops decelerate at the requested
rate. Joint-space commands are acknowledged and logged but do not move the model.

Test hooks are JSON lines on ``HOOK_PORT`` of the same address (see :class:`URSimProcess`):
read the state, the log of received commands and the pose history; set the pose; inject a
protective or emergency stop; drop every client connection; restart (a reboot as the clients
see it); pause the data stream; change the model's speed limits (an arm that falls behind its
set-points); exit.

Run it with ``dqpose sim ur --host 127.0.0.2`` or ``python -m dqpose.drivers.sim.ursim``.
"""
from __future__ import annotations

import argparse
import collections
import json
import os
import re
import signal
import socket
import struct
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np

from dqpose.drivers import rtde as rp
from dqpose.drivers.rotvec import quat_from_rotvec, rotvec_from_quat
from dqpose.drivers.sim import end_process, start_process, stop_when_orphaned
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
        return self.p0 + f * (self.p1 - self.p0), _qmul(self.q0, quat_from_rotvec(f * self.w)), False


# Linux's per-packet receive stamps (CLOCK_REALTIME, nanoseconds); Python names neither constant.
_SO_TIMESTAMPNS = 35


class _StampedReader:
    """RTDE messages off a session's socket, each with when its last byte reached this machine:
    the kernel's receive stamp of the packet (SO_TIMESTAMPNS) moved to CLOCK_MONOTONIC, so
    that what the reading thread was doing then (waiting for the GIL, descheduled) is not in
    it, as a controller's network card would see the set-points. Without kernel stamps: when
    this thread read the message."""

    def __init__(self, sock: socket.socket):
        self.sock, self.buf, self.stamp = sock, bytearray(), 0.0
        try:
            sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
        except OSError:
            pass

    def _fill(self) -> None:
        data, ancillary, _, _ = self.sock.recvmsg(65536, 64)
        if not data:
            raise ConnectionError("the client closed the connection")
        real, mono = time.time_ns(), time.monotonic_ns()
        stamp = mono
        for level, kind, payload in ancillary:
            if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(payload) >= 16:
                sec, nsec = struct.unpack("qq", payload[:16])
                stamp = sec * 1_000_000_000 + nsec - (real - mono)
        self.buf += data
        self.stamp = stamp * 1e-9

    def read(self) -> tuple[int, bytes, float]:
        """The next message's ``(kind, body, arrival)``."""
        while len(self.buf) < rp.HEADER.size:
            self._fill()
        size, kind = rp.header(self.buf)
        while len(self.buf) < size:
            self._fill()
        body = bytes(self.buf[rp.HEADER.size:size])
        del self.buf[:size]
        return kind, body, self.stamp


class _Session:
    """One RTDE client connection."""

    def __init__(self, sock, peer):
        self.sock, self.peer = sock, peer
        self.send_lock = threading.Lock()
        self.output: rp.Recipe | None = None
        self.every = 1
        self.inputs: dict[int, rp.Recipe] = {}
        self.started = False
        self.alive = True

    def send(self, data: bytes) -> bool:
        try:
            with self.send_lock:
                self.sock.sendall(data)
            return True
        except OSError:
            self.close()
            return False

    def close(self):
        self.alive = False
        self.started = False
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()


class URSim:
    """The controller: servers, the 500 Hz (or 125 Hz) cycle, the register protocol, the model."""

    def __init__(self, cfg: SimConfig | None = None):
        self.cfg = cfg = cfg or SimConfig()
        self.dt = cfg.period
        self.lock = threading.RLock()
        self.stopping = threading.Event()
        self.listeners: list[socket.socket] = []
        self.sessions: list[_Session] = []
        self.clients: list[socket.socket] = []      # dashboard and script connections
        self.register_owner: dict[str, _Session] = {}
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
        self.stream_paused_until = 0.0
        self.down_until = 0.0        # restart(): no connection taken until then
        self.scripts: list[str] = []
        self.log: collections.deque = collections.deque(maxlen=cfg.log)
        self.log_base = 0            # index of log[0] in the whole run
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

    def drop_connections(self):
        with self.lock:
            for s in self.sessions:
                s.close()
            self.sessions.clear()
            self.register_owner.clear()
            for c in self.clients:
                try:
                    c.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                c.close()
            self.clients.clear()

    def restart(self, down: float = 1.0):
        """A controller reboot as its clients see it: every connection closed, none taken for
        ``down`` seconds (each is closed at once: the ports stay bound, so a test's address is
        never free for another simulator to take meanwhile), then the controller is back with
        its program stopped, the registers cleared, the arm at rest where it stood."""
        with self.lock:
            self.down_until = time.monotonic() + float(down)
            self.drop_connections()
            self.values = {k: v for k, v in self.values.items()
                           if not k.startswith(("input_", "output_"))}
            self.runtime_state = STOPPED
            self.safety_bits = NORMAL_MODE
            self.executing = self.servoing = self.async_running = False
            self.busy = self.background = self.servo_target = None
            self.servo_queue.clear()
            self.v, self.w = np.zeros(3), np.zeros(3)
            self.stream_paused_until = 0.0
            self._publish()

    def state(self) -> dict:
        with self.lock:
            return {
                "tick": self.tick, "time": self.tick * self.dt, "period": self.dt,
                "pose": self.values["actual_TCP_pose"], "runtime_state": self.runtime_state,
                "safety_status_bits": self.safety_bits, "servoing": self.servoing,
                "busy": self.busy[0] if self.busy else None,
                # rounding leaves ~1e-14 rad/s on a resting arm
                "moving": bool(np.linalg.norm(self.v) > 1e-9 or np.linalg.norm(self.w) > 1e-9),
                "output_int_register_0": self.values.get("output_int_register_0", 0),
                "rtde_clients": sum(1 for s in self.sessions if s.alive),
                "scripts": len(self.scripts), "version": list(self.cfg.version),
                "pid": os.getpid(),
            }

    def hook(self, req: dict) -> dict:
        op = req.get("op")
        if op == "state":
            return self.state()
        if op == "set_pose":
            self.set_pose(req["pose"])
            return self.state()
        if op in ("protective_stop", "emergency_stop"):
            bit = PROTECTIVE_STOP_BIT if op == "protective_stop" else EMERGENCY_STOP_BIT
            self.set_safety(bit, bool(req.get("on", True)))
            return self.state()
        if op == "drop":
            self.drop_connections()
            return {"dropped": True}
        if op == "restart":
            self.restart(float(req.get("down", 1.0)))
            return {"restarted": True}
        if op == "set_speed":
            # the model's speed limits: an arm slowed down (or held back) that no longer
            # keeps up with its set-points
            with self.lock:
                self.cfg.max_linear_speed = float(req.get("linear", self.cfg.max_linear_speed))
                self.cfg.max_angular_speed = float(req.get("angular",
                                                           self.cfg.max_angular_speed))
            return {"max_linear_speed": self.cfg.max_linear_speed,
                    "max_angular_speed": self.cfg.max_angular_speed}
        if op == "pause_stream":
            self.stream_paused_until = time.monotonic() + float(req.get("seconds", 1.0))
            return {"paused": True}
        if op == "log":
            # optional "cmd" (only that command) and "keys" (only those fields): a minute of
            # set-point arrival times at 500 Hz stays a small reply
            cmd, keys = req.get("cmd"), req.get("keys")
            with self.lock:
                since = max(int(req.get("since", 0)) - self.log_base, 0)
                entries = list(self.log)[since:]
                nxt = self.log_base + len(self.log)
            if cmd is not None:
                entries = [e for e in entries if e["cmd"] == cmd]
            if keys is not None:
                entries = [{k: e[k] for k in keys} for e in entries]
            return {"entries": entries, "next": nxt}
        if op == "history":
            since = int(req.get("since_tick", 0))
            with self.lock:
                return {"history": [h for h in self.history if h[0] >= since]}
        if op == "kill":
            threading.Timer(0.05, os._exit, args=(0,)).start()
            return {"killed": True}
        raise ValueError(f"op: unknown hook operation {op!r}")

    # ---------------------------------------------------------------- RTDE server
    def _rtde_client(self, sess: _Session):
        try:
            reader = _StampedReader(sess.sock)
            while sess.alive and not self.stopping.is_set():
                self._rtde_message(sess, *reader.read())
        except (OSError, ConnectionError, struct.error):
            pass
        finally:
            with self.lock:
                for name in [n for n, s in self.register_owner.items() if s is sess]:
                    del self.register_owner[name]
                if sess in self.sessions:
                    self.sessions.remove(sess)
            sess.close()

    def _rtde_message(self, sess: _Session, kind: int, body: bytes, arrived: float):
        if kind == rp.REQUEST_PROTOCOL_VERSION:
            ok = len(body) >= 2 and struct.unpack(">H", body[:2])[0] in (1, 2)
            sess.send(rp.frame(kind, bytes([int(ok)])))
        elif kind == rp.GET_URCONTROL_VERSION:
            sess.send(rp.frame(kind, struct.pack(">IIII", *self.cfg.version)))
        elif kind == rp.SETUP_OUTPUTS:
            freq = struct.unpack(">d", body[:8])[0]
            names = [n for n in body[8:].decode("ascii", "replace").split(",") if n]
            types = [rp.output_type(n) or "NOT_FOUND" for n in names]
            ok = names and "NOT_FOUND" not in types and 0 < freq <= 1.0 / self.dt + 1e-9
            if ok:
                sess.output = rp.Recipe(1, names, types, freq)
                sess.every = max(1, round(1.0 / (self.dt * freq)))
            sess.send(rp.frame(kind, bytes([1 if ok else 0]) + ",".join(types).encode()))
        elif kind == rp.SETUP_INPUTS:
            names = [n for n in body.decode("ascii", "replace").split(",") if n]
            with self.lock:
                types = []
                for n in names:
                    owner = self.register_owner.get(n)
                    t = rp.input_type(n)
                    types.append("NOT_FOUND" if t is None else
                                 "IN_USE" if owner is not None and owner is not sess else t)
                ok = names and all(t in rp.FORMATS for t in types)
                rid = 0
                if ok:
                    rid = len(sess.inputs) + 1
                    sess.inputs[rid] = rp.Recipe(rid, names, types)
                    for n in names:
                        self.register_owner[n] = sess
            sess.send(rp.frame(kind, bytes([rid]) + ",".join(types).encode()))
        elif kind == rp.START:
            ok = sess.output is not None
            sess.send(rp.frame(kind, bytes([int(ok)])))
            sess.started = ok
        elif kind == rp.PAUSE:
            sess.started = False
            sess.send(rp.frame(kind, b"\x01"))
        elif kind == rp.DATA_PACKAGE and body:
            recipe = sess.inputs.get(body[0])
            if recipe is None:
                return
            fields = recipe.unpack(body[1:])
            with self.lock:
                self.values.update(fields)
                if "input_int_register_0" in fields:
                    if len(self.log) == self.log.maxlen:
                        self.log_base += 1      # the oldest entry falls out
                    self.log.append({
                        "tick": self.tick, "time": self.tick * self.dt,
                        "mono": arrived, "read": time.monotonic(), "recipe": recipe.id,
                        "cmd": fields["input_int_register_0"],
                        "args": [fields[n] for n in recipe.names if n.startswith("input_double")],
                        "ints": [fields[n] for n in recipe.names[1:]
                                 if n.startswith("input_int")],
                    })

    # ---------------------------------------------------------------- dashboard and script port
    def _dashboard_client(self, conn: socket.socket):
        answers = {
            "polyscopeversion": lambda: "URSoftware {}.{}.{}.{} (Jun 13 2023)".format(*self.cfg.version),
            "version": lambda: "{}.{}.{}.{}".format(*self.cfg.version),
            "get serial number": lambda: self.cfg.serial,
            "get robot model": lambda: "UR5",
            "is in remote control": lambda: "true",
            "robotmode": lambda: "Robotmode: RUNNING",
            "running": lambda: f"Program running: {str(self.runtime_state == PLAYING).lower()}",
            "programstate": lambda: ("PLAYING rtde_control" if self.runtime_state == PLAYING
                                     else "STOPPED rtde_control"),
            "safetystatus": lambda: "Safetystatus: " + self._safety_name(),
            "safetymode": lambda: "Safetymode: " + self._safety_name(),
            "get operational mode": lambda: "AUTOMATIC",
            "power on": lambda: "Powering on", "power off": lambda: "Powering off",
            "brake release": lambda: "Brake releasing",
            "close popup": lambda: "closing popup",
            "close safety popup": lambda: "closing safety popup",
            "isprogramsaved": lambda: "true rtde_control",
            "get loaded program": lambda: "rtde_control",
        }
        try:
            conn.sendall(b"Connected: Universal Robots Dashboard Server\n")
            buf = b""
            while not self.stopping.is_set():
                data = conn.recv(4096)
                if not data:
                    break
                buf += data
                while b"\n" in buf:
                    line, buf = buf.split(b"\n", 1)
                    cmd = line.decode("utf-8", "replace").strip()
                    key = cmd.lower()
                    if key == "quit":
                        conn.sendall(b"Disconnected\n")
                        return
                    if key == "stop":
                        with self.lock:
                            self._end_program()
                        reply = "Stopped"
                    elif key == "play":
                        reply = "Starting program" if self.scripts else "Failed to execute: play"
                        if self.scripts:
                            self.start_program(self.scripts[-1])
                    elif key == "pause":
                        with self.lock:
                            if self.runtime_state == PLAYING:
                                self.runtime_state = PAUSED
                        reply = "Pausing program"
                    elif key == "unlock protective stop":
                        self.set_safety(PROTECTIVE_STOP_BIT, False)
                        reply = "Protective stop releasing"
                    elif key.startswith("popup "):
                        reply = "showing popup"
                    elif key in answers:
                        reply = answers[key]()
                    else:
                        reply = f"could not understand: '{cmd}'"
                    conn.sendall((reply + "\n").encode())
        except OSError:
            pass
        finally:
            conn.close()

    def _safety_name(self):
        if self.safety_bits & EMERGENCY_STOP_BIT:
            return "ROBOT_EMERGENCY_STOP"
        return "PROTECTIVE_STOP" if self.safety_bits & PROTECTIVE_STOP_BIT else "NORMAL"

    _PROGRAM = re.compile(r"^def\s+\w+\s*\(\s*\)\s*:.*^end\s*$", re.S | re.M)

    def _script_client(self, conn: socket.socket):
        buf = ""
        try:
            while not self.stopping.is_set():
                data = conn.recv(65536)
                if not data:
                    break
                buf += data.decode("utf-8", "replace")
                # A whole program has arrived when its top-level "def" is closed by an "end".
                if self._PROGRAM.search(buf):
                    self.start_program(buf)
                    buf = ""
        except OSError:
            pass
        finally:
            conn.close()

    # ---------------------------------------------------------------- serving
    def _listen(self, port):
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind((self.cfg.host, port))
        s.listen(8)
        self.listeners.append(s)
        return s

    def _accept(self, listener, handler, kind):
        while not self.stopping.is_set():
            try:
                conn, peer = listener.accept()
            except OSError:
                return
            if kind != "hook" and time.monotonic() < self.down_until:
                conn.close()            # rebooting
                continue
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            # Reads block (idle clients are normal); a send blocked for 1 s means a client that
            # stopped reading, and the cycle must not wait for it.
            conn.setsockopt(socket.SOL_SOCKET, socket.SO_SNDTIMEO, struct.pack("ll", 1, 0))
            if kind == "rtde":
                arg = _Session(conn, peer)
                with self.lock:
                    self.sessions.append(arg)
            else:
                arg = conn
                if kind != "hook":
                    with self.lock:
                        self.clients.append(conn)
            threading.Thread(target=handler, args=(arg,), daemon=True).start()

    def _hook_client(self, conn: socket.socket):
        f = conn.makefile("rwb")
        try:
            for line in f:
                try:
                    reply = {"ok": True, **self.hook(json.loads(line))}
                except Exception as e:  # a bad hook request must not take the controller down
                    reply = {"ok": False, "error": f"{type(e).__name__}: {e}"}
                f.write((json.dumps(reply) + "\n").encode())
                f.flush()
        except OSError:
            pass
        finally:
            conn.close()

    def bind(self):
        """Open every port (raises OSError if the address is taken)."""
        self._servers = [
            (self._listen(RTDE_PORT), self._rtde_client, "rtde"),
            (self._listen(DASHBOARD_PORT), self._dashboard_client, "dashboard"),
            (self._listen(SCRIPT_PORT), self._script_client, "script"),
            (self._listen(self.cfg.hook_port), self._hook_client, "hook"),
        ]

    def serve_forever(self):
        for listener, handler, kind in self._servers:
            threading.Thread(target=self._accept, args=(listener, handler, kind), daemon=True).start()
        next_t = time.monotonic()
        while not self.stopping.is_set():
            next_t += self.dt
            values = self.step()
            if time.monotonic() >= self.stream_paused_until:
                for sess in list(self.sessions):
                    if sess.started and sess.output is not None and self.tick % sess.every == 0:
                        sess.send(rp.frame(rp.DATA_PACKAGE, sess.output.pack(values)))
            delay = next_t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            elif delay < -0.05:
                next_t = time.monotonic()   # fell far behind (machine busy): do not burst
        self.shutdown()

    def shutdown(self):
        self.stopping.set()
        for s in self.listeners:
            s.close()
        self.drop_connections()


# -------------------------------------------------------------------- CLI
def _parse_pose(text: str):
    vals = [float(x) for x in text.replace(",", " ").split()]
    if len(vals) != 6:
        raise argparse.ArgumentTypeError("pose: expected 6 numbers x y z rx ry rz")
    return tuple(vals)


def _parse_version(text: str):
    vals = tuple(int(x) for x in text.split("."))
    if len(vals) != 4:
        raise argparse.ArgumentTypeError("version: expected major.minor.bugfix.build")
    return vals


def main(argv: list[str] | None = None) -> int:
    d = SimConfig()
    ap = argparse.ArgumentParser(prog="dqpose sim ur", description=__doc__.split("\n\n")[0])
    ap.add_argument("--host", default=d.host, help="address to serve on (default %(default)s; one simulator per address, 0.0.0.0 only inside a container)")
    ap.add_argument("--hook-port", type=int, default=d.hook_port, help="JSON-lines test hooks port")
    ap.add_argument("--pose", type=_parse_pose, default=d.pose,
                    help="initial TCP pose 'x y z rx ry rz' (metres, rotation vector in radians)")
    ap.add_argument("--version", type=_parse_version, default=d.version,
                    help="controller version major.minor.bugfix.build (major 3 = CB3, 125 Hz)")
    ap.add_argument("--servo-lag", type=int, default=d.servo_lag,
                    help="servo lag in controller cycles (2 ms e-series, 8 ms CB3; "
                         "default %(default)s)")
    ap.add_argument("--max-linear-speed", type=float, default=d.max_linear_speed,
                    metavar="M_PER_S",
                    help="the model's tool speed limit in m/s (default %(default)g)")
    ap.add_argument("--max-angular-speed", type=float, default=d.max_angular_speed,
                    metavar="RAD_PER_S",
                    help="the model's tool rotation speed limit in rad/s (default %(default)g)")
    ap.add_argument("--exit-with-parent", action="store_true",
                    help="stop when the process that started this one ends (even if killed)")
    args = ap.parse_args(argv)
    if args.servo_lag < 0:
        ap.error("--servo-lag: must be >= 0")
    cfg = SimConfig(host=args.host, hook_port=args.hook_port, pose=args.pose, version=args.version,
                    servo_lag=args.servo_lag, max_linear_speed=args.max_linear_speed,
                    max_angular_speed=args.max_angular_speed)
    sim = URSim(cfg)
    try:
        sim.bind()
    except OSError as e:
        print(f"ursim: cannot serve on {cfg.host}: {e}", file=sys.stderr)
        return 3
    signal.signal(signal.SIGTERM, lambda *_: sim.stopping.set())
    if args.exit_with_parent:
        stop_when_orphaned(sim.stopping)
    print(f"ursim {'.'.join(map(str, cfg.version))} on {cfg.host}: RTDE {RTDE_PORT}, dashboard "
          f"{DASHBOARD_PORT}, script {SCRIPT_PORT}, hooks {cfg.hook_port}; "
          f"{1 / cfg.period:.0f} Hz", flush=True)
    try:
        sim.serve_forever()
    except KeyboardInterrupt:
        sim.shutdown()
    return 0


# -------------------------------------------------------------------- running it from tests
class URSimProcess:
    """A simulator in its own process (the ur_rtde constructor holds the GIL, so a simulator in
    the client's process would deadlock), with the test hooks as methods."""

    def __init__(self, host: str | None = None, *, args: tuple = (), timeout: float = 10.0):
        candidates = [host] if host else [f"127.0.0.{i}" for i in range(20, 250)]
        last = "no address tried"
        for addr in candidates:
            if host is None and not _address_free(addr):
                continue
            self.host = addr
            self.proc = start_process("dqpose.drivers.sim.ursim", "--host", addr, *args)
            err = self._wait_ready(timeout)
            if err is None:
                return
            last = err
        raise RuntimeError(f"could not start the UR simulator: {last}")

    def _wait_ready(self, timeout):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                return self.proc.stderr_tail() or f"exit code {self.proc.returncode}"
            try:
                self._conn = socket.create_connection((self.host, HOOK_PORT), timeout=0.2)
                self._conn.settimeout(timeout)
                self._file = self._conn.makefile("rwb")
            except OSError:
                time.sleep(0.05)
                continue
            # Another process's simulator may have taken the address between the check that it
            # was free and our simulator's bind (ours then exits): only ours will do.
            if self.state().get("pid") == self.proc.pid:
                return None
            self._conn.close()
            self.proc.kill()
            self.proc.wait()
            return f"{self.host} was taken by another simulator"
        self.proc.kill()
        self.proc.wait()
        return f"no answer on {self.host}:{HOOK_PORT} within {timeout} s"

    def call(self, op: str, **kw) -> dict:
        self._file.write((json.dumps({"op": op, **kw}) + "\n").encode())
        self._file.flush()
        reply = json.loads(self._file.readline())
        if not reply.pop("ok"):
            raise RuntimeError(reply["error"])
        return reply

    def state(self) -> dict:
        return self.call("state")

    def set_pose(self, p6) -> dict:
        return self.call("set_pose", pose=[float(x) for x in p6])

    def set_speed(self, linear: float | None = None, angular: float | None = None) -> dict:
        """The model's speed limits (m/s, rad/s) from now on."""
        kw = {k: float(v) for k, v in (("linear", linear), ("angular", angular)) if v is not None}
        return self.call("set_speed", **kw)

    def restart(self, down: float = 1.0) -> dict:
        """The controller reboots: its connections close, it takes none for ``down`` s, its
        program stops (:meth:`URSim.restart`)."""
        return self.call("restart", down=float(down))

    def pause_stream(self, seconds: float) -> dict:
        """No data packages for ``seconds`` (the connections stay open): a stalled controller."""
        return self.call("pause_stream", seconds=float(seconds))

    def protective_stop(self, on: bool = True) -> dict:
        return self.call("protective_stop", on=on)

    def log(self, since: int = 0, cmd: int | None = None, keys: list | None = None) -> dict:
        """Received commands from index ``since`` (``next`` is where the next call starts); each
        entry has the cycle ``tick``, ``mono`` (this machine's CLOCK_MONOTONIC when the package
        arrived: the kernel's receive stamp), ``read`` (when the simulator's thread had read and
        decoded it), ``cmd``, ``args``, ``ints``. ``cmd`` keeps one command, ``keys`` those fields."""
        kw = {k: v for k, v in (("cmd", cmd), ("keys", keys)) if v is not None}
        return self.call("log", since=since, **kw)

    def history(self, since_tick: int = 0) -> np.ndarray:
        """Rows ``[tick, time, x, y, z, rx, ry, rz]``."""
        return np.array(self.call("history", since_tick=since_tick)["history"]).reshape(-1, 8)

    def kill(self):
        """SIGKILL: the controller vanishes without closing its connections."""
        self.proc.kill()
        self.proc.wait()

    def close(self):
        try:
            self._conn.close()
        except (AttributeError, OSError):
            pass
        end_process(self.proc)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def servo_lag_cycles(entries: list[dict], history: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """For each servoL command in a hook log, the cycles from its receipt until the arm stood
    within ``tol`` metres of it or of a later set-point (a set-point overwritten before the
    controller read it is reached when its successor is). -1 where it never was."""
    cmds = [e for e in entries if e["cmd"] == SERVOL]
    targets = np.array([e["args"][:3] for e in cmds]).reshape(-1, 3)
    ticks, pos = history[:, 0], history[:, 2:5]
    # distance from every history sample to every set-point, then "reached set-point j or later"
    dist = np.linalg.norm(pos[:, None, :] - targets[None, :, :], axis=-1) <= tol
    reached_later = np.flip(np.logical_or.accumulate(np.flip(dist, axis=1), axis=1), axis=1)
    lags = np.full(len(cmds), -1)
    for i, e in enumerate(cmds):
        hit = np.nonzero((ticks > e["tick"]) & reached_later[:, i])[0]
        if hit.size:
            lags[i] = int(ticks[hit[0]] - e["tick"])
    return lags


def _address_free(host: str) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind((host, RTDE_PORT))
            return True
        except OSError:
            return False


if __name__ == "__main__":
    sys.exit(main())
