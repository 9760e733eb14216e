"""The simulated UR controller as one process serves it: :class:`URSim` is the model
(:class:`~dqpose.drivers.sim.ur.model.Controller`) with its four servers (RTDE, dashboard,
script, hooks) on one address, a thread per connection, and the cycle that steps the model and
streams its state.
"""
from __future__ import annotations

import socket
import struct
import threading
import time

from dqpose.drivers.sim.ur.dashboard import TextPorts
from dqpose.drivers.sim.ur.hooks import Hooks
from dqpose.drivers.sim.ur.model import (
    DASHBOARD_PORT,
    RTDE_PORT,
    SCRIPT_PORT,
    Controller,
    SimConfig,
)
from dqpose.drivers.sim.ur.rtde_server import RTDEServer, Session

#: how much missed time the model catches up on at most, seconds (beyond, the arm lags)
CATCH_UP = 0.5


class URSim(Controller, RTDEServer, TextPorts, Hooks):
    """The controller: servers, the 500 Hz (or 125 Hz) cycle, the register protocol, the model."""

    def __init__(self, cfg: SimConfig | None = None):
        super().__init__(cfg)
        self.stopping = threading.Event()
        self.listeners: list[socket.socket] = []
        self.clients: list[socket.socket] = []      # dashboard and script connections
        self.down_until = 0.0        # restart(): no connection taken until then
        self._init_rtde()

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
            self.stream_paused_until = 0.0
            self._reset_program()

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
                arg = Session(conn, peer)
                with self.lock:
                    self.sessions.append(arg)
            else:
                arg = conn
                if kind != "hook":
                    with self.lock:
                        self.clients.append(conn)
            threading.Thread(target=handler, args=(arg,), daemon=True).start()

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
            threading.Thread(target=self._accept, args=(listener, handler, kind),
                             daemon=True).start()
        next_t = time.monotonic()
        while not self.stopping.is_set():
            next_t += self.dt
            values = self.step()
            self._stream(values)
            delay = next_t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            elif delay < -0.05:
                # Fell far behind (a starved machine): a real arm would have moved on in the
                # meantime, so the model steps through the missed cycles (at most CATCH_UP s of
                # them) without streaming them, and the stream resumes from now without a burst.
                for _ in range(int(min(-delay, CATCH_UP) / self.dt)):
                    self.step()
                next_t = time.monotonic()
        self.shutdown()

    def shutdown(self):
        self.stopping.set()
        for s in self.listeners:
            s.close()
        self.drop_connections()
