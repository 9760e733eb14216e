"""drivers/sim/fleet.py through `dqpose serve --sims` (what `make run` starts): the server and
the simulated devices come up together, the real clients reach each, and SIGTERM takes them all
down."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

import numpy as np
import pytest

from drivers.sim.fleet import Fleet

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))


def test_serve_with_sims_brings_up_reachable_devices_and_takes_them_down():
    pytest.importorskip("rtde_control")
    from drivers.camera import CharucoCamera, read_image
    from drivers.sim.camera import DEFAULT_INTRINSICS
    from drivers.sim.ursim import _address_free
    from drivers.ur import URArm
    from service import dq
    from service.rpc.client import Client

    proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", "0",
                             "--sims", "--no-call-log"], cwd=ROOT, stderr=subprocess.PIPE,
                            text=True)
    try:
        events = {}
        while "serving" not in events:
            line = proc.stderr.readline()
            assert line, "the server ended before serving"
            e = json.loads(line)
            events[e.get("device", e["event"])] = e
        host, folder = events["ur"]["host"], events["camera"]["images"]

        with URArm(host) as arm:                      # the real ur_rtde client, end to end
            _, pose = arm.tool_pose()
            assert np.isclose(np.linalg.norm(pose[:4]), 1.0)
        with open(os.path.join(folder, "poses.json")) as f:
            truth = json.load(f)["T_camera_board"]
        cam = CharucoCamera(DEFAULT_INTRINSICS)
        errors = []
        for name, T in truth.items():
            d = cam.detect(read_image(os.path.join(folder, name)))
            if d.ok:
                errors.append(np.linalg.norm(dq.to_pose(d.pose)[1] - dq.to_pose(np.array(T))[1]))
        assert len(errors) >= 15                      # a few random views may be rejected
        assert np.median(errors) < 0.002
        with Client(events["serving"]["address"], timeout=5) as c:
            assert c.health() == "SERVING"

        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
        assert _address_free(host)                    # the UR simulator is gone
        assert not os.path.exists(folder)             # and its temporary views
    finally:
        if proc.poll() is None:
            proc.kill()


def test_unknown_device_is_named():
    with pytest.raises(ValueError, match="sims: unknown device 'tractor'"):
        Fleet(devices=("ur", "tractor"))


def test_simulators_do_not_outlive_a_killed_server():
    pytest.importorskip("rtde_control")
    import time

    from drivers.sim.ursim import _address_free
    proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", "0",
                             "--sims"], cwd=ROOT, stderr=subprocess.PIPE, text=True)
    try:
        host = None
        while True:
            e = json.loads(proc.stderr.readline())
            host = e.get("host", host)
            if e["event"] == "serving":
                break
        assert not _address_free(host)
    finally:
        proc.kill()                                   # no chance to clean up
        proc.wait()
    deadline = time.monotonic() + 5
    while not _address_free(host) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert _address_free(host)
