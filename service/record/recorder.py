"""The server-wide recorder: what the servicers hand it becomes frames in a bounded buffer
(no waiting, no disk), written to a pipe that does not block, whose other end is the writer
process (:mod:`dqpose.record.writer`): the MCAP files, their rotation, the Foxglove views and the
compression all run there, where they cannot hold the server's interpreter lock. (In a thread,
the writer's work, ~14 us a message, cost the server's event loop 80 us a message and 7-12 ms of
p99 latency at 2,000 messages/s in lock hand-offs: docs/benchmarks/record.md.)

When the writer falls behind (the pipe is full, the buffer reaches ``queue`` messages or
``max_buffer`` bytes), what comes is dropped and counted (:attr:`Recorder.dropped`), and once
there is room again a marker goes where the messages are missing (``/dqpose/record/dropped``),
which the writer logs and a replay stops at. An RPC never waits for the disk.

When the files cannot be written (a full disk, a read-only one), the writer says so once, with the
cause (``recording_failed``, logged here), and counts what it cannot write
(:attr:`Recorder.failed`); :attr:`Recorder.failure` says why until a new file can be written
(``recording_resumed``; it begins with the marker of what was lost), and :meth:`Recorder.watch`
hears each change (the server's health service ``dqpose.record``). A directory that cannot be
written at all is refused at the start.
"""
from __future__ import annotations

import collections
import fcntl
import json
import logging
import math
import os
import subprocess
import sys
import threading
import time

from dqpose.record import frames
from dqpose.record.schemas import descriptor_set
from dqpose.record.settings import LIVE_TOKEN_ENV, LiveFailed, cannot_write, live_problem

log = logging.getLogger("dqpose.record")

#: a flush when this much is waiting, else at most every FLUSH_PERIOD s
FLUSH_BYTES = 64 << 10
FLUSH_PERIOD = 0.005
#: what is left waiting when messages stop is handed over within this many s
IDLE_FLUSH = 0.05
_F_SETPIPE_SZ = 1031


class CallRecord:
    """What one call records: :meth:`request` (a request as it arrived), :meth:`answer` (an
    answer), :meth:`end`. Each takes the message or its wire bytes."""

    __slots__ = ("recorder", "id", "alive")

    def __init__(self, recorder: "Recorder", call: int, alive: bool):
        self.recorder, self.id, self.alive = recorder, call, alive

    def request(self, request) -> None:
        if not isinstance(request, bytes):
            request = request.SerializeToString()
        self.recorder._put(self, frames.REQUEST, self.id, request)

    def answer(self, answer) -> None:
        if not isinstance(answer, bytes):
            answer = answer.SerializeToString()
        self.recorder._put(self, frames.ANSWER, self.id, answer)

    def end(self, code: str, details: str = "") -> None:
        """The call ended with status ``code`` (``"OK"``, ``"INVALID_ARGUMENT"``, ...) and, for
        a refusal, its ``details``."""
        self.recorder._put(self, frames.END, self.id,
                           frames.as_json({"code": code, "details": details}))


def _writer_process(directory, max_bytes, max_seconds, live, live_token, live_origins,
                    live_insecure) -> subprocess.Popen:
    """The writer process (:mod:`dqpose.record.writer`) started, its input and output pipes."""
    live_args = [] if live is None else [json.dumps(
        {"host": live[0], "port": live[1], "origins": list(live_origins),
         "insecure": live_insecure})]
    # the token in the writer's environment, which only its user can read (not its argv)
    env = {k: v for k, v in os.environ.items() if k != LIVE_TOKEN_ENV}
    if live is not None and live_token is not None:
        env[LIVE_TOKEN_ENV] = live_token
    return subprocess.Popen(
        [sys.executable, "-m", "dqpose.record.writer", directory or "", str(max_bytes),
         repr(float(max_seconds)), *live_args],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, bufsize=0, env=env,
        # out of the server's process group: a Ctrl-C at its terminal (SIGINT to the group)
        # must not end the writer, even while it starts; it ends when its input does
        start_new_session=True)


class Recorder:
    """Records calls into MCAP files in ``directory`` (``dqpose-<UTC time>-<n>.mcap``; ``None``:
    no files), a new file once one holds ``max_bytes`` or is ``max_seconds`` old, and serves
    the same channels live on ``live`` (``(host, port)``, port 0 a free one; ``None``: no live
    view), :attr:`live_port` its port, to the clients ``live_token`` (the server's bearer token),
    ``live_origins`` and ``live_insecure`` let in (:mod:`dqpose.record.live`; ``ValueError``
    beyond the loopback without a token or ``live_insecure``);
    :class:`~dqpose.record.LiveFailed` when it cannot listen. ``queue`` messages (and
    ``max_buffer`` bytes) wait for the writer at most; beyond, they are dropped. :meth:`close`
    hands over what is waiting and waits for the file to be finished.

    ``stall`` is a test hook: while it is set nothing is handed to the writer (a disk that
    hangs).

    Counted in messages (schemas aside): :attr:`written` to the files (or the live server alone),
    as the writer last told (every 0.25 s at most); :attr:`dropped` before the writer, the
    recording behind; :attr:`failed` lost because the files could not be written or the writer
    ended. ``OSError`` when ``directory`` cannot be written into."""

    recording = True

    def __init__(self, directory: str | os.PathLike | None, max_bytes: int = 256 << 20,
                 max_seconds: float = 3600.0, queue: int = 100_000,
                 max_buffer: int = 64 << 20, live: tuple[str, int] | None = None,
                 live_token: str | None = None, live_origins=(), live_insecure: bool = False,
                 world_rate: float = 30.0):
        if not (isinstance(max_bytes, int) and max_bytes > 0):
            raise ValueError(f"max_bytes: must be a positive integer, got {max_bytes!r}")
        if not (max_seconds > 0):
            raise ValueError(f"max_seconds: must be > 0, got {max_seconds!r}")
        if not (isinstance(queue, int) and queue > 0):
            raise ValueError(f"queue: must be a positive integer, got {queue!r}")
        if not (isinstance(world_rate, (int, float)) and 0 < world_rate < math.inf):
            raise ValueError(f"world_rate: must be a rate > 0 Hz, got {world_rate!r}")
        #: the rate (Hz of measurement time) at which the recorder's own subscriber records every
        #: body of a world (dqpose.rpc.world._follow)
        self.world_rate = float(world_rate)
        self._internal: list[CallRecord] = []
        if directory is None and live is None:
            raise ValueError("directory: None needs a live address")
        if live is not None and (why := live_problem(*live, live_token, live_insecure)):
            raise ValueError(why)
        self.directory = None if directory is None else os.fspath(directory)
        if self.directory is not None:
            os.makedirs(self.directory, exist_ok=True)
            if (e := cannot_write(self.directory)) is not None:
                raise OSError(e.errno, f"cannot write into it: {e.strerror or e}")
        #: the live server's port once it listens
        self.live_port: int | None = None
        self._live_said = threading.Event()
        self._live_error = ""
        self.capacity, self.max_buffer = queue, max_buffer
        self.stall = threading.Event()
        self.files: list[str] = []
        self.written = 0            # messages written, as the writer last told
        self.handed = 0             # messages handed to the writer
        self.dropped = 0
        self._failed = [0, 0]       # lost: as the writer last told, and here (the writer gone)
        #: why the files are not written now (None: they are)
        self.failure: str | None = None
        self._watchers: list = []
        self._buf = bytearray()
        self._lengths: collections.deque = collections.deque()   # of the frames in _buf
        self._head = 0              # bytes of _lengths[0] written already
        self._pending = 0           # messages (schemas aside) in _buf
        self._lock = threading.Lock()
        self._calls = 0
        self._gap = 0               # dropped since the last marker
        self._gap_ns = 0            # when the first of them arrived
        self._schemas: set[str] = set()
        self._flushed = 0.0
        self._closed = False
        self._gone = False          # the writer ended before close
        self._proc = _writer_process(self.directory, max_bytes, max_seconds, live, live_token,
                                     live_origins, live_insecure)
        assert self._proc.stdin is not None
        self._fd = self._proc.stdin.fileno()
        os.set_blocking(self._fd, False)
        try:
            fcntl.fcntl(self._fd, _F_SETPIPE_SZ, 1 << 20)   # Linux: fewer, larger writes
        except OSError:
            pass
        self._events = threading.Thread(target=self._read_events, name="dqpose-record-log",
                                        daemon=True)
        self._events.start()
        self._flusher = threading.Thread(target=self._flush_periodically,
                                         name="dqpose-record-flush", daemon=True)
        self._flusher.start()
        if live is not None:
            self._wait_for_live(live)

    def _wait_for_live(self, live: tuple[str, int], timeout: float = 30.0) -> None:
        """Until the writer says its live server listens (or cannot)."""
        if not self._live_said.wait(timeout) or self.live_port is None:
            why = self._live_error or f"the writer process did not start it in {timeout:g} s"
            self.close(timeout=5.0)
            raise LiveFailed(f"--live {live[0]}:{live[1]}: {why}")

    # -- the servicers' side: no waiting

    def call(self, rpc: str, request_type, answer_type, world: str = "",
             internal: bool = False) -> CallRecord:
        """A call of ``rpc`` (``"dqpose.v1.Fusion/StreamFuse"``) begins; its requests are
        ``request_type`` messages, its answers ``answer_type`` (protobuf classes); ``world``:
        the named world a World call is in (its ``x-dqpose-world``); ``internal``: the server's
        own, no client's (its call log says so), ended ``OK`` by :meth:`close` if not before."""
        names = (request_type.DESCRIPTOR.full_name, answer_type.DESCRIPTOR.full_name)
        with self._lock:
            self._calls += 1
            call = self._calls
            rec = CallRecord(self, call, False)
            ns = time.time_ns()
            if not self._full():
                # the schemas first, outside the count: the writer cannot do without them
                for cls, name in zip((request_type, answer_type), names):
                    if name not in self._schemas:
                        self._schemas.add(name)
                        self._append(frames.frame(frames.SCHEMA, 0, ns, frames.named(
                            name, descriptor_set(cls))), counted=False)
            begin = {"rpc": rpc, "request_type": names[0], "answer_type": names[1]}
            if world:
                begin["world"] = world
            if internal:
                begin["internal"] = True
            rec.alive = self._put_locked(None, frames.BEGIN, call, ns, frames.as_json(begin))
            if internal and rec.alive:
                self._internal.append(rec)
        return rec

    def plan(self, name: str, dqs) -> None:
        """A planned path (dual quaternions ``(n, 8)``, world frame) on ``/plans/<name>``."""
        from dqpose.record import views

        ns = time.time_ns()
        data = views.poses_in_frame(ns, dqs).SerializeToString()
        with self._lock:
            self._put_locked(None, frames.PLAN, 0, ns, frames.named(name, data))

    def note(self, topic: str, title: str, data: dict) -> None:
        """One JSON object ``data`` on ``topic`` (its schema titled ``title``, its properties'
        types from the values): what a call knows beside its messages (an arm's limits)."""
        payload = frames.as_json({"topic": topic, "title": title, "data": data})
        with self._lock:
            self._put_locked(None, frames.NOTE, 0, time.time_ns(), payload)

    @property
    def failed(self) -> int:
        return self._failed[0] + self._failed[1]

    def watch(self, changed) -> None:
        """``changed()`` is called (from a thread of the recorder's) each time :attr:`failure`
        changes."""
        self._watchers.append(changed)

    def _set_failure(self, why: str | None) -> None:
        self.failure = why
        for changed in self._watchers:
            changed()

    def _put(self, rec, kind: int, call: int, payload: bytes) -> bool:
        with self._lock:
            return self._put_locked(rec, kind, call, time.time_ns(), payload)

    def _full(self) -> bool:
        return (self._pending >= self.capacity or len(self._buf) >= self.max_buffer
                or self._closed)

    def _put_locked(self, rec, kind: int, call: int, ns: int, payload: bytes) -> bool:
        if self._gone:
            self._failed[1] += 1
            return False
        if self._full() or (rec is not None and not rec.alive):
            if not self._gap:
                self._gap_ns = ns
            self._gap += 1
            self.dropped += 1
            return False
        if self._gap:
            self._append(frames.frame(frames.GAP, 0, ns, frames.as_json(
                {"first_dropped": self._gap_ns, "count": self._gap})))
            self._gap = 0
        self._append(frames.frame(kind, call, ns, payload))
        if len(self._buf) >= FLUSH_BYTES or time.monotonic() - self._flushed >= FLUSH_PERIOD:
            self._flush_locked()
        return True

    def _append(self, data: bytes, counted: bool = True) -> None:
        self._buf += data
        self._lengths.append(len(data) if counted else -len(data))
        self._pending += counted

    def _flush_locked(self) -> None:
        """Hands the pipe what it takes without waiting."""
        self._flushed = time.monotonic()
        if not self._buf or self.stall.is_set():
            return
        try:
            n = os.write(self._fd, self._buf)
        except BlockingIOError:
            return
        except (BrokenPipeError, ValueError, OSError):     # the writer is gone
            self._writer_gone()
            return
        del self._buf[:n]
        n += self._head
        lengths = self._lengths
        while lengths and n >= abs(lengths[0]):
            size = lengths.popleft()
            n -= abs(size)
            if size > 0:
                self.handed += 1
                self._pending -= 1
        self._head = n

    def _writer_gone(self) -> None:
        """The writer process ended before the recorder closed: what waits and what comes is
        lost (counted failed), said once."""
        if self._closed:
            return
        self._closed = self._gone = True
        self._failed[1] += self._pending
        log.error(json.dumps({"event": "recording_failed", "error": "the writer process ended"}))
        self._set_failure("the writer process ended")

    def _flush_periodically(self) -> None:
        """What came last before a pause (the servicers' own puts flush while messages come)."""
        while not self._closed:
            time.sleep(IDLE_FLUSH)
            if self._buf and time.monotonic() - self._flushed >= IDLE_FLUSH:
                with self._lock:
                    self._flush_locked()

    def _read_events(self) -> None:
        """The writer's JSON lines, logged here (and the files it opened, kept)."""
        assert self._proc.stdout is not None
        for line in self._proc.stdout:
            text = line.decode().strip()
            try:
                event = json.loads(text)
            except ValueError:
                log.warning(json.dumps({"event": "recording_output", "line": text}))
                continue
            kind = event.get("event")
            if kind == "recording_counts":
                self.written, self._failed[0] = event["written"], event["failed"]
            elif kind == "recording":
                self.files.append(event["file"])
                log.info(text)
            elif kind in ("recording_dropped", "live_refused"):
                log.warning(text)
            elif kind == "recording_failed":
                log.error(text)
                self._set_failure(event["error"])
            elif kind == "recording_resumed":
                log.warning(text)
                self._set_failure(None)
            elif kind == "live":
                self.live_port = event["port"]
                log.info(text)
                self._live_said.set()
            elif kind == "live_failed":
                self._live_error = event["error"]
                log.error(text)
                self._live_said.set()
            else:
                log.error(text)
        self._live_said.set()       # the writer ended
        with self._lock:
            self._writer_gone()

    def close(self, timeout: float = 30.0) -> None:
        """Ends the internal calls, hands over what is waiting (unless stalled), then waits for
        the writer to finish the file."""
        for rec in self._internal:
            rec.end("OK")
        with self._lock:
            self._internal.clear()
            if self._proc.stdin is None or self._proc.stdin.closed:
                return
            self.stall.clear()
            deadline = time.monotonic() + timeout
            while self._buf and not self._closed and time.monotonic() < deadline:
                self._flush_locked()
                if self._buf:
                    time.sleep(0.001)
            self._closed = True
            try:
                self._proc.stdin.close()
            except OSError:
                pass
        try:
            self._proc.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            log.warning(json.dumps({"event": "recording_unfinished", "timeout_s": timeout}))
            self._proc.kill()
            self._proc.wait()
        self._events.join(5)
