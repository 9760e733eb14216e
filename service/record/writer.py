"""The recorder's writer process (``python -m dqpose.record.writer DIR MAX_BYTES MAX_SECONDS
[LIVE]``): frames (:mod:`dqpose.record.frames`) on standard input, MCAP files in DIR (an empty
DIR: none), rotated by size and age, and the same channels on the live WebSocket server when
LIVE is given (:mod:`dqpose.record.live`; JSON: ``host``, ``port``, ``origins``, ``insecure``;
its token in the environment's ``DQPOSE_LIVE_TOKEN``); JSON lines on standard output for the
server to log (``recording``: a file opened, ``recording_dropped``: a drop marker written,
``recording_failed``: the files cannot be written, with the cause, said once until
``recording_resumed``: a new file takes the frames again, behind a marker of those lost;
``recording_counts``: the frames written and lost so far, at most every :data:`COUNTS_PERIOD` s;
``live``: the live server listens, with its port, or ``live_failed``, after which the process
ends; ``live_refused``: a client the live server did not let in, with why). Its own process, so
that neither the writing nor the views nor the compression nor the live server's clients take
the server's interpreter lock. Ends, the file finished, when its input does.
"""
from __future__ import annotations

import json
import os
import select
import signal
import sys
import time
from typing import Any

from dqpose.events import say
from dqpose.record import frames, handeye, types, views
from dqpose.record.live import LiveServer
from dqpose.record.mcapfile import CHUNK_BYTES, McapFile
from dqpose.record.schemas import message_class
from dqpose.record.settings import LIVE_TOKEN_ENV, cannot_write, describe
from dqpose.record.sink import Sink
from dqpose.record.topics import (
    ARM_STATE_FIELDS,
    CALL_FIELDS,
    CALLS_TOPIC,
    DROPPED_FIELDS,
    DROPPED_TOPIC,
    ELLIPSOIDS_TOPIC,
    FEEDBACK_FIELDS,
    MAX_VIEW_BODIES,
    STATS_FIELDS,
    TF_STATIC_TOPIC,
    TF_TOPIC,
    answers_topic,
    arm_topic,
    plan_topic,
    pose_topic,
    requests_topic,
    stats_topic,
)

#: while the files cannot be written, a new one is tried this often (s), once a probe file can be
RETRY_PERIOD = 1.0
#: the frames written and lost are told the server at most this often (s)
COUNTS_PERIOD = 0.25


class Writer:
    """Writes what comes into the MCAP files of ``directory`` (``None``: no files) and the live
    server ``live`` (``None``: none): the same channels, built here once for both."""

    def __init__(self, directory: str | None, max_bytes: int, max_seconds: float,
                 live: LiveServer | None = None):
        self.directory, self.max_bytes, self.max_seconds = directory, max_bytes, max_seconds
        self.live = live
        self.file: McapFile | None = None
        # every file of this run named after its start, numbered: the run's files are found
        # and ordered by their names alone (dqpose.record.reader.runs)
        self.run = time.strftime("dqpose-%Y%m%dT%H%M%SZ", time.gmtime())
        self.opened = 0.0
        self.count = 0
        self.frames = 0
        self.schemas: dict[str, bytes] = {}
        self.classes: dict[str, object] = {}
        # rpc, types, world, internal
        self.calls: dict[int, tuple[str, str, str, str, bool]] = {}
        # the request of a call whose answers' views need it (an Execute's arm, a Calibrate's
        # views and setup)
        self.requests: dict[int, Any] = {}
        # each world's last /tf_static message (its frames fixed in their parents), latched:
        # repeated at the start of every later file
        self.latched: dict[str, bytes] = {}
        # frames (schemas aside) a file took, and those lost because no file could be written
        # (a file's last chunk, being filled when its write failed, is lost with it uncounted)
        self.written = self.failed = 0
        # while the files cannot be written: [why, ns of the first frame lost, frames lost]
        self.failure: list | None = None
        self.retry_at = 0.0
        self.told = (0, 0, 0.0)     # the counts last told the server, and when

    def open(self) -> McapFile | None:
        """The file frames go to (a new one when there is none); ``None`` while files cannot be
        written (tried again every :data:`RETRY_PERIOD` s)."""
        if self.file is None:
            assert self.directory is not None
            if self.failure is not None:
                if time.monotonic() < self.retry_at:
                    return None
                if cannot_write(self.directory) is not None:
                    self.retry_at = time.monotonic() + RETRY_PERIOD
                    return None
            path = os.path.join(self.directory, f"{self.run}-{self.count:04d}.mcap")
            self.count += 1
            try:
                self.file = McapFile(path, chunk_size=min(CHUNK_BYTES,
                                                          max(self.max_bytes // 8, 1024)))
            except (OSError, RuntimeError) as e:
                self.fail(e, time.time_ns(), path)
                return None
            self.opened = time.monotonic()
            say(event="recording", file=path)
            if self.failure is not None:
                self.resume(self.file)
            for call, began in self.calls.items():
                self.log_call((self.file,), call, time.time_ns(), *began, continued=True)
            for data in self.latched.values():
                self.file.write(self.file.channel(TF_STATIC_TOPIC, views.FrameTransforms),
                                time.time_ns(), data)
        return self.file

    def fail(self, error: BaseException, ns: int, path: str | None = None) -> None:
        """The files cannot be written (``error``, found at frame time ``ns``): the file is
        given up (cut where its writes failed), said once until a new one can be written."""
        if self.file is not None:
            path = self.file.path
            try:
                self.file.close()
            except (OSError, RuntimeError):
                pass
            self.file = None
        self.retry_at = time.monotonic() + RETRY_PERIOD
        if self.failure is None:
            self.failure = [describe(error), ns, 0]
            say(event="recording_failed", file=path, error=self.failure[0])

    def resume(self, file: McapFile) -> None:
        """A file takes frames again: it begins with the marker of those lost."""
        why, first, count = self.failure or ("", 0, 0)
        self.failure = None
        ns = time.time_ns()
        file.write_json(file.json_channel(DROPPED_TOPIC, "dqpose.record.Dropped",
                                          DROPPED_FIELDS), ns,
                        {"first_dropped": first, "count": count, "resumed": ns, "error": why})
        say(event="recording_resumed", file=file.path, lost=count, first_lost=first,
            error=why)

    def sinks(self) -> list[Sink]:
        """Where a message goes: the file (opened when there is none and files can be written)
        and the live server."""
        out: list[Sink] = []
        if self.directory is not None and (f := self.open()) is not None:
            out.append(f)
        if self.live is not None:
            out.append(self.live)
        return out

    def rotate_if_due(self, every: int = 1) -> None:
        """A new file next when this one is too large or too old, looked at once ``every``
        messages (the size is a system call)."""
        f = self.file
        self.frames += 1
        if f is None or self.frames % every:
            return
        if f.size >= self.max_bytes or time.monotonic() - self.opened >= self.max_seconds:
            try:
                f.close()
            except (OSError, RuntimeError) as e:
                self.fail(f.error or e, time.time_ns())
            self.file = None

    @staticmethod
    def log_call(sinks, call, ns, rpc, req, ans, world="", internal=False,
                 continued=False) -> None:
        begin = {"call": call, "rpc": rpc, "event": "begin", "request_type": req,
                 "answer_type": ans, "continued": continued}
        if world:
            begin["world"] = world
        if internal:
            begin["internal"] = True
        for s in sinks:
            s.write_json(s.json_channel(CALLS_TOPIC, "dqpose.record.Call", CALL_FIELDS), ns,
                         begin)

    def channel(self, s: Sink, topic: str, name: str, call: int):
        return s.proto_channel(topic, name, self.schemas[name], (("call", str(call)),))

    def message(self, name: str, data: bytes):
        cls = self.classes.get(name)
        if cls is None:
            cls = self.classes[name] = message_class(self.schemas[name], name)
        return cls.FromString(data)      # type: ignore[attr-defined]

    def write(self, kind: int, call: int, ns: int, payload: bytes) -> None:
        """One frame to every sink; counted written, or lost when the files fail."""
        lost = False
        try:
            self.put(kind, call, ns, payload)
        except Exception as e:     # one message lost, not the recording
            say(event="recording_message_failed", kind=kind, error=repr(e))
            lost = True
        if self.file is not None and self.file.error is not None:
            self.fail(self.file.error, ns)
        if kind != frames.SCHEMA:
            if self.failure is not None:
                if not self.failure[2]:
                    self.failure[1] = ns
                self.failure[2] += 1
                lost = True
            self.failed += lost
            self.written += not lost
        self.rotate_if_due(16 if self.max_bytes >= 1 << 20 else 1)

    def tell_counts(self, now: float, force: bool = False) -> None:
        """``recording_counts`` when they changed, at most every :data:`COUNTS_PERIOD` s."""
        written, failed, when = self.told
        if (self.written, self.failed) != (written, failed) and (
                force or now - when >= COUNTS_PERIOD):
            self.told = (self.written, self.failed, now)
            say(event="recording_counts", written=self.written, failed=self.failed)

    def put(self, kind: int, call: int, ns: int, payload: bytes) -> None:
        if kind == frames.SCHEMA:
            name, data = frames.unnamed(payload)
            self.schemas[name] = data
        elif kind == frames.BEGIN:
            d = json.loads(payload)
            sinks = self.sinks()    # first: a file opened now repeats the calls open before it
            self.calls[call] = (d["rpc"], d["request_type"], d["answer_type"],
                                d.get("world", ""), d.get("internal", False))
            self.log_call(sinks, call, ns, *self.calls[call])
        elif kind in (frames.REQUEST, frames.ANSWER):
            began = self.calls.get(call)
            if began is None:
                return
            rpc, req, ans, world, _ = began
            sinks = self.sinks()
            if kind == frames.REQUEST:
                for s in sinks:
                    s.write(self.channel(s, requests_topic(rpc), req, call), ns, payload)
                if req in KEPT_REQUESTS:
                    self.requests[call] = self.message(req, payload)
            else:
                for s in sinks:
                    s.write(self.channel(s, answers_topic(rpc), ans, call), ns, payload)
                draw = ANSWER_VIEWS.get(ans)
                if draw is not None and (ans not in NEEDS_REQUEST or call in self.requests):
                    draw(self, sinks, ns, self.requests.get(call), world,
                         self.message(ans, payload))
        elif kind == frames.END:
            d = json.loads(payload)
            sinks = self.sinks()    # first: a file opened now says the call began earlier
            began = self.calls.pop(call, None)
            self.requests.pop(call, None)
            for s in sinks:
                if began is not None:
                    rpc, req, ans, *_ = began
                    s.forget(requests_topic(rpc), req, (("call", str(call)),))
                    s.forget(answers_topic(rpc), ans, (("call", str(call)),))
                s.write_json(s.json_channel(CALLS_TOPIC, "dqpose.record.Call", CALL_FIELDS),
                             ns, {"call": call, "event": "end", "code": d["code"],
                                  "details": d["details"]})
        elif kind == frames.GAP:
            d = json.loads(payload)
            for s in self.sinks():
                s.write_json(s.json_channel(DROPPED_TOPIC, "dqpose.record.Dropped",
                                            DROPPED_FIELDS), ns,
                             {"first_dropped": d["first_dropped"], "count": d["count"],
                              "resumed": ns})
            say(event="recording_dropped", count=d["count"], first_dropped=d["first_dropped"],
                resumed=ns, file=self.file.path if self.file is not None else None)
        elif kind == frames.NOTE:
            d = json.loads(payload)
            fields = {k: views.json_type(v) for k, v in d["data"].items()}
            for s in self.sinks():
                s.write_json(s.json_channel(d["topic"], d["title"], fields), ns, d["data"])
        elif kind == frames.PLAN:
            name, data = frames.unnamed(payload)
            for s in self.sinks():
                s.write(s.channel(plan_topic(name), views.PosesInFrame), ns, data)

    @staticmethod
    def fused_views(s: Sink, ns: int, msg) -> None:
        """The Foxglove views of a fused pose (not of an error entry), logged at its arrival
        ``ns``, stamped with its own time."""
        if msg.HasField("error") or not msg.HasField("pose"):
            return
        body = msg.body
        if body not in s.view_bodies:
            if len(s.view_bodies) >= MAX_VIEW_BODIES:
                return
            s.view_bodies.add(body)
        p, o = msg.pose.position, msg.pose.orientation
        t, q = (p.x, p.y, p.z), (o.w, o.x, o.y, o.z)
        at = views.time_ns(msg.time)
        s.write(s.channel(pose_topic(body), views.PoseInFrame), ns,
                views.pose_in_frame(at, t, q).SerializeToString())
        s.write(s.channel(TF_TOPIC, views.FrameTransforms), ns,
                views.frame_transforms(at, [(views.WORLD, body, t, q)]).SerializeToString())
        if len(msg.covariance) == 36:
            s.write(s.channel(ELLIPSOIDS_TOPIC, views.SceneUpdate), ns, views.scene_update(
                [views.ellipsoid(at, body, msg.covariance)]).SerializeToString())
        s.write_json(s.json_channel(stats_topic(body), "dqpose.record.FusedStats",
                                    STATS_FIELDS), ns, views.scalars(msg))

    def static_views(self, sinks, ns: int, world: str, config) -> None:
        """A World's configuration in force (Configure's answer) on ``/tf_static``: one message
        of its statics and sources, kept as the world's latched one (none when it has none)."""
        msg = views.static_transforms(config)
        if not msg.transforms:
            self.latched.pop(world, None)
            return
        self.latched[world] = data = msg.SerializeToString()
        for s in sinks:
            s.write(s.channel(TF_STATIC_TOPIC, views.FrameTransforms), ns, data)

    @staticmethod
    def feedback_views(s: Sink, ns: int, arm: str, msg) -> None:
        """An Execute feedback's views: the commanded and the actual pose, the arm's tool on
        ``/tf``, the state and the tracking error as scalars."""
        for what in ("commanded", "actual"):
            if msg.HasField(what):
                t, q = views.pose_of(getattr(msg, what))
                s.write(s.channel(arm_topic(arm, what), views.PoseInFrame), ns,
                        views.pose_in_frame(ns, t, q).SerializeToString())
        if msg.HasField("actual"):
            Writer.tool_tf(s, ns, arm, msg.actual)
        s.write_json(s.json_channel(arm_topic(arm, "feedback"), "dqpose.record.ArmFeedback",
                                    FEEDBACK_FIELDS), ns, views.feedback_scalars(msg))

    @staticmethod
    def arm_views(s: Sink, ns: int, msg) -> None:
        """A watched arm's views (WatchArm): its actual pose, its tool on ``/tf``, its state,
        speeds and limits as scalars."""
        if msg.HasField("pose"):
            t, q = views.pose_of(msg.pose)
            s.write(s.channel(arm_topic(msg.arm, "actual"), views.PoseInFrame), ns,
                    views.pose_in_frame(ns, t, q).SerializeToString())
            Writer.tool_tf(s, ns, msg.arm, msg.pose)
        s.write_json(s.json_channel(arm_topic(msg.arm, "state"), "dqpose.record.ArmState",
                                    ARM_STATE_FIELDS), ns, views.arm_scalars(msg))

    @staticmethod
    def handeye_views(s: Sink, ns: int, request, answer) -> None:
        """A hand-eye calibration's views (:mod:`dqpose.record.handeye`)."""
        if not answer.HasField("x") or not request.pairs:
            return
        s.write(s.channel(TF_TOPIC, views.FrameTransforms), ns, views.frame_transforms(
            ns, handeye.transforms(request, answer)).SerializeToString())
        _, x, z = handeye.TF
        s.write(s.channel(handeye.ELLIPSOIDS_TOPIC, views.SceneUpdate), ns, views.scene_update(
            [views.ellipsoid(ns, x, answer.covariance_x),
             views.ellipsoid(ns, z, answer.covariance_z)]).SerializeToString())
        for topic, path in zip((handeye.FLANGES_TOPIC, handeye.TARGETS_TOPIC),
                               handeye.paths(request, answer)):
            s.write(s.channel(topic, views.PosesInFrame), ns,
                    views.poses_in_frame(ns, path).SerializeToString())
        channel = s.json_channel(handeye.RESIDUALS_TOPIC, "dqpose.record.HandEyeResidual",
                                 handeye.RESIDUAL_FIELDS)
        for row in handeye.residuals(answer, len(request.pairs)):
            s.write_json(channel, ns, row)

    @staticmethod
    def tool_tf(s: Sink, ns: int, arm: str, pose) -> None:
        t, q = views.pose_of(pose)
        s.write(s.channel(TF_TOPIC, views.FrameTransforms), ns, views.frame_transforms(
            ns, [(views.WORLD, views.tool_frame(arm), t, q)]).SerializeToString())

    def close(self) -> None:
        if self.file is not None:
            try:
                self.file.close()
            except (OSError, RuntimeError) as e:
                self.fail(self.file.error or e, time.time_ns())
            self.file = None
        if self.live is not None:
            self.live.close()
            self.live = None

def _fused(w: Writer, sinks, ns: int, request, world: str, msg) -> None:
    for s in sinks:
        w.fused_views(s, ns, msg)


def _arm_state(w: Writer, sinks, ns: int, request, world: str, msg) -> None:
    for s in sinks:
        w.arm_views(s, ns, msg)


def _feedback(w: Writer, sinks, ns: int, request, world: str, msg) -> None:
    for s in sinks:
        w.feedback_views(s, ns, request.arm, msg)


def _calibration(w: Writer, sinks, ns: int, request, world: str, msg) -> None:
    for s in sinks:
        w.handeye_views(s, ns, request, msg)


def _config(w: Writer, sinks, ns: int, request, world: str, msg) -> None:
    w.static_views(sinks, ns, world, msg)


#: the views an answer draws, by its type: ``draw(writer, sinks, ns, the call's kept request,
#: its world, the answer)``
ANSWER_VIEWS = {
    types.FUSED_POSE: _fused,
    types.ARM_STATE: _arm_state,
    types.EXECUTION_FEEDBACK: _feedback,
    types.CALIBRATE_RESPONSE: _calibration,
    types.WORLD_CONFIG: _config,
}
#: the requests a call's answers' views need (an Execute's arm, a Calibrate's views and setup),
#: kept until the call ends, and the answers drawn only with them
KEPT_REQUESTS = (types.EXECUTE_REQUEST, types.CALIBRATE_REQUEST)
NEEDS_REQUEST = (types.EXECUTION_FEEDBACK, types.CALIBRATE_RESPONSE)

#: how far below the server the writer's scheduling priority is (``nice``)
WRITER_NICE = 10


def main(argv: list[str]) -> int:
    # It ends when its input does (the server closes it after its last call, or dies), so that
    # the file is finished: a signal meant for the server is not for it.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    # Below the server and its clients on a shared CPU: the writer works in bursts (a read of
    # many frames, a chunk compressed), and a burst on the CPU an RPC's thread waits for delays
    # that answer; niced, the scheduler hands the CPU back as soon as they wake. A writer that
    # then falls behind drops recording messages, counted, never RPCs.
    os.nice(WRITER_NICE)
    directory, max_bytes, max_seconds = argv[0] or None, int(argv[1]), float(argv[2])
    live = None
    if len(argv) > 3:
        opts = json.loads(argv[3])
        host, port = opts["host"], opts["port"]
        try:
            live = LiveServer(host, port, token=os.environ.pop(LIVE_TOKEN_ENV, None),
                              origins=opts["origins"], insecure=opts["insecure"], say=say)
        except (OSError, RuntimeError) as e:
            say(event="live_failed", host=host, port=port, error=describe(e))
            return 1
        say(event="live", host=host, port=live.port, token=live.token is not None,
            origins=sorted(live.origins), insecure=live.insecure)
    w = Writer(directory, max_bytes, max_seconds, live)
    fd = sys.stdin.fileno()
    buffer = bytearray()
    try:
        while True:
            ready, _, _ = select.select([fd], [], [], 0.05)
            if not ready:
                w.rotate_if_due()
                if w.failure is not None:
                    w.open()        # a file again once one can be written, frames or none
                w.tell_counts(time.monotonic())
                continue
            data = os.read(fd, 1 << 20)
            if not data:
                break
            buffer += data
            for kind, call, ns, payload in frames.read_frames(buffer):
                w.write(kind, call, ns, payload)
            w.tell_counts(time.monotonic())
    finally:
        w.close()
        w.tell_counts(time.monotonic(), force=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
