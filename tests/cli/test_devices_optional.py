"""`pip install .` brings no device library and no extra (the server image has none): the server,
its health check and the UR simulator run with every extra's modules unimportable, and the
commands and calls that need one name the extra that brings it (tests/install/ installs for real,
slower)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

import numpy as np
import pytest

from dqpose import dq, trajectory
from dqpose.rpc.client import Client, RpcError

LIMITS = trajectory.Limits(max_linear_velocity=1.0, max_angular_velocity=1.0,
                           max_linear_acceleration=1.0, max_angular_acceleration=1.0)
ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

DEVICE_MODULES = ("cv2", "can", "rtde_control", "rtde_receive", "yaml", "casadi", "piper_sdk",
                  "scipy", "matplotlib", "mcap", "foxglove_schemas_protobuf", "rosbags", "foxglove",
                  "viser")


def hint(extra: str) -> str:
    """What a command or call that needs ``extra`` ends with, here (an editable install run from
    its clone)."""
    return f"install dqpose with the [{extra}] extra: pip install '.[{extra}]'"

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
from dqpose.cli import main
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
        health = _dqpose("health", "--server", target, "--timeout", "20")
        out, err = health.communicate(timeout=60)
        assert (health.returncode, out.strip()) == (0, "SERVING"), err
        assert "blocked import" not in err
        with Client(target, timeout=20) as c:   # a blend and an interpolation served by it
            assert np.allclose(c.blend(dq.identity((3,))), dq.identity(), atol=1e-12)
            assert c.interpolate([0.0, 1.0], dq.identity((2,)), [0.5]).shape == (1, 8)
            with pytest.raises(RpcError) as e:      # Smooth needs the [planning] extra
                c.smooth(np.linspace(0, 1, 5), dq.identity((5,)), LIMITS)
            assert (e.value.code.name, e.value.details) == ("FAILED_PRECONDITION", hint("planning"))
        server.send_signal(signal.SIGTERM)
        _, err = server.communicate(timeout=30)
        assert server.returncode == 0, err
        blocked = {line for line in (first + err).splitlines() if line.startswith("blocked import")}
        assert blocked == {"blocked import: scipy"}, err     # Smooth's, and only when called
    finally:
        if server.poll() is None:
            server.kill()
            server.communicate()


def test_commands_needing_an_extra_name_it(tmp_path):
    recording = tmp_path / "recording.csv"
    recording.write_text("t,x,y,z,qw,qx,qy,qz\n"
                         + "".join(f"{i},{0.01 * i},0,0,1,0,0,0\n" for i in range(5)))
    limits = [f"--{k.replace('_', '-')}=1" for k in LIMITS.__dataclass_fields__ if "jerk" not in k]
    poses = tmp_path / "poses.yaml"
    poses.write_text("poses:\n  - {orientation: {w: 1}}\n")
    for argv, extra in [(("sim", "piper", "--help"), "devices"),
                        (("sim", "camera", "--help"), "devices"),
                        (("serve", "--port", "0", "--sims"), "devices"),
                        (("serve", "--port", "0", "--record", str(tmp_path / "rec")), "record"),
                        (("serve", "--port", "0", "--live", "127.0.0.1:0"), "record"),
                        (("replay", str(tmp_path / "x.mcap")), "record"),
                        (("view", str(tmp_path / "x.mcap")), "view"),
                        (("export", str(tmp_path / "x.mcap"), "--ros2", str(tmp_path / "b")),
                         "record"),
                        (("handeye", "solve", ROOT, "--local"), "devices"),
                        (("handeye", "capture", os.path.join(ROOT, "no-such-dir")), "devices"),
                        (("smooth", str(recording), "--local", *limits), "planning"),
                        (("plan", str(recording), "--local", "--plot", "x.png", *limits), "plot"),
                        (("blend", str(poses), "--local"), "yaml")]:
        proc = _dqpose(*argv)
        out, err = proc.communicate(timeout=60)
        assert proc.returncode == 2, (out, err)
        words = 2 if argv[0] in ("sim", "handeye") else 1
        cmd = f"serve {argv[3]}" if argv[0] == "serve" else " ".join(argv[:words])
        assert err.strip().splitlines()[-1] == f"dqpose {cmd}: error: {hint(extra)}", err
        assert "Traceback" not in err
    # the UR simulator speaks RTDE itself: it needs no device library
    proc = _dqpose("sim", "ur", "--help")
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0 and "blocked import" not in err, err
