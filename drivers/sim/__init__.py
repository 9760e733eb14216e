"""Simulators that speak the devices' own protocols (``dqpose sim ur|piper|camera``)."""
from __future__ import annotations

import os
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
