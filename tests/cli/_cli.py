"""What the command-line tests share: ``run``, the ``dqpose`` entry point in this process with its
output captured, ``server``, a real server on 127.0.0.1 (tests/rpc/_grpc_server.py), one per
module (a fixture: import it into the test module), and ``serving``, ``dqpose serve`` in a
process of its own."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from dqpose.cli import main
from tests.rpc._grpc_server import ServerThread


@pytest.fixture(scope="module")
def server():
    with ServerThread() as s:
        yield s


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def serving(*flags):
    """``dqpose serve --port 0 FLAGS`` in its own process, once it serves: ``(process, its JSON
    log events so far)``, the last one ``serving`` with the ``address``; its standard error
    stays a pipe for the rest."""
    proc = subprocess.Popen([sys.executable, "-m", "dqpose.cli", "serve", "--port", "0",
                             *flags], cwd=ROOT, stderr=subprocess.PIPE, text=True)
    events: list = []
    try:
        while not events or events[-1].get("event") != "serving":
            line = proc.stderr.readline()
            assert line, "the server ended before serving"
            if line.startswith("{"):
                events.append(json.loads(line))
    except BaseException:
        proc.kill()
        raise
    return proc, events
