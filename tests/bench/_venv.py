"""A benchmark's own Python environment for a comparison package dqpose cannot import (OpenCV 4.x,
KinHEC): a venv under ``tests/bench/_build/``, created from PyPI on first use and reused after."""
from __future__ import annotations

import fcntl
import subprocess
import sys
from pathlib import Path


class BenchEnvUnavailable(RuntimeError):
    """The environment cannot be made (offline, no access to PyPI) or lacks what it needs."""


def probe(python: Path, code: str) -> str | None:
    """What ``code`` prints when run by ``python`` (a version), or None if it fails or is absent."""
    if not python.exists():
        return None
    r = subprocess.run([str(python), "-c", code], capture_output=True, text=True)
    return r.stdout.strip() if r.returncode == 0 else None


def bench_python(env: Path, requirements: tuple[str, ...], code: str, why: str,
                 fallback: str) -> tuple[Path, str]:
    """The interpreter of the venv ``env`` and what ``code`` prints there, installing
    ``requirements`` into a new venv when ``code`` fails (a lock keeps concurrent runs from
    building it twice). ``why`` says in the progress line why the environment exists; ``fallback``
    in the error what the caller can do instead."""
    py = env / "bin" / "python"
    env.parent.mkdir(parents=True, exist_ok=True)
    with open(env.parent / f"{env.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        version = probe(py, code)
        if version is not None:
            return py, version
        print(f"creating the environment {env} (once; {why}): pip install "
              f"{' '.join(requirements)}", file=sys.stderr)
        # The base interpreter, not this venv's: a venv of a venv still works, but needs no link
        # to ours.
        base = getattr(sys, "_base_executable", None) or sys.executable
        steps = ([base, "-m", "venv", "--clear", str(env)],
                 [str(py), "-m", "pip", "install", "-q", "--disable-pip-version-check",
                  "--timeout", "20", "--retries", "2", *requirements])
        for cmd in steps:
            r = subprocess.run(cmd, capture_output=True, text=True)
            if r.returncode != 0:
                tail = "\n".join((r.stderr or r.stdout).strip().splitlines()[-5:])
                raise BenchEnvUnavailable(
                    f"cannot create the environment {env} (offline, or no access to PyPI?): "
                    f"`{' '.join(cmd)}` failed:\n{tail}\n{fallback}")
        version = probe(py, code)
        if version is None:
            raise BenchEnvUnavailable(f"{env}: installed {' '.join(requirements)}, but "
                                      f"`{code}` still fails there")
        return py, version
