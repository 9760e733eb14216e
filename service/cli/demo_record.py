"""``--record FILE.mcap`` of ``dqpose demo`` (the demo's in-process server records) and of
``dqpose handeye capture`` (its solves): one file (the recorder writes into a folder beside it,
one file there, renamed to FILE at the end)."""
from __future__ import annotations

import os
import shutil

from dqpose.cli.common import fail, missing_extra

#: bounds no demo reaches: one file
_ONE_FILE = dict(max_bytes=1 << 40, max_seconds=1e9)


def open_file_recorder(cmd: str, path: str, target: str | None):
    """``(recorder, 0)``, or ``(None, exit code)`` having said why not."""
    from dqpose.errors import MissingExtra

    if target is not None:
        return None, fail(cmd, "--record: records the demo's own server; not with --server")
    if os.path.exists(path):
        return None, fail(cmd, f"--record {path}: exists already")
    try:
        from dqpose.record import open_recorder
        return open_recorder(path + ".parts", **_ONE_FILE), 0
    except MissingExtra as e:
        return None, missing_extra(cmd, e)
    except OSError as e:
        return None, fail(cmd, f"--record {path}: {e.strerror or e}")


def finish(recorder, path: str) -> str:
    """After the server stopped (which closed the recorder): the file moved to ``path`` (none
    when nothing was recorded)."""
    recorder.close()
    parts = recorder.files
    if parts:
        os.replace(parts[0], path)
    shutil.rmtree(recorder.directory, ignore_errors=True)
    if not parts:
        return f"recording: nothing was recorded, no {path}"
    return f"recording: {path} (dqpose view {path}; dqpose replay {path})"
