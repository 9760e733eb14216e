"""``make run ARGS="--port N"``: the documented server, on the port the user asked for, driving
the simulated UR and PiPER as its arms."""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import threading

import pytest

from tests.install._install import ROOT

pytestmark = pytest.mark.install


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_make_run_serves_on_the_port_given_in_args():
    from dqpose.rpc.client import Client

    port = _free_port()
    proc = subprocess.Popen(["make", "--no-print-directory", "run", f"ARGS=--port {port}"],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)      # make, the server and its simulators
    # a server that never says it serves is stopped rather than waited for
    watchdog = threading.Timer(300, os.killpg, (proc.pid, signal.SIGKILL))
    watchdog.start()
    try:
        lines = []
        for line in proc.stderr:
            lines.append(line)
            if line.startswith("{") and json.loads(line).get("event") == "serving":
                break
        assert lines and json.loads(lines[-1]).get("event") == "serving", "".join(lines)
        assert json.loads(lines[-1])["address"] == f"127.0.0.1:{port}"
        with Client(f"127.0.0.1:{port}", timeout=30) as c:
            assert c.health() == "SERVING"
            assert [(a.arm, a.state, a.busy) for a in c.list_arms()] == [
                ("piper", "", False), ("ur", "", False)]
        os.killpg(proc.pid, signal.SIGINT)                # Ctrl-C in the terminal
        proc.communicate(timeout=120)
    finally:
        watchdog.cancel()
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
