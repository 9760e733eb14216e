"""What the fresh-install tests share: a new virtual environment with nothing in it, the project's
sources copied out as a clone has them (no build output), and a ``dqpose serve`` started from
such an environment.

These tests install from the package index (pip's cache makes a rerun quicker) and take minutes,
so they are marked ``install`` and left out of the default run: ``make test ARGS="-m install"``
runs them (CI does, after ``make test``)."""
from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

# What a clone holds that an install reads (the rest is tests, docs, examples).
SOURCES = ("pyproject.toml", "setup.py", "README.md", "MANIFEST.in", "proto", "service", "drivers")
# Build output and caches of the working tree: a clone has none of them.
_NOT_SOURCE = shutil.ignore_patterns("__pycache__", "*.so", "_proto", "build", "*.egg-info")


def copy_sources(dest: str, names=SOURCES) -> str:
    """The sources ``names`` (files or folders of the repository) copied into ``dest``."""
    os.makedirs(dest, exist_ok=True)
    for name in names:
        src = os.path.join(ROOT, name)
        if os.path.isdir(src):
            shutil.copytree(src, os.path.join(dest, name), ignore=_NOT_SOURCE)
        else:
            shutil.copy2(src, os.path.join(dest, name))
    return dest


class Venv:
    """A virtual environment created by this test run's interpreter, with nothing installed."""

    def __init__(self, path: str):
        self.path = path
        subprocess.run([sys.executable, "-m", "venv", "--clear", path], check=True)
        self.bin = os.path.join(path, "bin")
        self.python = os.path.join(self.bin, "python")

    def env(self, **extra: str) -> dict:
        """The environment of a shell with this venv activated (and not this test's venv)."""
        env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH")}
        env.update(extra)
        env["PATH"] = self.bin + os.pathsep + env.get("PATH", "")
        env["VIRTUAL_ENV"] = self.path
        env["PYTHONWARNINGS"] = "ignore"     # setuptools' boxed notices, pip's upgrade hints
        return env

    def run(self, *argv: str, cwd: str | None = None, timeout: float = 900, check: bool = True,
            env_extra: dict | None = None) -> subprocess.CompletedProcess:
        """``argv`` in this venv (its ``bin`` first on PATH, ``env_extra`` set), output captured
        as text."""
        proc = subprocess.run(list(argv), cwd=cwd, env=self.env(**(env_extra or {})),
                              capture_output=True,
                              text=True, timeout=timeout)
        if check and proc.returncode != 0:
            raise AssertionError(f"{' '.join(argv)} exited {proc.returncode}:\n"
                                 f"{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
        return proc

    def site_packages(self) -> str:
        out = self.run(self.python, "-c",
                       "import sysconfig; print(sysconfig.get_paths()['purelib'])")
        return out.stdout.strip()


@contextlib.contextmanager
def serving(venv: Venv, *argv: str, cwd: str):
    """``dqpose serve ARGV`` of ``venv`` on a free loopback port until the block ends (SIGTERM);
    yields its address. A server that dies at start fails with its output."""
    proc = subprocess.Popen([os.path.join(venv.bin, "dqpose"), "serve", *argv], cwd=cwd,
                            env=venv.env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        first = proc.stderr.readline()
        try:
            event = json.loads(first)
        except json.JSONDecodeError:
            try:        # the traceback of a server that failed at start
                _, err = proc.communicate(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                _, err = proc.communicate()
            raise AssertionError(f"dqpose serve did not start:\n{first}{err[-3000:]}") from None
        assert event.get("event") == "serving", first
        yield event["address"]
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 0, err[-3000:]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def build_requirements() -> list[str]:
    """pyproject.toml's ``[build-system] requires``: what ``pip install .`` puts into its isolated
    build environment, installed here beforehand so ``--no-build-isolation`` (as ``make`` runs)
    builds the same way and pip's cache serves a rerun."""
    with open(os.path.join(ROOT, "pyproject.toml")) as f:   # no tomllib before Python 3.11
        text = f.read()
    table = re.search(r"^\[build-system\]$(.*?)^\[", text, re.M | re.S).group(1)
    requires = re.search(r"^requires\s*=\s*\[(.*?)\]", table, re.M | re.S).group(1)
    return re.findall(r'"([^"]+)"', requires)


def hint(extra: str, spec: str) -> str:
    """The line a command or call that needs ``extra`` ends with; ``spec`` is how pip names this
    install: ``.`` from a clone, ``dqpose`` for an installed wheel."""
    return f"install dqpose with the [{extra}] extra: pip install '{spec}[{extra}]'"


LIMITS = dict(max_linear_velocity=0.25, max_angular_velocity=1.0, max_linear_acceleration=1.0,
              max_angular_acceleration=2.0)


def check_bare_server(address: str, smooth_hint: str) -> None:
    """Every service of a server installed without extras answers through the shipped
    :class:`~dqpose.rpc.client.Client` as the same code does in this process; Smooth, which
    needs the [planning] extra, is FAILED_PRECONDITION with ``smooth_hint``."""
    import math

    import numpy as np

    from dqpose import dq, handeye, trajectory
    from dqpose.rpc.client import Client, RpcError
    from tests._handeye import scene

    poses = dq.from_pose([[1, 0, 0, 0], [math.cos(0.5), 0, 0, math.sin(0.5)]],
                         [[0.1, 0.0, 0.0], [0.3, 0.1, 0.0]])
    limits = trajectory.Limits(**LIMITS)
    waypoints = [trajectory.Waypoint(dq.from_pose([0, 1, 0, 0], [x, 0.0, 0.3])) for x in (0.4, 0.5)]
    s = scene(8, seed=3)
    with Client(address, timeout=120) as c:
        assert c.health() == "SERVING"
        mean = dq.dib(poses, [1, 3])
        np.testing.assert_allclose(c.blend(poses, weights=[1, 3]), mean, atol=1e-12)
        np.testing.assert_allclose(c.blend_batch(np.stack([poses] * 4), [[1, 3]] * 4), [mean] * 4,
                                   atol=1e-12)
        np.testing.assert_allclose(list(c.blend_stream((poses, [1, 3]) for _ in range(3))),
                                   [mean] * 3, atol=1e-12)
        path = c.interpolate([0.0, 2.0], poses, [0.0, 1.0, 2.0])
        np.testing.assert_allclose(path[[0, 2]], poses, atol=1e-12)
        measured = np.stack([poses[1]] * 3)
        fused = c.fuse(measured, np.stack([np.eye(6) * 1e-4] * 3))
        np.testing.assert_allclose(fused.mean, poses[1], atol=1e-9)
        planned = c.plan(waypoints, limits, 100.0)
        assert abs(planned.duration - trajectory.plan(waypoints, limits).duration) < 1e-9
        cal = c.calibrate(s.base_flange, s.camera_target, "eye_in_hand")
        local = handeye.calibrate(s.base_flange, s.camera_target, "eye_in_hand")
        np.testing.assert_allclose(cal.x, local.x, atol=1e-9)
        times = np.linspace(0.0, 1.0, 11)
        try:
            c.smooth(times, dq.identity((11,)), limits)
        except RpcError as e:
            assert (e.code.name, e.details) == ("FAILED_PRECONDITION", smooth_hint), e
        else:
            raise AssertionError("Smooth answered on a server without the [planning] extra")
