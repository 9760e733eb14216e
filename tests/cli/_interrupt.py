"""What the Ctrl-C tests share: a ``dqpose`` command run as a terminal runs it (its own process
group, so a Ctrl-C is SIGINT to the whole group), the UR simulators it started (found by their
command line among its children), and a watcher of a simulator's received commands through its
test hooks (drivers/sim/ursim.py), read until the simulator goes away."""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
#: generous: a loaded machine may take this long; the tests do not time anything
EXIT_TIMEOUT = 120.0


def _as_a_terminal_starts():
    # a shell's background job (nohup, &) starts with SIGINT ignored, and a child inherits that:
    # the command would never see the Ctrl-C the test sends
    signal.signal(signal.SIGINT, signal.SIG_DFL)


class Command:
    """``python -m service.cli ARGV`` in a new session; output collected as it comes."""

    def __init__(self, *argv: str):
        self.proc = subprocess.Popen([sys.executable, "-m", "service.cli", *argv], cwd=ROOT,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                     start_new_session=True, preexec_fn=_as_a_terminal_starts)
        self.out: list[str] = []
        self.err: list[str] = []
        self._readers = [threading.Thread(target=self._read, args=(f, into), daemon=True)
                         for f, into in ((self.proc.stdout, self.out),
                                         (self.proc.stderr, self.err))]
        for t in self._readers:
            t.start()
        self.interrupted_at = None

    @staticmethod
    def _read(f, into):
        for line in f:
            into.append(line)

    @property
    def stdout(self) -> str:
        return "".join(self.out)

    @property
    def stderr(self) -> str:
        return "".join(self.err)

    def wait_for(self, predicate, what: str, timeout: float = 300.0) -> None:
        deadline = time.monotonic() + timeout
        while not predicate():
            if self.proc.poll() is not None:
                raise AssertionError(f"dqpose ended ({self.proc.returncode}) before {what}:\n"
                                     f"{self.stdout}\n{self.stderr}")
            if time.monotonic() > deadline:
                raise AssertionError(f"no {what} within {timeout} s:\n{self.stdout}\n"
                                     f"{self.stderr}")
            time.sleep(0.05)

    def interrupt(self) -> None:
        """One Ctrl-C: SIGINT to the process group, as a terminal sends it."""
        self.interrupted_at = time.monotonic()
        os.killpg(self.proc.pid, signal.SIGINT)

    def wait(self, timeout: float = EXIT_TIMEOUT) -> int:
        try:
            code = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()
            raise AssertionError(f"dqpose still running {timeout} s after one Ctrl-C:\n"
                                 f"{self.stdout}\n{self.stderr}") from None
        for t in self._readers:
            t.join(10)
        return code

    def kill(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()


def children(pid: int, module: str) -> list[tuple[int, list[str]]]:
    """``(pid, argv)`` of the processes whose parent is ``pid`` running ``python -m module``."""
    out = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                ppid = int(f.read().rsplit(")", 1)[1].split()[1])
            if ppid != pid:
                continue
            with open(f"/proc/{entry}/cmdline", "rb") as f:
                argv = f.read().decode().split("\0")
        except (OSError, ValueError, IndexError):
            continue
        if module in argv:
            out.append((int(entry), argv))
    return out


def sim_host(cmd: Command, timeout: float = 120.0) -> tuple[int, str]:
    """The pid and address of the UR simulator ``cmd`` started."""
    found: list = []

    def started():
        found[:] = children(cmd.proc.pid, "drivers.sim.ursim")
        return bool(found)
    cmd.wait_for(started, "a UR simulator", timeout)
    pid, argv = found[0]
    return pid, argv[argv.index("--host") + 1]


def alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


class SimWatch:
    """Every command a UR simulator receives (``cmd``, ``mono``: when it arrived, this machine's
    CLOCK_MONOTONIC, as ``time.monotonic()``), polled through its hooks until it goes away."""

    def __init__(self, host: str):
        from drivers.sim.ursim import HOOK_PORT
        deadline = time.monotonic() + 60
        while True:
            try:
                self.sock = socket.create_connection((host, HOOK_PORT), timeout=10)
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.05)
        self.file = self.sock.makefile("rwb")
        self.entries: list[dict] = []
        self.gone = threading.Event()
        self.thread = threading.Thread(target=self._poll, daemon=True)
        self.thread.start()

    def _poll(self):
        since = 0
        try:
            while True:
                self.file.write((json.dumps({"op": "log", "since": since,
                                             "keys": ["cmd", "mono"]}) + "\n").encode())
                self.file.flush()
                line = self.file.readline()
                if not line:
                    break
                reply = json.loads(line)
                self.entries += reply["entries"]
                since = reply["next"]
                time.sleep(0.01)
        except (OSError, ValueError):
            pass
        finally:
            self.gone.set()
            self.sock.close()

    def count(self, cmd: int) -> int:
        return sum(1 for e in self.entries if e["cmd"] == cmd)

    def wait_gone(self, timeout: float = EXIT_TIMEOUT) -> None:
        assert self.gone.wait(timeout), "the simulator outlived the command"


def assert_stopped_after(entries: list[dict], since: float, motion: tuple, stops: tuple) -> float:
    """After ``since`` (the Ctrl-C), a stop command arrived and no motion command came after
    it; returns how long after ``since`` the first stop arrived (for the record, not asserted)."""
    after = [e for e in entries if e["mono"] >= since]
    first_stop = next((i for i, e in enumerate(after) if e["cmd"] in stops), None)
    assert first_stop is not None, f"no stop command after the Ctrl-C: {after[-10:]}"
    moved = [e for e in after[first_stop:] if e["cmd"] in motion]
    assert not moved, f"motion commands after the stop: {moved[:5]}"
    return after[first_stop]["mono"] - since
