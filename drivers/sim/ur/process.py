"""The simulated UR controller run from tests and commands: :class:`URSimProcess` starts one in
its own process on a free loopback address and is the client of its test hooks;
:func:`servo_lag_cycles` reads a servo run's lag out of the hooks' log and history.
"""
from __future__ import annotations

import json
import socket
import time

import numpy as np

from dqpose.drivers.sim import end_process, start_process
from dqpose.drivers.sim.ur.model import HOOK_PORT, RTDE_PORT, SERVOL


class URSimProcess:
    """A simulator in its own process (the ur_rtde constructor holds the GIL, so a simulator in
    the client's process would deadlock), with the test hooks as methods."""

    def __init__(self, host: str | None = None, *, args: tuple = (), timeout: float = 10.0):
        candidates = [host] if host else [f"127.0.0.{i}" for i in range(20, 250)]
        last = "no address tried"
        for addr in candidates:
            if host is None and not address_free(addr):
                continue
            self.host = addr
            self.proc = start_process("dqpose.drivers.sim.ur", "--host", addr, *args)
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
        decoded it), ``cmd``, ``args``, ``ints``. ``cmd`` keeps one command, ``keys`` those
        fields."""
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


def address_free(host: str) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind((host, RTDE_PORT))
            return True
        except OSError:
            return False
