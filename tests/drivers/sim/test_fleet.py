"""drivers/sim/fleet.py through `dqpose serve --sims` (what `make run` starts): the server and
the simulated devices come up together, the real clients reach each, and SIGTERM takes them all
down."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np
import pytest

from dqpose.drivers.sim.fleet import Fleet

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))


def _gone(pid: int) -> bool:
    """The process has ended (a zombie nobody reaps counts as ended)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] == "Z"
    except FileNotFoundError:
        return True


def test_serve_with_sims_brings_up_reachable_devices_and_takes_them_down():
    pytest.importorskip("rtde_control")
    pytest.importorskip("msgpack")                    # the PiPER simulator's udp_multicast bus
    from dqpose import dq, drivers
    from dqpose.drivers.camera import read_image
    from dqpose.drivers.sim.ur import address_free
    from dqpose.rpc.client import Client

    # the PiPER served as an arm, the UR left to the user (--sims alone serves both)
    proc = subprocess.Popen([sys.executable, "-m", "dqpose.cli", "serve", "--port", "0",
                             "--sims", "--arm", "piper=piper:sim", "--no-call-log"], cwd=ROOT,
                            stderr=subprocess.PIPE, text=True)
    try:
        events = {}
        while "serving" not in events:
            line = proc.stderr.readline()
            assert line, "the server ended before serving"
            e = json.loads(line)
            events.setdefault(e.get("device", e["event"]), e)
        host, folder = events["ur"]["host"], events["camera"]["images"]
        # every device is reached by the name its "use" line gives
        assert events["ur"]["use"] == f"drivers.open_arm('ur:{host}')"
        with drivers.open_arm(events["ur"]["spec"]) as arm:   # the real ur_rtde client
            _, pose = arm.tool_pose()
            assert np.isclose(np.linalg.norm(pose[:4]), 1.0)
        piper = events["piper"]
        # the server drives it: it is used through the server
        assert (piper["arm"], piper["use"]) == ("piper", "dqpose arm get piper; "
                                                         "Client.get_arm('piper')")
        assert piper["spec"].startswith("piper:udp_multicast:239.")
        assert "arm" not in events["ur"]
        with Client(events["serving"]["address"], timeout=5) as c:   # over UDP, in its process
            (arm,) = c.list_arms()
            assert arm.arm == "piper" and not arm.faults
            assert np.isclose(np.linalg.norm(arm.pose[:4]), 1.0)
        with open(os.path.join(folder, "poses.json")) as f:
            truth = json.load(f)["T_camera_board"]
        cam = drivers.open_source(events["camera"]["spec"],
                                  intrinsics=os.path.join(folder, "poses.json"))
        assert cam.read().source == "camera"
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
        assert address_free(host)                    # the UR simulator is gone
        assert _gone(piper["pid"])                    # the PiPER simulator too
        assert not os.path.exists(folder)             # and the temporary views
    finally:
        if proc.poll() is None:
            proc.kill()


def test_unknown_device_is_named():
    with pytest.raises(ValueError, match="sims: unknown device 'tractor'"):
        Fleet(devices=("ur", "tractor"))


def test_simulators_do_not_outlive_a_killed_server():
    pytest.importorskip("rtde_control")
    pytest.importorskip("msgpack")
    from dqpose.drivers.sim.ur import address_free
    # A killed server cannot remove its camera views: give it a temporary directory of ours.
    with tempfile.TemporaryDirectory(prefix="dqpose-test-fleet-") as tmp:
        proc = subprocess.Popen([sys.executable, "-m", "dqpose.cli", "serve", "--port", "0",
                                 "--sims"], cwd=ROOT, stderr=subprocess.PIPE, text=True,
                                env={**os.environ, "TMPDIR": tmp})
        try:
            events = {}
            while "serving" not in events:
                e = json.loads(proc.stderr.readline())
                events[e.get("device", e["event"])] = e
            host, pid = events["ur"]["host"], events["piper"]["pid"]
            assert not address_free(host) and not _gone(pid)
            assert events["camera"]["images"].startswith(tmp)
        finally:
            proc.kill()                               # no chance to clean up
            proc.wait()
            proc.stderr.close()
        deadline = time.monotonic() + 5
        while not (address_free(host) and _gone(pid)) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert address_free(host) and _gone(pid)
