"""The simulated UR controller's test hooks: JSON lines on ``HOOK_PORT`` (one request, one
reply per line; :class:`~dqpose.drivers.sim.ur.process.URSimProcess` is their client). Read the
state, the log of received commands and the pose history; set the pose; inject a protective or
emergency stop; drop every client connection; restart (a reboot as the clients see it); pause
the data stream; change the model's speed limits (an arm that falls behind its set-points);
exit.
"""
from __future__ import annotations

import json
import os
import socket
import threading
import time

import numpy as np

from dqpose.drivers.sim.ur.model import EMERGENCY_STOP_BIT, PROTECTIVE_STOP_BIT


class Hooks:
    """The hooks of :class:`~dqpose.drivers.sim.ur.server.URSim` (mixed into it)."""

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
