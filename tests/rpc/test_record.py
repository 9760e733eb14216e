"""Recording through a real server (ServerConfig.recorder, what `dqpose serve --record` sets):
StreamFuse and Fuse calls read back from the file byte for byte; a writer that stalls drops
messages, counts them on the metrics port and marks the file, while every RPC is answered."""
from __future__ import annotations

import json
import re
import urllib.request

import grpc
import numpy as np

from dqpose import dq
from dqpose.record.reader import read
from dqpose.record.recorder import Recorder
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as pb
from dqpose.rpc.client import Client
from dqpose.rpc.fusion import FUSE, STREAM_FUSE
from dqpose.rpc.server import ServerConfig
from tests._polling import wait_until
from tests.record import _stream
from tests.rpc._grpc_server import ServerThread
from tests.rpc.server._blending import socket_free_port


def stream_bytes(target: str, data: list[bytes]) -> list[bytes]:
    """StreamFuse with the requests as bytes, the answers as the server sent them."""
    with grpc.insecure_channel(target) as ch:
        call = ch.stream_stream(f"/{STREAM_FUSE}")
        return list(call(iter(data), timeout=60))


def test_a_stream_and_a_fuse_are_recorded_as_sent_and_answered(tmp_path):
    data = _stream.requests(30)
    recorder = Recorder(tmp_path)
    with ServerThread(ServerConfig(port=0, recorder=recorder)) as s:
        answers = stream_bytes(s.target, data)
        poses = dq.normalize(np.array([[1, 0, 0, 0, 0, 0.1, 0, 0], [1, 0.01, 0, 0, 0, 0.1, 0,
                                                                      0]]))
        fused = Client(s.target).fuse(poses, weights=[1.0, 2.0])
        try:
            stream_bytes(s.target, [pb.FuseStreamRequest(output_rate=-1).SerializeToString()])
        except grpc.RpcError as e:
            assert e.code() == grpc.StatusCode.INVALID_ARGUMENT
    # the server's stop closed the recorder: the file is finished
    assert len(answers) > 10
    (path,) = recorder.files
    rec = read(path)
    stream, fuse, refused = (rec.calls[k] for k in sorted(rec.calls))
    assert (stream.rpc, stream.request_type, stream.answer_type, stream.code) == \
        (STREAM_FUSE, "dqpose.v1.FuseStreamRequest", "dqpose.v1.FusedPose", "OK")
    got = [e for e in rec.events if e.call == stream.id]
    assert [e.data for e in got if e.kind == "request"] == data
    assert [e.data for e in got if e.kind == "answer"] == answers
    # each answer after the request that brought it
    kinds = [e.kind for e in got]
    assert kinds[0] == "request" and kinds.count("answer") == len(answers)
    (q, a) = [e for e in rec.events if e.call == fuse.id]
    assert (fuse.rpc, fuse.code, q.kind, a.kind) == (FUSE, "OK", "request", "answer")
    answer = pb.FusedPose.FromString(a.data)
    assert list(answer.covariance) == fused.covariance.ravel().tolist()
    assert len(pb.FuseRequest.FromString(q.data).measurements) == 2
    assert refused.code == "INVALID_ARGUMENT" and "output_rate" in refused.details
    assert [e.kind for e in rec.events if e.call == refused.id] == ["request"]
    assert rec.dropped == []


def test_a_stalled_recording_drops_says_so_and_every_rpc_is_answered(tmp_path, caplog):
    data = _stream.requests(40)
    want = _stream.answers(data)
    recorder = Recorder(tmp_path, queue=8)
    recorder.stall.set()          # a disk that hangs
    with socket_free_port() as port, \
            ServerThread(ServerConfig(port=0, recorder=recorder, metrics_port=port)) as s:
        answers = stream_bytes(s.target, data)
        # every answer came, and the same as unrecorded
        assert answers == [a.SerializeToString() for got in want for a in got]
        # the call's beginning, requests, answers, and its end once the server closed it
        wait_until(lambda: recorder.dropped == 1 + len(data) + len(answers) + 1 - 8, 10)
        text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read()
        assert re.search(rf'dqpose_record_messages_total{{outcome="dropped"}} '
                         rf'{recorder.dropped}\.0', text.decode())
        recorder.stall.clear()
        wait_until(lambda: recorder.written == 8, 10)       # the queue drained
        again = stream_bytes(s.target, data[:3])
    rec = read(recorder.files[0])
    (line,) = [json.loads(r.getMessage()) for r in caplog.records if r.name == "dqpose.record"
               and r.levelname == "WARNING"]
    assert (line["event"], line["count"], line["file"]) == \
        ("recording_dropped", rec.dropped[0].count, recorder.files[0])
    first, second = sorted(rec.calls)
    kept = [e for e in rec.events if e.call == first]      # the queue's 8, less the beginning
    assert len(kept) == 7 and [e.data for e in kept if e.kind == "request"] == \
        data[:sum(e.kind == "request" for e in kept)]
    assert len(rec.dropped) == 1 and rec.dropped[0].at == 7
    assert rec.dropped[0].count == 1 + len(data) + len(answers) + 1 - 8
    # the next call is whole, after the marker
    assert [e.data for e in rec.events if e.call == second and e.kind == "request"] == data[:3]
    assert len([e for e in rec.events if e.call == second and e.kind == "answer"]) == len(again)


def test_a_plan_is_recorded_as_a_path_to_view(tmp_path):
    from dqpose.record import PLAN_VIEW_POSES
    from tests.rpc.test_trajectories import LIMITS, _waypoints

    recorder = Recorder(tmp_path)
    with ServerThread(ServerConfig(port=0, recorder=recorder)) as s:
        few = Client(s.target).plan(_waypoints(), LIMITS, 10.0)
        many = Client(s.target).plan(_waypoints(), LIMITS, 1000.0)
    rec = read(recorder.files[0])
    assert [name for name, _, _ in rec.plans] == ["Plan", "Plan"]
    Poses = rec.message_class("foxglove.PosesInFrame")
    for (_, _, data), planned in zip(rec.plans, (few, many)):
        path = Poses.FromString(data).poses
        assert len(path) <= PLAN_VIEW_POSES + 1
        assert path[0].position.y == dq.to_pose(planned.pose[0])[1][1]
        q, t = dq.to_pose(planned.pose[-1])
        assert (path[-1].position.x, path[-1].orientation.z) == (t[0], q[3])
    assert len(Poses.FromString(rec.plans[0][2]).poses) == len(few.time) + 1
    assert len(many.time) > PLAN_VIEW_POSES
