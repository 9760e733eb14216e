"""The simulated UR controller's text interfaces: the dashboard server (port 29999: banner,
version, serial number, program and safety commands, answered as a controller words them) and
the script port (30003: an uploaded program, ``def ...: ... end``, starts playing at once).
"""
from __future__ import annotations

import re
import socket

from dqpose.drivers.sim.ur.model import PAUSED, PLAYING, PROTECTIVE_STOP_BIT


class TextPorts:
    """The dashboard and script ports of :class:`~dqpose.drivers.sim.ur.server.URSim` (mixed
    into it, beside the :class:`~dqpose.drivers.sim.ur.model.Controller` they command)."""

    def _dashboard_client(self, conn: socket.socket):
        answers = {
            "polyscopeversion":
                lambda: "URSoftware {}.{}.{}.{} (Jun 13 2023)".format(*self.cfg.version),
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
