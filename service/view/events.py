"""The JSON event lines a view prints on its standard error (``{"event": "drawn", ...}``), each
one whole line written at once: several threads say things (a server's world and its arms are
followed by threads of their own), and a line interleaved with another is not JSON."""
from __future__ import annotations

import json
import sys
import threading

_lock = threading.Lock()


def say(**event) -> None:
    line = json.dumps(event) + "\n"
    with _lock:
        sys.stderr.write(line)
        sys.stderr.flush()
