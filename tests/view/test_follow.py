"""``dqpose view --live``: a real ``dqpose serve --live`` followed by a real ``dqpose view``
process; Fuse calls through gRPC; the page draws both bodies with their ellipsoids (its own
events say so) and headless Chromium shows the ellipsoids' colour. A World configured before the
page connected: its source's frame drawn from ``/tf_static``'s latched message."""
from __future__ import annotations

import json
import queue
import subprocess
import sys
import threading

import numpy as np
import pytest

from dqpose import dq
from tests.cli._cli import ROOT, serving
from tests.view.test_page import CHROMIUM, ellipsoid_pixels, screenshot

#: pixels of the live scene's two ellipsoids at the least
LIVE = 500

pytest.importorskip("viser", reason="the [view] extra (pip install -e '.[view]')")
pytest.importorskip("websockets", reason="the [view] extra (pip install -e '.[view]')")
pytest.importorskip("foxglove", reason="the [record] extra")


def test_the_page_follows_a_live_server(tmp_path):
    from dqpose.fusion import Source
    from dqpose.rpc.client import Client

    server, events = serving("--live", "127.0.0.1:0")
    live = next(e for e in events if e.get("event") == "live")
    target = next(e for e in events if e.get("event") == "serving")["address"]
    with Client(target) as c:       # before the page: /tf_static is latched
        c.configure_world([Source("cam", extrinsic=dq.from_pose([0, 1, 0, 0], [0.3, 0, 1]))])
    view = subprocess.Popen([sys.executable, "-m", "dqpose.cli", "view", "--live",
                             f"127.0.0.1:{live['port']}", "--port", "0"], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    said: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: [said.put(line) for line in view.stderr], daemon=True).start()
    try:
        url = None
        while url is None:
            line = said.get(timeout=60)
            if line.startswith("{") and json.loads(line)["event"] == "viewing":
                url = json.loads(line)["url"]
        c = Client(target)
        cov = np.diag([1e-3, 1e-3, 1e-3, 0.08 ** 2, 0.05 ** 2, 0.03 ** 2])
        drawn: set = set()
        frames: set = set()
        # the channels are made by the first calls; the page sees what comes once it subscribed
        for _ in range(200):
            for body, x in (("box", 0.0), ("cup", 0.6)):
                poses = dq.from_pose(np.array([[1.0, 0, 0, 0]] * 2),
                                     np.array([[x, 0.0, 0.3], [x + 0.01, 0.0, 0.3]]))
                c.fuse(poses, np.array([cov, cov]), body=body)
            try:
                while True:
                    line = said.get(timeout=0.1)
                    if line.startswith("{"):
                        e = json.loads(line)
                        if e["event"] == "drawn" and "frame" in e:
                            frames.add(e["frame"])
                        elif e["event"] == "drawn" and e["ellipsoid"]:
                            drawn.add(e["body"])
            except queue.Empty:
                pass
            if drawn == {"box", "cup"} and frames:
                break
        assert drawn == {"box", "cup"} and frames == {"cam"}
        if CHROMIUM is None:
            pytest.skip("no Chromium: apt-get install -y chromium (.ci/run installs it)")
        # retaken until both ellipsoids are in, not a picture of the scene half arrived
        img = screenshot(url, tmp_path / "live.png", lambda i: ellipsoid_pixels(i) > LIVE)
        assert ellipsoid_pixels(img) > LIVE, ellipsoid_pixels(img)
    finally:
        view.terminate()
        view.wait(30)
        server.terminate()
        server.wait(30)


def test_view_needs_a_file_or_a_server():
    res = subprocess.run([sys.executable, "-m", "dqpose.cli", "view"], capture_output=True,
                         text=True, timeout=60, cwd=ROOT)
    assert (res.returncode, res.stderr) == (
        2, "dqpose view: error: give a recording FILE.mcap, --server HOST:PORT or --live "
           "HOST:PORT (one of them)\n")
