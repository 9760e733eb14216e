"""What the Ctrl-C tests share: a ``dqpose`` command run as a terminal runs it (its own process
group, so a Ctrl-C is SIGINT to the whole group), when it exited after the Ctrl-C and how much
slower than on an idle core CPU-bound work ran meanwhile (:class:`Slowdown`), the UR simulators
and arm processes it started (found by their command line among its children), and a watcher of
a simulator's received commands and RTDE clients through its test hooks
(drivers/sim/ur/), read until the simulator goes away."""
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
from tests._polling import Slowdown  # noqa: E402 (after ROOT)

#: generous: a loaded machine may take this long before the tests give up waiting
EXIT_TIMEOUT = 120.0
#: how soon after one Ctrl-C a command has exited, in seconds of an idle core (a loaded machine
#: stretches it by the :class:`Slowdown` measured meanwhile)
PROMPT = 1.0
#: the ``python -m`` argument of an arm's own process (drivers.armproc: multiprocessing's spawn)
ARM_PROCESS = "--multiprocessing-fork"


def _as_a_terminal_starts():
    # a shell's background job (nohup, &) starts with SIGINT ignored, and a child inherits that:
    # the command would never see the Ctrl-C the test sends
    signal.signal(signal.SIGINT, signal.SIG_DFL)


class Command:
    """``python -m dqpose.cli ARGV`` in a new session; output collected as it comes."""

    def __init__(self, *argv: str):
        self.proc = subprocess.Popen([sys.executable, "-m", "dqpose.cli", *argv], cwd=ROOT,
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
        self.ended_at = None
        self.slowdown = 1.0
        self._probe = None
        self._waiter = threading.Thread(target=self._wait, daemon=True)
        self._waiter.start()

    def _wait(self):
        self.proc.wait()
        self.ended_at = time.monotonic()

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
        """One Ctrl-C: SIGINT to the process group, as a terminal sends it; the machine's
        :class:`Slowdown` is measured from now until the command has exited."""
        self._probe = Slowdown().start()
        self.interrupted_at = time.monotonic()
        os.killpg(self.proc.pid, signal.SIGINT)

    def wait(self, timeout: float = EXIT_TIMEOUT) -> int:
        self._waiter.join(timeout)
        if self._probe is not None:
            self.slowdown = self._probe.stop()
        if self._waiter.is_alive():
            os.killpg(self.proc.pid, signal.SIGKILL)
            self._waiter.join()
            raise AssertionError(f"dqpose still running {timeout} s after one Ctrl-C:\n"
                                 f"{self.stdout}\n{self.stderr}") from None
        for t in self._readers:
            t.join(10)
        return self.proc.returncode

    @property
    def exit_after(self) -> float:
        """Seconds from the Ctrl-C to the command's exit."""
        return self.ended_at - self.interrupted_at

    def assert_prompt(self) -> None:
        """The command exited within :data:`PROMPT` seconds of an idle core after the Ctrl-C,
        stretched by the slowdown measured meanwhile."""
        assert self.exit_after < PROMPT * self.slowdown, (
            f"exited {self.exit_after:.3f} s after the Ctrl-C, CPU-bound work {self.slowdown:.2f} "
            f"times slower than on an idle core meanwhile:\n{self.stderr[-3000:]}")

    def interrupted_when(self, predicate, what: str) -> int:
        """One Ctrl-C once ``predicate()`` holds (``what`` it waits for); the exit code. The
        command is killed whatever happens."""
        try:
            self.wait_for(predicate, what)
            self.interrupt()
            return self.wait()
        finally:
            self.kill()

    def kill(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self._waiter.join()


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
    """The pid and address of the UR simulator ``cmd`` started, once it serves there (its hooks
    answer with its pid: a simulator that could not have its address, or was too slow to start,
    is replaced by one on the next address)."""
    from dqpose.drivers.sim.ur import HOOK_PORT
    found: list = []

    def serving():
        for pid, argv in children(cmd.proc.pid, "dqpose.drivers.sim.ur"):
            host = argv[argv.index("--host") + 1]
            try:
                with socket.create_connection((host, HOOK_PORT), timeout=1.0) as s, \
                        s.makefile("rwb") as f:
                    f.write(b'{"op": "state"}\n')
                    f.flush()
                    if json.loads(f.readline()).get("pid") == pid:
                        found[:] = [pid, host]
                        return True
            except (OSError, ValueError):
                continue
        return False
    cmd.wait_for(serving, "a UR simulator serving", timeout)
    return found[0], found[1]


def alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def arm_process(cmd: Command, timeout: float = 120.0) -> int:
    """The pid of the arm process (drivers.armproc) ``cmd`` started."""
    found: list = []

    def started():
        found[:] = children(cmd.proc.pid, ARM_PROCESS)
        return bool(found)
    cmd.wait_for(started, "an arm process", timeout)
    return found[0][0]


class SimWatch:
    """Every command a UR simulator receives (``cmd``, ``mono``: when it arrived, this machine's
    CLOCK_MONOTONIC, as ``time.monotonic()``), and how many RTDE clients it has, polled through
    its hooks until it goes away; with each count, whether the process holding the arm's
    connections (:meth:`hold`) was still alive once the count was in."""

    def __init__(self, host: str):
        from dqpose.drivers.sim.ur import HOOK_PORT
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
        self.clients: list[tuple[float, int, bool]] = []    # (when, RTDE clients, holder alive)
        self.holder: int | None = None
        self.gone = threading.Event()
        self.thread = threading.Thread(target=self._poll, daemon=True)
        self.thread.start()

    def _ask(self, request: dict) -> dict | None:
        self.file.write((json.dumps(request) + "\n").encode())
        self.file.flush()
        line = self.file.readline()
        return json.loads(line) if line else None

    def _poll(self):
        since = 0
        try:
            while True:
                reply = self._ask({"op": "log", "since": since, "keys": ["cmd", "mono"]})
                if reply is None:
                    break
                self.entries += reply["entries"]
                since = reply["next"]
                state = self._ask({"op": "state"})
                if state is None:
                    break
                holder = self.holder
                self.clients.append((time.monotonic(), state["rtde_clients"],
                                     holder is not None and alive(holder)))
                time.sleep(0.01)
        except (OSError, ValueError):
            pass
        finally:
            self.gone.set()
            self.sock.close()

    def count(self, cmd: int) -> int:
        return sum(1 for e in self.entries if e["cmd"] == cmd)

    def hold(self, pid: int) -> None:
        """The process that holds the arm's RTDE connections (the command, or its arm
        process)."""
        self.holder = pid

    def linger(self, since: float) -> float:
        """How long the holder lived on once the simulator had no RTDE client left after
        ``since`` (the Ctrl-C): from the first count of none to the last that found the holder
        still alive (0 if none did).
        ur_rtde's disconnect ends a connection and then sleeps 0.5 s, and each destructor as
        long again: a process that disconnects its arm on its way out lingers a second or more;
        one whose end closes the connections, not at all."""
        t0 = next((t for t, n, _ in self.clients if t >= since and n == 0), None)
        if t0 is None:
            return 0.0
        return max((t for t, n, held in self.clients if t >= t0 and held), default=t0) - t0

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
