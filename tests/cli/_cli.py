"""What the command-line tests share: ``run``, the ``dqpose`` entry point in this process with its
output captured, and ``server``, a real server on 127.0.0.1 (tests/rpc/_grpc_server.py), one per
module (a fixture: import it into the test module)."""
from __future__ import annotations

import os
import sys

import pytest

from service.cli import main

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(__file__)), "rpc"))
from _grpc_server import ServerThread  # noqa: E402


@pytest.fixture(scope="module")
def server():
    with ServerThread() as s:
        yield s


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err
