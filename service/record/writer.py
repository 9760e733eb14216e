"""The recorder's writer process (``python -m dqpose.record.writer DIR MAX_BYTES MAX_SECONDS``):
frames (:mod:`dqpose.record.frames`) on standard input, MCAP files in DIR, rotated by size and
age; JSON lines on standard output for the server to log (``recording``: a file opened,
``recording_dropped``: a drop marker written). Its own process, so that neither the writing nor
the views nor the compression take the server's interpreter lock. Ends, the file finished, when
its input does.
"""
from __future__ import annotations

import json
import os
import select
import signal
import sys
import time

from dqpose.record import frames, views
from dqpose.record.mcapfile import CHUNK_BYTES, McapFile
from dqpose.record.schemas import message_class
from dqpose.record.topics import (
    CALL_FIELDS,
    CALLS_TOPIC,
    DROPPED_FIELDS,
    DROPPED_TOPIC,
    ELLIPSOIDS_TOPIC,
    MAX_VIEW_BODIES,
    STATS_FIELDS,
    TF_TOPIC,
    answers_topic,
    plan_topic,
    pose_topic,
    requests_topic,
    stats_topic,
)


def say(**event) -> None:
    print(json.dumps(event), flush=True)


class Writer:
    def __init__(self, directory: str, max_bytes: int, max_seconds: float):
        self.directory, self.max_bytes, self.max_seconds = directory, max_bytes, max_seconds
        self.file: McapFile | None = None
        self.opened = 0.0
        self.count = 0
        self.frames = 0
        self.schemas: dict[str, bytes] = {}
        self.classes: dict[str, object] = {}
        self.calls: dict[int, tuple[str, str, str]] = {}
        self.view_bodies: set[str] = set()

    def open(self) -> McapFile:
        if self.file is None:
            name = time.strftime("dqpose-%Y%m%dT%H%M%SZ", time.gmtime())
            path = os.path.join(self.directory, f"{name}-{self.count:04d}.mcap")
            self.count += 1
            self.file = McapFile(path, chunk_size=min(CHUNK_BYTES,
                                                      max(self.max_bytes // 8, 1024)))
            self.opened = time.monotonic()
            self.view_bodies.clear()
            say(event="recording", file=path)
            for call, began in self.calls.items():
                self.log_call(call, time.time_ns(), *began, continued=True)
        return self.file

    def rotate_if_due(self, every: int = 1) -> None:
        """A new file next when this one is too large or too old, looked at once ``every``
        messages (the size is a system call)."""
        f = self.file
        self.frames += 1
        if f is None or self.frames % every:
            return
        if f.size >= self.max_bytes or time.monotonic() - self.opened >= self.max_seconds:
            f.close()
            self.file = None

    def log_call(self, call, ns, rpc, req, ans, continued=False) -> None:
        f = self.open()
        f.write_json(f.json_channel(CALLS_TOPIC, "dqpose.record.Call", CALL_FIELDS), ns,
                     {"call": call, "rpc": rpc, "event": "begin", "request_type": req,
                      "answer_type": ans, "continued": continued})

    def channel(self, f: McapFile, topic: str, name: str, call: int):
        return f.proto_channel(topic, name, self.schemas[name], (("call", str(call)),))

    def message(self, name: str, data: bytes):
        cls = self.classes.get(name)
        if cls is None:
            cls = self.classes[name] = message_class(self.schemas[name], name)
        return cls.FromString(data)      # type: ignore[attr-defined]

    def write(self, kind: int, call: int, ns: int, payload: bytes) -> None:
        if kind == frames.SCHEMA:
            name, data = frames.unnamed(payload)
            self.schemas[name] = data
        elif kind == frames.BEGIN:
            d = json.loads(payload)
            self.open()      # first: a file opened now repeats the calls open before it
            self.calls[call] = (d["rpc"], d["request_type"], d["answer_type"])
            self.log_call(call, ns, *self.calls[call])
        elif kind in (frames.REQUEST, frames.ANSWER):
            began = self.calls.get(call)
            if began is None:
                return
            rpc, req, ans = began
            f = self.open()
            if kind == frames.REQUEST:
                f.write(self.channel(f, requests_topic(rpc), req, call), ns, payload)
            else:
                f.write(self.channel(f, answers_topic(rpc), ans, call), ns, payload)
                if ans == "dqpose.v1.FusedPose":
                    self.views(f, ns, self.message(ans, payload))
        elif kind == frames.END:
            d = json.loads(payload)
            f = self.open()      # first: a file opened now says the call began earlier
            began = self.calls.pop(call, None)
            if began is not None:
                rpc, req, ans = began
                f.forget(requests_topic(rpc), req, (("call", str(call)),))
                f.forget(answers_topic(rpc), ans, (("call", str(call)),))
            f.write_json(f.json_channel(CALLS_TOPIC, "dqpose.record.Call", CALL_FIELDS), ns,
                         {"call": call, "event": "end", "code": d["code"],
                          "details": d["details"]})
        elif kind == frames.GAP:
            d = json.loads(payload)
            f = self.open()
            f.write_json(f.json_channel(DROPPED_TOPIC, "dqpose.record.Dropped",
                                        DROPPED_FIELDS), ns,
                         {"first_dropped": d["first_dropped"], "count": d["count"],
                          "resumed": ns})
            say(event="recording_dropped", count=d["count"], first_dropped=d["first_dropped"],
                resumed=ns, file=f.path)
        elif kind == frames.PLAN:
            name, data = frames.unnamed(payload)
            f = self.open()
            f.write(f.channel(plan_topic(name), views.PosesInFrame), ns, data)
        self.rotate_if_due(16 if self.max_bytes >= 1 << 20 else 1)

    def views(self, f: McapFile, ns: int, msg) -> None:
        """The Foxglove views of a fused pose (not of an error entry)."""
        if msg.HasField("error") or not msg.HasField("pose"):
            return
        body = msg.body
        if body not in self.view_bodies:
            if len(self.view_bodies) >= MAX_VIEW_BODIES:
                return
            self.view_bodies.add(body)
        p, o = msg.pose.position, msg.pose.orientation
        t, q = (p.x, p.y, p.z), (o.w, o.x, o.y, o.z)
        f.write(f.channel(pose_topic(body), views.PoseInFrame), ns,
                views.pose_in_frame(ns, t, q).SerializeToString())
        f.write(f.channel(TF_TOPIC, views.FrameTransforms), ns,
                views.frame_transforms(ns, [(views.WORLD, body, t, q)]).SerializeToString())
        if len(msg.covariance) == 36:
            f.write(f.channel(ELLIPSOIDS_TOPIC, views.SceneUpdate), ns, views.scene_update(
                [views.ellipsoid(ns, body, msg.covariance)]).SerializeToString())
        f.write_json(f.json_channel(stats_topic(body), "dqpose.record.FusedStats",
                                    STATS_FIELDS), ns, views.scalars(msg))

    def close(self) -> None:
        if self.file is not None:
            self.file.close()
            self.file = None


def main(argv: list[str]) -> int:
    # It ends when its input does (the server closes it after its last call, or dies), so that
    # the file is finished: a signal meant for the server is not for it.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    directory, max_bytes, max_seconds = argv[0], int(argv[1]), float(argv[2])
    w = Writer(directory, max_bytes, max_seconds)
    fd = sys.stdin.fileno()
    buffer = bytearray()
    try:
        while True:
            ready, _, _ = select.select([fd], [], [], 0.05)
            if not ready:
                w.rotate_if_due()
                continue
            data = os.read(fd, 1 << 20)
            if not data:
                break
            buffer += data
            for kind, call, ns, payload in frames.read_frames(buffer):
                try:
                    w.write(kind, call, ns, payload)
                except Exception as e:     # one message lost, not the recording
                    say(event="recording_failed", kind=kind, error=repr(e))
    finally:
        w.close()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
