"""``dqpose view --server``: a real ``dqpose view`` process following a real server (on
127.0.0.1, its arm the simulated UR through ur_rtde) through World/Subscribe and
Trajectories/WatchArm. Each body's measurements are published once, after the page's
subscription reached the server: the page draws both bodies with their ellipsoids (so a body's
first fused pose is not lost), the arm's path as it moves, the world's static and source frames
(one on a body that comes later), and headless Chromium shows the ellipsoids' and the path's
colours."""
from __future__ import annotations

import json
import queue
import subprocess
import sys
import threading

import numpy as np
import pytest

from dqpose import dq
from dqpose.frames import Static
from dqpose.fusion import Source
from tests._polling import wait_until
from tests.cli._cli import ROOT
from tests.robustness._arms import LIMITS, URRig, offset, serve
from tests.view.test_page import CHROMIUM, actual_pixels, ellipsoid_pixels, screenshot

#: pixels of the two ellipsoids and of the arm's actual path at the least
LIVE, PATH = 500, 30

pytest.importorskip("viser", reason="the [view] extra (pip install -e '.[view]')")
pytest.importorskip("foxglove", reason="the [record] extra")

COV = np.diag([1e-3, 1e-3, 1e-3, 0.08 ** 2, 0.05 ** 2, 0.03 ** 2])


def _events(proc) -> queue.Queue:
    said: queue.Queue = queue.Queue()

    def read() -> None:
        for line in proc.stderr:
            if line.startswith("{"):
                said.put(json.loads(line))
    threading.Thread(target=read, daemon=True).start()
    return said


def _until(said: queue.Queue, done, seen: list, timeout: float = 60.0) -> None:
    """Reads the page's events into ``seen`` until ``done(seen)``."""
    while not done(seen):
        seen.append(said.get(timeout=timeout))


def test_the_page_follows_a_server_through_its_rpcs(tmp_path):
    from dqpose.rpc.client import Batch, Client

    # a heartbeat for a machine drawing WebGL in software beside the server (the hang safety is
    # tests/robustness/test_execute.py's): this test is about the page
    rig = URRig(heartbeat=0.5)
    view = None
    try:
        rig.reset()
        with serve([rig]) as server, Client(server.target) as c:
            c.configure_world([Source("cam", dq.from_pose([1.0, 0, 0, 0], [0.0, 0.0, 0.0]))],
                              statics=[Static("", "table", dq.from_pose([1.0, 0, 0, 0],
                                                                        [0.3, 0.2, 0.0])),
                                       Static("box", "lid", dq.from_pose([1.0, 0, 0, 0],
                                                                         [0.0, 0.0, 0.05]))])
            view = subprocess.Popen([sys.executable, "-m", "dqpose.cli", "view", "--server",
                                     server.target, "--port", "0"], cwd=ROOT,
                                    stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                    text=True)
            said = _events(view)
            seen: list = []
            _until(said, lambda s: any(e["event"] == "following" for e in s), seen)
            url = next(e["url"] for e in seen if e["event"] == "viewing")
            assert next(e["arms"] for e in seen if e["event"] == "following") == ["ur"]
            (world,) = [s for s in server.running.servicers if s.NAME == "dqpose.v1.World"]
            assert wait_until(lambda: len(world.hub("", make=True).subscriptions) == 1,
                              timeout=30)
            # each body's measurements once: its first (and only) fused pose must be drawn
            poses = dq.from_pose(np.array([[1.0, 0, 0, 0]] * 4),
                                 np.array([[0.0, 0, 0.3], [0.01, 0, 0.3], [0.6, 0, 0.3],
                                           [0.61, 0, 0.3]]))
            acks = list(c.publish([Batch(poses, np.repeat(COV[None], 4, 0), None,
                                         ["cam"] * 4, ["box", "box", "cup", "cup"],
                                         np.full(4, 1.0))], producer="test"))
            assert acks[0].errors == ()
            feedback = list(c.execute("ur", [rig.home, offset(rig.home, dx=0.15)], LIMITS))
            assert feedback[-1].state == "FINISHED"
            _until(said, lambda s: {(e.get("body"), e.get("ellipsoid")) for e in s
                                    if e["event"] == "drawn"} >= {("box", True), ("cup", True)}
                   and any(e.get("arm") == "ur" and e.get("path") for e in s)
                   and {e.get("frame") for e in s} >= {"cam", "table", "lid"}, seen)
            if CHROMIUM is None:
                pytest.skip("no Chromium: apt-get install -y chromium (.ci/run installs it)")
            img = screenshot(url, tmp_path / "server.png",
                             lambda i: ellipsoid_pixels(i) > LIVE and actual_pixels(i) > PATH)
            assert ellipsoid_pixels(img) > LIVE, ellipsoid_pixels(img)
            assert actual_pixels(img) > PATH, actual_pixels(img)
    finally:
        if view is not None:
            view.terminate()
            view.wait(30)
        rig.close()


def test_a_server_that_is_not_there_is_said():
    res = subprocess.run([sys.executable, "-m", "dqpose.cli", "view", "--server",
                          "127.0.0.1:1", "--port", "0"], capture_output=True, text=True,
                         timeout=120, cwd=ROOT)
    assert res.returncode == 2
    assert res.stderr.splitlines()[-1].startswith("dqpose view: error: --server 127.0.0.1:1: ")
