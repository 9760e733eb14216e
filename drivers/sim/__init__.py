"""Simulators that speak the devices' own protocols (``dqpose sim ur|piper|camera``)."""
from __future__ import annotations

import collections
import json
import logging
import os
import subprocess
import sys
import threading

log = logging.getLogger("dqpose.sim")


def stop_when_orphaned(stopping: threading.Event) -> None:
    """Set ``stopping`` once the process that started this one has ended, even by SIGKILL (a
    parent killed that way cannot stop its children; the re-parenting shows it instead)."""
    parent = os.getppid()

    def watch():
        while not stopping.wait(0.2):
            if os.getppid() != parent:
                stopping.set()
    threading.Thread(target=watch, name="orphan-watch", daemon=True).start()


class SimProcess(subprocess.Popen):
    """A simulator process whose standard output and error are read as they come, each line
    logged on ``dqpose.sim`` (a JSON line: stdout at INFO, stderr at WARNING): a pipe nobody
    reads fills at 64 KB and then blocks the simulator's next write. The first line of its
    output (:meth:`first_line`, simulators print one when ready) and the last lines of its
    errors (:meth:`errors`, to say why it did not start) are kept."""

    def __init__(self, argv: list[str], name: str, **kw):
        super().__init__(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)
        self.name = name
        self._first: list[str] = []
        self._has_first = threading.Event()
        self._errors: collections.deque[str] = collections.deque(maxlen=20)
        self._readers = [
            threading.Thread(target=self._read, args=(self.stdout, "stdout", logging.INFO),
                             name=f"{name}-stdout", daemon=True),
            threading.Thread(target=self._read, args=(self.stderr, "stderr", logging.WARNING),
                             name=f"{name}-stderr", daemon=True)]
        for t in self._readers:
            t.start()

    def _read(self, pipe, stream: str, level: int) -> None:
        try:
            for line in pipe:
                line = line.rstrip("\n")
                if stream == "stdout" and not self._has_first.is_set():
                    self._first.append(line)
                    self._has_first.set()
                elif stream == "stderr":
                    self._errors.append(line)
                log.log(level, json.dumps({"event": "sim_output", "sim": self.name,
                                           "pid": self.pid, "stream": stream, "line": line}))
        except (OSError, ValueError):   # the pipe was closed under us
            pass
        finally:
            if stream == "stdout":
                self._has_first.set()   # no first line will come

    def first_line(self, timeout: float) -> str | None:
        """The first line the simulator wrote, None if it wrote none in ``timeout`` s or ended
        without one."""
        self._has_first.wait(timeout)
        return self._first[0] if self._first else None

    def join_output(self, timeout: float = 5.0) -> None:
        """Waits until the readers have logged everything (they end with the process)."""
        for t in self._readers:
            t.join(timeout)

    def stderr_tail(self) -> str:
        """The last lines the simulator wrote to standard error, once it has ended."""
        self.join_output()
        return "\n".join(self._errors).strip()


def start_process(module: str, *args) -> SimProcess:
    """``python -m module args --exit-with-parent`` from the repository root, its output
    logged (:class:`SimProcess`).

    In a session of its own: a Ctrl-C at the terminal goes to the whole foreground process
    group, and a simulated controller that ended on it at once left its client (ur_rtde)
    reconnecting for minutes while the parent was still stopping the arm. The parent, which
    handles the Ctrl-C, stops the arm and then ends the simulator (:func:`end_process`); a
    parent killed outright, or one that leaves its arm's connections for its own end to close
    (``dqpose handeye capture`` interrupted), still takes it along: the simulator, which looks
    every 0.2 s, ends by itself once its parent has (``--exit-with-parent``)."""
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    return SimProcess([sys.executable, "-m", module, *map(str, args), "--exit-with-parent"],
                      module, cwd=root, start_new_session=True)


#: s a simulator gets to end after SIGTERM before SIGKILL: they end within 0.1 s of it on an
#: idle machine, and keep nothing worth a longer wait (a command's Ctrl-C waits for it)
KILL_AFTER = 1.0


def end_process(proc: SimProcess, timeout: float = 5.0) -> None:
    """SIGTERM, SIGKILL after :data:`KILL_AFTER` s, reap it, log the rest of its output (for up
    to ``timeout`` s) and close its pipes."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(KILL_AFTER)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    proc.join_output(timeout)
    for f in (proc.stdout, proc.stderr):
        if f is not None:
            f.close()
