"""One real server on 127.0.0.1 per test module, and a Blending stub on it."""
from __future__ import annotations

import grpc
import pytest

from dqpose.rpc._proto.dqpose.v1 import blending_pb2_grpc as pb_grpc
from tests.rpc._grpc_server import ServerThread
from tests.rpc.server._blending import (
    MAX_BYTES,
    MAX_POSES,
)


@pytest.fixture(scope="module")
def server():
    with ServerThread(max_poses=MAX_POSES, max_message_bytes=MAX_BYTES) as s:
        yield s


@pytest.fixture(scope="module")
def stub(server):
    with grpc.insecure_channel(server.target) as ch:
        yield pb_grpc.BlendingStub(ch)
