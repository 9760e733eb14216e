"""The command-line tests' real server on 127.0.0.1 (tests/rpc/_grpc_server.py), one per module."""
from __future__ import annotations

import os
import sys

import pytest

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(__file__)), "rpc"))
from _grpc_server import ServerThread  # noqa: E402


@pytest.fixture(scope="module")
def server():
    with ServerThread() as s:
        yield s

