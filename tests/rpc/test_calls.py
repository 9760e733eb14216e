"""What every stream's handler does with a defect (`Calls.stream`, `Calls.failed`): the call ends
INTERNAL with the same readable details, the exception's text stays in the server's log with its
traceback, its recording ends INTERNAL, and the server goes on answering. A real server; the
defect is a patched-in exception."""
from __future__ import annotations

import logging

import grpc
import numpy as np
import pytest

from dqpose import dq
from dqpose.hub import Hub
from dqpose.record.reader import read
from dqpose.record.recorder import Recorder
from dqpose.rpc.blending import Blending
from dqpose.rpc.calls import INTERNAL_DETAILS
from dqpose.rpc.client import Client, RpcError
from dqpose.rpc.fusion import Fusion
from dqpose.rpc.server import ServerConfig
from dqpose.rpc.trajectories import Trajectories
from dqpose.rpc.world import World
from tests.rpc._grpc_server import ServerThread
from tests.rpc.test_trajectories import LIMITS, _waypoints

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


def _plan(c: Client):
    return c.plan(_waypoints(), LIMITS, 10.0).time.size


def _subscribe(c: Client):
    c.configure_world()
    try:
        list(c.subscribe(timeout=0.2))      # a stream of no answers, ended by its deadline
    except RpcError as e:
        if e.code != grpc.StatusCode.DEADLINE_EXCEEDED:
            raise
    return True


@pytest.mark.parametrize("rpc, owner, name, call", [
    ("BlendStream", Blending, "blend_wire", _blend_stream),
    ("StreamFuse", Fusion, "start_stream", _stream_fuse),
    ("Publish", Hub, "publish", _publish),
    # (these two ended UNKNOWN with the defect's text before Calls.stream)
    ("Plan", Trajectories, "sample_chunk", _plan),
    ("SubscribeBatches", World, "_admit", _subscribe),
])
def test_a_defect_in_a_stream_is_internal_logged_and_the_server_goes_on(rpc, owner, name, call,
                                                                        monkeypatch, caplog,
                                                                        tmp_path):
    caplog.set_level(logging.ERROR, logger="dqpose.server")
    recorder = Recorder(tmp_path)
    with ServerThread(ServerConfig(port=0, recorder=recorder)) as server, \
            Client(server.target) as c:
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
    # the server's stop closed the recorder: the file is finished
    if rpc not in ("BlendStream", "Plan"):      # (not recorded)
        (path,) = recorder.files
        calls = read(path).calls
        recorded = rpc.removesuffix("Batches")       # (recorded as Subscribe)
        ended = [calls[k].code for k in sorted(calls)
                 if calls[k].rpc.endswith(f"/{recorded}") and not calls[k].internal]
        answered = "CANCELLED" if recorded == "Subscribe" else "OK"     # (its deadline)
        assert ended == [answered, "INTERNAL", answered], ended
