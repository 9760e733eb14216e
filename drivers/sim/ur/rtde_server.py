"""The simulated UR controller's RTDE server (port 30004): one session per client connection,
the handshake (``V v O I S P``), input recipes written into the controller's register table, each
command logged with the time its packet arrived, and the data packages sent every cycle at each
session's requested rate. The wire format is :mod:`dqpose.drivers.rtde`, shared with the driver.
"""
from __future__ import annotations

import collections
import socket
import struct
import threading
import time

from dqpose.drivers import rtde as rp

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


class Session:
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

class RTDEServer:
    """The RTDE side of :class:`~dqpose.drivers.sim.ur.server.URSim` (mixed into it, beside the
    :class:`~dqpose.drivers.sim.ur.model.Controller` whose ``lock``, ``values``, ``tick`` and
    ``dt`` it uses)."""

    def _init_rtde(self):
        self.sessions: list[Session] = []
        self.register_owner: dict[str, Session] = {}
        self.stream_paused_until = 0.0
        self.log: collections.deque = collections.deque(maxlen=self.cfg.log)
        self.log_base = 0            # index of log[0] in the whole run

    def _rtde_client(self, sess: Session):
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

    def _rtde_message(self, sess: Session, kind: int, body: bytes, arrived: float):
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

    def _stream(self, values: dict) -> None:
        """This cycle's data packages, to each started session whose rate falls on it."""
        if time.monotonic() >= self.stream_paused_until:
            for sess in list(self.sessions):
                if sess.started and sess.output is not None and self.tick % sess.every == 0:
                    sess.send(rp.frame(rp.DATA_PACKAGE, sess.output.pack(values)))
