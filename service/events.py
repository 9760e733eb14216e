"""The JSON event lines the server's recorder, the views and the CLI print (``{"event": ...}``),
each one whole line written at once: several threads say things, and a line interleaved with
another is not JSON."""
from __future__ import annotations

import json
import sys
import threading

_lock = threading.Lock()


def say(**event) -> None:
    """One event line on standard output (what a supervising script reads)."""
    _write(sys.stdout, event)


def say_err(**event) -> None:
    """One event line on standard error (a view's, beside its page's output)."""
    _write(sys.stderr, event)


def _write(stream, event: dict) -> None:
    line = json.dumps(event) + "\n"
    with _lock:
        stream.write(line)
        stream.flush()
