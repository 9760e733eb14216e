"""`pip install dqpose` brings no device library (the server image has none): the server, its
health check and the UR simulator run with cv2, can, rtde_* and yaml unimportable, and the
commands that need one name the extra that brings it."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

import numpy as np

from service import dq
from service.rpc.client import Client

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

DEVICE_MODULES = ("cv2", "can", "rtde_control", "rtde_receive", "yaml", "casadi", "piper_sdk")

# Runs the dqpose command in a process where importing a device library fails as if it were not
# installed, and reports every such attempt on standard error.
_BLOCKED_MAIN = f"""
import sys
from importlib.abc import MetaPathFinder

class Blocker(MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {DEVICE_MODULES!r}:
            print("blocked import: " + name, file=sys.stderr, flush=True)
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
        return None

sys.meta_path.insert(0, Blocker())
from service.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _dqpose(*argv: str, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", _BLOCKED_MAIN, *argv], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


def test_server_and_health_run_without_device_libraries():
    server = _dqpose("serve", "--port", "0", "--grace", "0")
    try:
        first = server.stderr.readline()
        assert json.loads(first)["event"] == "serving", first
        target = json.loads(first)["address"]
        health = _dqpose("health", "--target", target, "--timeout", "20")
        out, err = health.communicate(timeout=60)
        assert (health.returncode, out.strip()) == (0, "SERVING"), err
        assert "blocked import" not in err
        with Client(target, timeout=20) as c:   # a blend and an interpolation served by it
            assert np.allclose(c.blend(dq.identity((3,))), dq.identity(), atol=1e-12)
            assert c.interpolate([0.0, 1.0], dq.identity((2,)), [0.5]).shape == (1, 8)
        server.send_signal(signal.SIGTERM)
        _, err = server.communicate(timeout=30)
        assert server.returncode == 0, err
        assert "blocked import" not in first + err
    finally:
        if server.poll() is None:
            server.kill()
            server.communicate()


def test_commands_needing_a_device_library_name_the_extra():
    # --sims starts several simulators: whichever needs a blocked library first is named
    for argv, missing in [(("sim", "piper", "--help"), ("can",)), (("sim", "camera", "--help"), ("cv2",)),
                          (("serve", "--port", "0", "--sims"), ("can", "cv2")),
                          (("handeye", "solve", ROOT, "--local"), ("cv2",)),
                          (("handeye", "capture", os.path.join(ROOT, "no-such-dir")), ("cv2",))]:
        proc = _dqpose(*argv)
        out, err = proc.communicate(timeout=60)
        assert proc.returncode == 2, (out, err)
        cmd = "serve --sims" if argv[0] == "serve" else " ".join(argv[:2])
        assert any(f"dqpose {cmd}: error: No module named '{m}'" in err for m in missing), err
        assert "pip install 'dqpose[devices]'" in err
        assert "Traceback" not in err
    # the UR simulator speaks RTDE itself: it needs no device library
    proc = _dqpose("sim", "ur", "--help")
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0 and "blocked import" not in err, err
