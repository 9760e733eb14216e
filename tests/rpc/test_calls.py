"""What every stream's handler does with a defect (`Calls.failed`): the call ends INTERNAL with
the same readable details, the exception's text stays in the server's log with its traceback,
and the server goes on answering. A real server; the defect is a patched-in exception."""
from __future__ import annotations

import logging

import grpc
import numpy as np
import pytest

from dqpose import dq
from dqpose.hub import Hub
from dqpose.rpc.blending import Blending
from dqpose.rpc.calls import INTERNAL_DETAILS
from dqpose.rpc.client import Client, RpcError
from dqpose.rpc.fusion import Fusion
from tests.rpc._grpc_server import ServerThread

SECRET = "a defect's text the client must not see"


def _boom(*_args, **_kw):
    raise RuntimeError(SECRET)


def _blend_stream(c: Client):
    return list(c.blend_stream([(np.stack([dq.identity(), dq.identity()]), None)]))


def _stream_fuse(c: Client):
    return list(c.stream_fuse([(np.stack([dq.identity()]), None, None, None, ["box"], [0.0])]))


def _publish(c: Client):
    c.configure_world()
    return list(c.publish([(np.stack([dq.identity()]), None, None, None, ["box"], [0.0])],
                          producer="cam1"))


@pytest.mark.parametrize("rpc, owner, name, call", [
    ("BlendStream", Blending, "blend_wire", _blend_stream),
    ("StreamFuse", Fusion, "_open_stream", _stream_fuse),
    ("Publish", Hub, "publish", _publish),
])
def test_a_defect_in_a_stream_is_internal_logged_and_the_server_goes_on(rpc, owner, name, call,
                                                                        monkeypatch, caplog):
    caplog.set_level(logging.ERROR, logger="dqpose.server")
    with ServerThread() as server, Client(server.target) as c:
        call(c)                          # answered before the defect
        monkeypatch.setattr(owner, name, _boom)
        with pytest.raises(RpcError) as e:
            call(c)
        assert e.value.code == grpc.StatusCode.INTERNAL
        assert e.value.details == INTERNAL_DETAILS
        # a World call's log line names its world too
        named = (f"{rpc} failed", f"World/{rpc} in world '' failed")
        failed = [r for r in caplog.records if r.getMessage() in named]
        assert len(failed) == 1 and SECRET in str(failed[0].exc_info[1])
        monkeypatch.undo()
        assert call(c)                   # the server answers the next stream
