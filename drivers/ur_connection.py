"""A UR controller's connections as ``ur_rtde`` keeps them: probing its ports, Nagle's algorithm
turned off again on the RTDE sockets, and how the interfaces end (a stop bounded in time, the
disconnects, or left to the process's end where ending them could hang or crash it)."""
from __future__ import annotations

import os
import socket
import threading

from dqpose.drivers.base import ArmError
from dqpose.drivers.rtde import RTDE_PORT


def probe(host: str, port: int, timeout: float) -> None:
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


def restore_nodelay(host: str) -> int:
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


class Closed:
    """What stands for ur_rtde's interfaces once the arm is closed."""

    def isConnected(self) -> bool:
        return False

    def __getattr__(self, name):
        raise ArmError("arm: closed")


#: how long each step of :meth:`~dqpose.drivers.ur.URArm.close` may take (s)
CLOSE_WAIT = 3.0


def end_script(ctrl, decel: float) -> None:
    try:
        ctrl.servoStop(decel)
        ctrl.stopScript()
    except RuntimeError:
        pass        # gone meanwhile


def within(seconds: float, fn, *args) -> bool:
    """``fn(*args)`` in a thread of its own (ur_rtde's calls leave the interpreter lock); True
    when it returned within ``seconds``."""
    t = threading.Thread(target=fn, args=args, daemon=True)
    t.start()
    t.join(seconds)
    return not t.is_alive()


def disconnect(interface) -> None:
    try:
        interface.disconnect()
    except RuntimeError:
        pass    # the controller is already gone


#: ur_rtde interfaces left to the process's end (:func:`keep_to_exit`)
_kept = 0


def keep_to_exit(interfaces) -> None:
    """Never destroy these ur_rtde interfaces: their destructors disconnect (0.5 s, holding the
    interpreter lock), also in the interpreter's own teardown at exit. Their connections and
    threads last until the process ends (:func:`kept_to_exit`)."""
    import ctypes
    global _kept
    for i in interfaces:
        ctypes.pythonapi.Py_IncRef(ctypes.py_object(i))
        _kept += 1


def kept_to_exit() -> bool:
    """Whether ur_rtde connections were left to the process's end: its threads then still run
    while the interpreter tears itself down, and crash it now and then (SIGSEGV, an exit code of
    -11 after a clean stop); a program that knows it is done ends with ``os._exit`` instead
    (``dqpose``'s commands do)."""
    return _kept > 0
