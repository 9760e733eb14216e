"""The server-wide recorder: what the servicers hand it is queued (a bounded deque, on their own
thread, no I/O) and written to MCAP files by one writer thread, which rotates them by size and age.

When the writer falls behind and the queue is full, what comes is dropped, counted
(:attr:`Recorder.dropped`) and, once there is room again, a marker goes in the file where the
messages are missing (``/dqpose/record/dropped``) and a line in the log: a replay stops there.
An RPC never waits for the disk.
"""
from __future__ import annotations

import collections
import json
import logging
import os
import threading
import time

from dqpose.record import views
from dqpose.record.mcapfile import CHUNK_BYTES, McapFile

log = logging.getLogger("dqpose.record")

#: the call log: one JSON object a call's beginning (with what it records) and end
CALLS_TOPIC = "/dqpose/calls"
#: where messages are missing (the writer fell behind)
DROPPED_TOPIC = "/dqpose/record/dropped"
TF_TOPIC = "/tf"
ELLIPSOIDS_TOPIC = "/fused/ellipsoids"
#: views are drawn for this many bodies a file at most (each has its channels)
MAX_VIEW_BODIES = 1000


def requests_topic(rpc: str) -> str:
    return f"/dqpose/{rpc}/requests"


def answers_topic(rpc: str) -> str:
    return f"/dqpose/{rpc}/answers"


def pose_topic(body: str) -> str:
    return f"/fused/{body}"


def stats_topic(body: str) -> str:
    return f"/fused/{body}/stats"


def plan_topic(name: str) -> str:
    return f"/plans/{name}"


_CALL_FIELDS = {"call": "integer", "rpc": "string", "event": "string",
                "request_type": "string", "answer_type": "string", "code": "string",
                "details": "string", "continued": "boolean"}
_DROPPED_FIELDS = {"first_dropped": "integer", "count": "integer", "resumed": "integer"}
_STATS_FIELDS = {"body": "string", "time": "number", "chi2": "number", "dof": "integer",
                 "sigma_position": "number", "sigma_rotation": "number"}


class CallRecord:
    """What one call records: :meth:`measurements` (a request as it arrived), :meth:`fused` (an
    answer, a ``dqpose.v1.FusedPose`` or another message), :meth:`end`. Each takes the message
    or its wire bytes; serialising and parsing happen on the writer's thread."""

    __slots__ = ("recorder", "id", "alive")

    def __init__(self, recorder: "Recorder", call: int, alive: bool):
        self.recorder, self.id, self.alive = recorder, call, alive

    def measurements(self, request) -> None:
        self.recorder._put(self, ("request", self.id, time.time_ns(), request))

    def fused(self, answer) -> None:
        self.recorder._put(self, ("answer", self.id, time.time_ns(), answer))

    def end(self, code: str, details: str = "") -> None:
        """The call ended with status ``code`` (``"OK"``, ``"INVALID_ARGUMENT"``, ...) and, for
        a refusal, its ``details``."""
        self.recorder._put(self, ("end", self.id, time.time_ns(), (code, details)))


class Recorder:
    """Records calls into MCAP files in ``directory`` (``dqpose-<UTC time>-<n>.mcap``), a new
    file once one holds ``max_bytes`` or is ``max_seconds`` old. ``queue``: messages waiting at
    most (beyond: dropped). :meth:`close` writes what is queued and finishes the file.

    ``stall`` is a test hook: while it is set the writer writes nothing (a disk that hangs)."""

    def __init__(self, directory: str | os.PathLike, max_bytes: int = 256 << 20,
                 max_seconds: float = 3600.0, queue: int = 100_000):
        if not (isinstance(max_bytes, int) and max_bytes > 0):
            raise ValueError(f"max_bytes: must be a positive integer, got {max_bytes!r}")
        if not (max_seconds > 0):
            raise ValueError(f"max_seconds: must be > 0, got {max_seconds!r}")
        if not (isinstance(queue, int) and queue > 0):
            raise ValueError(f"queue: must be a positive integer, got {queue!r}")
        self.directory = os.fspath(directory)
        os.makedirs(self.directory, exist_ok=True)
        self.max_bytes, self.max_seconds, self.capacity = max_bytes, max_seconds, queue
        self.stall = threading.Event()
        self.files: list[str] = []
        self.written = 0
        self.dropped = 0
        self._q: collections.deque = collections.deque()
        self._lock = threading.Lock()
        self._calls = 0
        self._gap = 0              # dropped since the last marker
        self._gap_ns = 0           # when the first of them was dropped
        self._closing = False
        self._file: McapFile | None = None
        self._opened = 0.0
        self._open_calls: dict[int, tuple] = {}
        self._view_bodies: set[str] = set()
        self._thread = threading.Thread(target=self._run, name="dqpose-record", daemon=True)
        self._thread.start()

    # -- the servicers' side: no I/O, no waiting

    def call(self, rpc: str, request_type, answer_type) -> CallRecord:
        """A call of ``rpc`` (``"dqpose.v1.Fusion/StreamFuse"``) begins; its requests are
        ``request_type`` messages, its answers ``answer_type`` (protobuf classes)."""
        with self._lock:
            self._calls += 1
            call = self._calls
        rec = CallRecord(self, call, True)
        rec.alive = self._put(rec, ("begin", call, time.time_ns(),
                                    (rpc, request_type, answer_type)))
        return rec

    def plan(self, name: str, dqs) -> None:
        """A planned path (dual quaternions ``(n, 8)``, world frame) on ``/plans/<name>``."""
        self._put(None, ("plan", 0, time.time_ns(), (name, dqs)))

    def _put(self, rec, item) -> bool:
        with self._lock:
            if len(self._q) >= self.capacity or (rec is not None and not rec.alive):
                if not self._gap:
                    self._gap_ns = item[2]
                self._gap += 1
                self.dropped += 1
                return False
            if self._gap:
                self._q.append(("gap", 0, item[2], (self._gap_ns, self._gap)))
                self._gap = 0
            self._q.append(item)
            return True

    # -- the writer thread

    def _run(self) -> None:
        q = self._q
        while True:
            if self.stall.is_set():
                time.sleep(0.01)
                continue
            try:
                item = q.popleft()
            except IndexError:
                if self._closing:
                    break
                if self._file is not None and time.monotonic() - self._opened >= self.max_seconds:
                    self._rotate()
                time.sleep(0.002)
                continue
            try:
                self._write(item)
            except Exception:
                log.exception(json.dumps({"event": "recording_failed", "message": item[0]}))
        if self._file is not None:
            self._file.close()
            self._file = None

    def _open(self) -> McapFile:
        if self._file is None:
            name = time.strftime("dqpose-%Y%m%dT%H%M%SZ", time.gmtime())
            path = os.path.join(self.directory, f"{name}-{len(self.files):04d}.mcap")
            # a file is at most a chunk over max_bytes (a chunk is written when full)
            self._file = McapFile(path, chunk_size=min(CHUNK_BYTES, max(self.max_bytes // 8, 1024)))
            self._opened = time.monotonic()
            self._view_bodies.clear()
            self.files.append(path)
            log.info(json.dumps({"event": "recording", "file": path}))
            for call, (rpc, req, ans) in self._open_calls.items():
                self._log_call(call, time.time_ns(), rpc, req, ans, continued=True)
        return self._file

    def _rotate(self) -> None:
        assert self._file is not None
        self._file.close()
        self._file = None

    def _log_call(self, call, ns, rpc, req, ans, continued=False) -> None:
        f = self._open()
        f.write_json(f.json_channel(CALLS_TOPIC, "dqpose.record.Call", _CALL_FIELDS), ns,
                     {"call": call, "rpc": rpc, "event": "begin",
                      "request_type": req.DESCRIPTOR.full_name,
                      "answer_type": ans.DESCRIPTOR.full_name, "continued": continued})

    def _write(self, item) -> None:
        kind, call, ns, payload = item
        if kind == "begin":
            self._open()        # first: a file opened now repeats the calls open before it
            self._open_calls[call] = payload
            self._log_call(call, ns, *payload)
        elif kind in ("request", "answer"):
            rpc, req, ans = self._open_calls[call]
            cls = req if kind == "request" else ans
            topic = requests_topic(rpc) if kind == "request" else answers_topic(rpc)
            data = payload if isinstance(payload, bytes) else payload.SerializeToString()
            f = self._open()
            f.write(f.channel(topic, cls, (("call", str(call)),)), ns, data)
            if kind == "answer":
                msg = cls.FromString(payload) if isinstance(payload, bytes) else payload
                self._views(f, ns, msg)
        elif kind == "end":
            f = self._open()    # first: a file opened now says the call began earlier
            began = self._open_calls.pop(call, None)
            if began is not None:
                rpc, req, ans = began
                f.forget(requests_topic(rpc), req, (("call", str(call)),))
                f.forget(answers_topic(rpc), ans, (("call", str(call)),))
            f.write_json(f.json_channel(CALLS_TOPIC, "dqpose.record.Call", _CALL_FIELDS), ns,
                         {"call": call, "event": "end", "code": payload[0],
                          "details": payload[1]})
        elif kind == "gap":
            first, count = payload
            f = self._open()
            f.write_json(f.json_channel(DROPPED_TOPIC, "dqpose.record.Dropped",
                                        _DROPPED_FIELDS), ns,
                         {"first_dropped": first, "count": count, "resumed": ns})
            log.warning(json.dumps({"event": "recording_dropped", "count": count,
                                    "first_dropped": first / 1e9, "resumed": ns / 1e9,
                                    "file": f.path, "replay": "stops there"}))
        elif kind == "plan":
            name, dqs = payload
            f = self._open()
            f.write(f.channel(plan_topic(name), views.PosesInFrame), ns,
                    views.poses_in_frame(ns, dqs).SerializeToString())
        self.written += 1
        if self._file is not None and self._file.size >= self.max_bytes:
            self._rotate()

    def _views(self, f: McapFile, ns: int, msg) -> None:
        """The Foxglove views of a fused pose (not of an error entry, nor of another kind of
        answer)."""
        if not (hasattr(msg, "covariance") and msg.HasField("pose")) or \
                (hasattr(msg, "error") and msg.HasField("error")):
            return
        body = msg.body
        if body not in self._view_bodies:
            if len(self._view_bodies) >= MAX_VIEW_BODIES:
                return
            self._view_bodies.add(body)
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
                                    _STATS_FIELDS), ns, views.scalars(msg))

    def close(self, timeout: float = 30.0) -> None:
        """Writes what is queued (unless stalled) and finishes the file."""
        self.stall.clear()
        self._closing = True
        self._thread.join(timeout)
        if self._thread.is_alive():
            log.warning(json.dumps({"event": "recording_unfinished", "timeout_s": timeout}))
