"""Recorded calls fed again, to this process's servicers or to a server, and their answers
compared with the recorded ones byte for byte (:mod:`dqpose.record.reader` reads the file).

Each call gets its own requests in their recorded order; Fusion's calls are independent (a
StreamFuse stream's answers are a function of its own requests: they are paced on the
measurements' time), so they are replayed one after the other, each as fast as it answers
(``speed`` None) or at ``speed`` times the recorded pace. The World's calls depend on each other
(one world, one order of arrivals): they are replayed together first, in process, in the order
the recorded world applied them (:mod:`dqpose.rpc.replay_world`). A file whose recorder fell
behind is replayed up to the first messages it is missing ("not replayable after T"); a call that
began in an earlier file (the recording was rotated) is skipped, saying so.
"""
from __future__ import annotations

import dataclasses
import time
from typing import Callable, Optional

import grpc

from dqpose.record.reader import Call, Event, Recording
from dqpose.rpc import replay_world
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as pb
from dqpose.rpc.calls import refused
from dqpose.rpc.fusion import FUSE, STREAM_FUSE, Fusion

#: the calls a replay can feed (the World's in process only: :mod:`dqpose.rpc.replay_world`)
REPLAYABLE = (FUSE, STREAM_FUSE, *replay_world.CALLS)


@dataclasses.dataclass
class Outcome:
    """What one call answered: its answers' bytes and its status (``"OK"`` or a refusal's code
    with ``details``)."""
    answers: list[bytes]
    code: str = "OK"
    details: str = ""


@dataclasses.dataclass
class Difference:
    call: Call
    answer: int                  # the call's answer where they first differ (-1: the status)
    what: str

    def __str__(self) -> str:
        where = "its status" if self.answer < 0 else f"answer {self.answer}"
        return f"call {self.call.id} ({self.call.rpc}), {where}: {self.what}"


@dataclasses.dataclass
class Report:
    calls: int = 0
    requests: int = 0
    answers: int = 0
    skipped: list[str] = dataclasses.field(default_factory=list)
    cut: Optional[str] = None    # "not replayable after T: ..." when messages are missing
    difference: Optional[Difference] = None
    seconds: float = 0.0


def _recorded(rec: Recording) -> tuple[dict[int, list[Event]], Optional[str], int]:
    """Each call's events up to the first messages the file is missing, the reason it stops
    there, and how many events that leaves."""
    events = rec.events
    cut = None
    if rec.dropped:
        d = rec.dropped[0]
        events = events[:d.at]
        cut = (f"not replayable after {d.first_dropped / 1e9:.6f} (Unix time): {d.count} "
               f"messages dropped by the recorder there")
    by_call: dict[int, list[Event]] = {}
    for e in events:
        by_call.setdefault(e.call, []).append(e)
    return by_call, cut, len(events)


class InProcess:
    """The Fusion servicer of this process, with the server's default limits."""

    def __init__(self, servicer: Optional[Fusion] = None):
        self.fusion = servicer or Fusion()

    def run(self, rpc: str, requests, pace: Callable[[int], None]) -> Outcome:
        answers: list[bytes] = []
        if rpc == FUSE:
            (data,) = requests
            pace(0)
            try:
                answers.append(self.fusion.fuse_bytes(data))
            except Exception as e:
                status, details = refused("Fuse", e)
                return Outcome(answers, status.name, details)
            return Outcome(answers)
        state, next_id = None, 0
        for r, data in enumerate(requests):
            pace(r)
            if state is None:
                try:
                    state, got, n = self.fusion._open_stream(data)
                except Exception as e:
                    status, details = refused("StreamFuse", e)
                    return Outcome(answers, status.name, details)
            else:
                got, n = self.fusion.stream_answers_wire(state, data, r, next_id)
            answers += [a.SerializeToString() for a in got]
            next_id += n
        return Outcome(answers)


class Remote:
    """A server at ``channel`` (metadata: a bearer token's, when it needs one)."""

    def __init__(self, channel: grpc.Channel, metadata=None, timeout: float = 600.0):
        self.channel, self.metadata, self.timeout = channel, metadata, timeout

    def run(self, rpc: str, requests, pace: Callable[[int], None]) -> Outcome:
        answers: list[bytes] = []
        try:
            if rpc == FUSE:
                (data,) = requests
                pace(0)
                answers.append(self.channel.unary_unary(f"/{rpc}")(
                    data, timeout=self.timeout, metadata=self.metadata))
            else:
                def paced():
                    for r, data in enumerate(requests):
                        pace(r)
                        yield data
                stream: grpc.StreamStreamMultiCallable = self.channel.stream_stream(f"/{rpc}")
                for a in stream(paced(), timeout=self.timeout, metadata=self.metadata):
                    answers.append(a)
        except grpc.RpcError as e:
            return Outcome(answers, e.code().name, e.details() or "")
        return Outcome(answers)


def replay(rec: Recording, target, speed: Optional[float] = None) -> Report:
    """Feeds ``rec``'s calls to ``target`` (:class:`InProcess` or :class:`Remote`) and compares;
    the report holds the first difference (the replay stops there)."""
    by_call, cut, n = _recorded(rec)
    report = Report(cut=cut)
    t0 = time.perf_counter()
    world = None
    if isinstance(target, InProcess) and any(c.rpc in replay_world.CALLS
                                             for c in rec.calls.values()):
        world = replay_world.run(rec, rec.events[:n], Outcome)
    for call in rec.calls.values():
        if call.rpc not in REPLAYABLE:
            report.skipped.append(f"call {call.id} ({call.rpc}): not a call replay feeds")
            continue
        if call.continued:
            report.skipped.append(f"call {call.id} ({call.rpc}): began in an earlier file")
            continue
        events = by_call.get(call.id, [])
        requests = [e for e in events if e.kind == "request"]
        if not requests:
            continue
        recorded = Outcome([e.data for e in events if e.kind == "answer"],
                           call.code or "OK", call.details)
        complete = cut is None and call.code is not None
        if call.rpc in replay_world.CALLS:
            if world is None:
                report.skipped.append(f"call {call.id} ({call.rpc}): the World's calls are "
                                      f"replayed in process only")
                continue
            got = world[call.id]
            report.calls += 1
            report.requests += len(requests)
            report.answers += len(got.answers)
            # a subscription's recorded answers are those it sent before its client left
            report.difference = compare_outcomes(call, recorded, got, complete and call.rpc
                                                 != replay_world.SUBSCRIBE)
            if report.difference is not None:
                break
            continue
        start = time.perf_counter()

        def pace(r: int, requests=requests, start=start) -> None:
            if speed is not None:
                due = (requests[r].ns - requests[0].ns) / 1e9 / speed
                wait = start + due - time.perf_counter()
                if wait > 0:
                    time.sleep(wait)

        got = target.run(call.rpc, [e.data for e in requests], pace)
        report.calls += 1
        report.requests += len(requests)
        report.answers += len(got.answers)
        report.difference = compare_outcomes(call, recorded, got, complete)
        if report.difference is not None:
            break
    report.seconds = time.perf_counter() - t0
    return report


def compare_outcomes(call: Call, want: Outcome, got: Outcome,
                     complete: bool = True) -> Optional[Difference]:
    """The first difference between a call's recorded answers ``want`` and ``got``. When the
    recording of the call is not ``complete`` (cut by missing messages, or the call had not
    ended when the file did), answers beyond the recorded ones are not a difference."""
    for k, (a, b) in enumerate(zip(want.answers, got.answers)):
        if a != b:
            return Difference(call, k, _what(a, b, call.answer_type))
    if len(got.answers) < len(want.answers):
        return Difference(call, len(got.answers),
                          f"{len(want.answers)} answers recorded, {len(got.answers)} given")
    if complete and len(got.answers) > len(want.answers):
        return Difference(call, len(want.answers),
                          f"{len(want.answers)} answers recorded, {len(got.answers)} given")
    if complete and (want.code, want.details) != (got.code, got.details):
        return Difference(call, -1, f"recorded {want.code} {want.details!r}, "
                                    f"given {got.code} {got.details!r}")
    return None


def _what(a: bytes, b: bytes, answer_type: str = "dqpose.v1.FusedPose") -> str:
    """Where two answers differ: the first field (in field order) whose values differ, after
    the body and time of a recorded FusedPose; bytes when they do not parse."""
    from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb

    cls = {"dqpose.v1.FusedPose": pb.FusedPose, "dqpose.v1.PublishAck": wpb.PublishAck,
           "dqpose.v1.WorldConfig": wpb.WorldConfig}.get(answer_type)
    try:
        x, y = cls.FromString(a), cls.FromString(b)     # type: ignore[union-attr]
    except Exception:
        return "the bytes differ"
    head = f"body {x.body!r} at {x.time!r} s (request {x.request}): " \
        if cls is pb.FusedPose else ""
    return f"{head}{_first(x, y, '') or 'the bytes differ (the same values)'}"


def _first(x, y, prefix: str) -> str:
    """The first field of messages ``x`` and ``y`` (in field order, into sub-messages) whose
    values differ, ``""`` when none does."""
    for field in x.DESCRIPTOR.fields:
        u, v = getattr(x, field.name), getattr(y, field.name)
        name = prefix + field.name
        message = field.type == field.TYPE_MESSAGE
        if field.is_repeated:
            u, v = list(u), list(v)
            if u != v:
                k = next((i for i, (p, q) in enumerate(zip(u, v)) if p != q), min(len(u), len(v)))
                if message and k < min(len(u), len(v)):
                    return _first(u[k], v[k], f"{name}[{k}].")
                p = u[k] if k < len(u) else "(none)"
                q = v[k] if k < len(v) else "(none)"
                return f"{name}[{k}] recorded {_short(p)}, given {_short(q)}"
        elif message and u != v:
            return _first(u, v, name + ".")
        elif u != v:
            return f"{name} recorded {_short(u)}, given {_short(v)}"
    return ""


def _short(v) -> str:
    return repr(v) if isinstance(v, float) else " ".join(str(v).split())[:200]


def compare(a: Recording, b: Recording) -> Report:
    """Two recordings of the same requests (two versions of the code, two settings) call by
    call in the order they began: the first difference of their answers; calls whose requests
    differ are a difference too."""
    ca, cut_a, _ = _recorded(a)
    cb, cut_b, _ = _recorded(b)
    report = Report(cut=cut_a or cut_b)
    for x, y in zip(a.calls.values(), b.calls.values()):
        ex, ey = ca.get(x.id, []), cb.get(y.id, [])
        qx = [e.data for e in ex if e.kind == "request"]
        qy = [e.data for e in ey if e.kind == "request"]
        report.calls += 1
        report.requests += len(qx)
        report.answers += sum(e.kind == "answer" for e in ex)
        if x.rpc != y.rpc or qx != qy:
            report.difference = Difference(x, -1, f"not the same requests: {b.path} call "
                                                  f"{y.id} ({y.rpc}) was sent others")
            break
        complete = report.cut is None and x.code is not None and y.code is not None
        report.difference = compare_outcomes(
            x, Outcome([e.data for e in ex if e.kind == "answer"], x.code or "OK", x.details),
            Outcome([e.data for e in ey if e.kind == "answer"], y.code or "OK", y.details),
            complete)
        if report.difference is not None:
            break
    else:
        if len(a.calls) != len(b.calls):
            report.skipped.append(f"{len(a.calls)} calls in {a.path}, {len(b.calls)} in "
                                  f"{b.path}: compared the first {min(len(a.calls), len(b.calls))}")
    return report
