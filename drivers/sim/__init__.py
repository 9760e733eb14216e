"""Simulators that speak the devices' own protocols (``dqpose sim ur|piper|camera``)."""
from __future__ import annotations

import os
import subprocess
import sys
import threading


def stop_when_orphaned(stopping: threading.Event) -> None:
    """Set ``stopping`` once the process that started this one has ended, even by SIGKILL (a
    parent killed that way cannot stop its children; the re-parenting shows it instead)."""
    parent = os.getppid()

    def watch():
        while not stopping.wait(0.2):
            if os.getppid() != parent:
                stopping.set()
    threading.Thread(target=watch, name="orphan-watch", daemon=True).start()


def start_process(module: str, *args) -> subprocess.Popen:
    """``python -m module args --exit-with-parent`` from the repository root, output piped."""
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    return subprocess.Popen([sys.executable, "-m", module, *map(str, args), "--exit-with-parent"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=root)


def end_process(proc: subprocess.Popen, timeout: float = 5.0) -> None:
    """SIGTERM, SIGKILL after ``timeout`` s, reap it and close its pipes."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    for f in (proc.stdout, proc.stderr):
        if f is not None:
            f.close()
