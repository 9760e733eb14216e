"""Recorded calls fed again, to this process's servicers or to a server, and their answers
compared with the recorded ones byte for byte, as the replay goes
(:mod:`dqpose.record.reader` reads the files).

A run (one file, or a server's rotated files read as one sequence: :func:`dqpose.record.reader.
runs`) is replayed in its recorded order, every call open at once as it was: each request is fed
to its call when the replay reaches it (as soon as the last was handed over, ``speed`` None, or at
``speed`` times the recorded pace), and each recorded answer is compared with the call's next
given one. A StreamFuse stream's answers are a function of its own requests (paced on the
measurements' time); the World's calls depend on each other (one world, one order of arrivals),
so each World step is fed only once the one before it is applied (in process: at once,
:mod:`dqpose.rpc.replay_world`; a server: :mod:`dqpose.rpc.replay_remote`). Nothing of a run is
held but its open calls and the answers not yet compared, so a recording larger than memory
replays whole. A run whose recorder fell behind is replayed up to the first messages it is
missing ("not replayable after T"), one with a file cut short (its server killed) or damaged (a
CRC or a declared size that fails its check: :mod:`dqpose.record.mcapread`) up to where it
stops being readable, naming the file, the byte and why; the runs after it are replayed. A call
that began before the run's first file is skipped, saying so. The first difference names its
call, answer and field, and the file and time the recorded answer is in.
"""
from __future__ import annotations

import collections
import dataclasses
import os
import time
from typing import Any, Iterable, Iterator, Optional, Protocol, Union

from dqpose.record import reader
from dqpose.record.reader import Call, Dropped, End, Event, Recording
from dqpose.record.types import FUSED_POSE
from dqpose.rpc import replay_world
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as pb
from dqpose.rpc.calls import refused
from dqpose.rpc.fusion import FUSE, STREAM_FUSE, Fusion
from dqpose.rpc.replay_remote import Remote

__all__ = ["REPLAYABLE", "InProcess", "Remote", "Outcome", "Difference", "Report", "replay",
           "compare", "compare_runs", "compare_outcomes"]

#: the calls a replay can feed
REPLAYABLE = (FUSE, STREAM_FUSE, *replay_world.CALLS)
#: how long a finished call's answers are waited for (a server's)
FINISH_SECONDS = 60.0


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
    file: str = ""               # the file the recorded answer (or the call's end) is in
    ns: int = 0                  # and its time (Unix, ns)

    def __str__(self) -> str:
        where = "its status" if self.answer < 0 else f"answer {self.answer}"
        at = (f" (recorded in {os.path.basename(self.file)} at {self.ns / 1e9:.6f} s, Unix "
              f"time)" if self.file else "")
        return f"call {self.call.id} ({self.call.rpc}), {where}: {self.what}{at}"


@dataclasses.dataclass
class Report:
    calls: int = 0
    requests: int = 0
    answers: int = 0
    skipped: list[str] = dataclasses.field(default_factory=list)
    #: "not replayable after T: ...", one for each run not replayed to its end (messages
    #: dropped, a file cut short or damaged): its answers up to there were compared
    cuts: list[str] = dataclasses.field(default_factory=list)
    difference: Optional[Difference] = None
    seconds: float = 0.0
    files: int = 0               # files replayed (a run of rotated files counts each)
    runs: int = 0

    @property
    def cut(self) -> Optional[str]:
        """The first of :attr:`cuts`, None when every run was replayed whole."""
        return self.cuts[0] if self.cuts else None


class Player(Protocol):
    """One call being replayed: :meth:`send` feeds a request; ``given`` holds the answers made
    and not yet compared (filled as they come: by :meth:`send` in process, by a thread of its
    own from a server); :meth:`end` says the recorded call ended there (``recorded``: its
    answers recorded); :meth:`result` its status once it has finished, None for the recorded
    one (a World stream's end is its client's doing); :meth:`cancel` stops it."""
    given: collections.deque

    def send(self, data: bytes) -> None: ...

    def end(self, recorded: int) -> None: ...

    def result(self) -> Optional[tuple[str, str]]: ...

    def cancel(self) -> None: ...


class _Player:
    def __init__(self, fusion: Fusion):
        self.fusion = fusion
        self.given: collections.deque = collections.deque()
        self.status = ("OK", "")

    def end(self, recorded: int) -> None:
        pass

    def result(self) -> Optional[tuple[str, str]]:
        return self.status

    def cancel(self) -> None:
        pass


class _Fuse(_Player):
    def send(self, data: bytes) -> None:
        try:
            self.given.append(self.fusion.fuse_bytes(data))
        except Exception as e:
            status, details = refused("Fuse", e)
            self.status = (status.name, details)


class _StreamFuse(_Player):
    state = None
    r = next_id = 0

    def send(self, data: bytes) -> None:
        if self.status[0] != "OK":
            return
        r = self.r
        self.r += 1
        if self.state is None:
            try:
                self.state, got, n = self.fusion.start_stream(data)
            except Exception as e:
                status, details = refused("StreamFuse", e)
                self.status = (status.name, details)
                return
        else:
            got, n = self.fusion.stream_answers_wire(self.state, data, r, self.next_id)
        self.given.extend(got)
        self.next_id += n


class InProcess:
    """The servicers of this process, with the server's default limits: the Fusion servicer
    (or ``servicer``) and, for each run, a new World servicer."""

    def __init__(self, servicer: Optional[Fusion] = None):
        self.fusion = servicer or Fusion()
        self.worlds = replay_world.Worlds()

    def begin(self) -> None:
        self.worlds = replay_world.Worlds()

    def open(self, call: Call) -> Player:
        if call.rpc == FUSE:
            return _Fuse(self.fusion)
        if call.rpc == STREAM_FUSE:
            return _StreamFuse(self.fusion)
        return self.worlds.open(call)       # type: ignore[return-value]


class _Answers:
    def __init__(self, answers: Iterable[bytes] = ()):
        self.given = collections.deque(answers)


class _Tally:
    """One call's recorded answers against the given ones (``player.given``), compared as both
    come."""

    def __init__(self, call: Call, player):
        self.call, self.player = call, player
        self.want: collections.deque = collections.deque()   # (bytes, file, ns)
        self.k = 0                   # answers compared
        self.requests = 0

    def check(self) -> Optional[Difference]:
        given, want = self.player.given, self.want
        while want and given:
            data, file, ns = want.popleft()
            got = given.popleft()
            if data != got:
                return Difference(self.call, self.k, _what(data, got, self.call.answer_type),
                                  file, ns)
            self.k += 1
        return None

    def finish(self, want: tuple[str, str], got: Optional[tuple[str, str]], complete: bool,
               where: tuple[str, int]) -> Optional[Difference]:
        """The last comparison once the call has finished: its answers left, their counts and
        (when its recording is ``complete``) its status ``want`` against ``got``."""
        d = self.check()
        if d is not None:
            return d
        recorded, given = self.k + len(self.want), self.k + len(self.player.given)
        if given < recorded or complete and given > recorded:
            file, ns = self.want[0][1:] if self.want else where
            return Difference(self.call, min(given, recorded),
                              f"{recorded} answers recorded, {given} given", file, ns)
        got = want if got is None else got
        if complete and want != got:
            return Difference(self.call, -1, f"recorded {want[0]} {want[1]!r}, given {got[0]} "
                                             f"{got[1]!r}", *where)
        return None


class _Run:
    """One run replayed into ``target`` (:class:`InProcess`, or
    :class:`~dqpose.rpc.replay_remote.Remote`), counted into ``report``."""

    def __init__(self, target, speed: Optional[float], report: Report, files: list[str]):
        self.target, self.speed, self.report, self.files = target, speed, report, files
        self.open: dict[int, tuple[Call, _Tally]] = {}
        self.first_ns: Optional[int] = None
        self.start = time.perf_counter()
        self.where: tuple[str, int] = (files[0] if files else "", 0)

    def file(self, k: int) -> str:
        return self.files[k] if k < len(self.files) else ""

    def pace(self, ns: int) -> None:
        if self.first_ns is None:
            self.first_ns = ns
        if self.speed is not None:
            wait = self.start + (ns - self.first_ns) / 1e9 / self.speed - time.perf_counter()
            if wait > 0:
                time.sleep(wait)

    def play(self, items: Iterable[reader.Item]) -> None:
        report = self.report
        self.target.begin()
        it = iter(items)
        try:
            while True:
                try:
                    item = next(it)
                except StopIteration:
                    break
                except reader.Damaged as e:
                    # a file cut short (its server killed) or damaged: what was read replays
                    ns = self.where[1]
                    at = f"after {ns / 1e9:.6f} (Unix time)" if ns else "at all"
                    report.cuts.append(f"not replayable {at}: {e}")
                    break
                if isinstance(item, Event):
                    self.where = (self.file(item.file), item.ns)
                    opened = self.open.get(item.call)
                    if opened is None:
                        continue
                    call, tally = opened
                    if item.kind == "request":
                        self.pace(item.ns)
                        tally.requests += 1
                        tally.player.send(item.data)
                    else:
                        tally.want.append((item.data, self.file(item.file), item.ns))
                    report.difference = tally.check()
                elif isinstance(item, Call):
                    self.begin(item)
                elif isinstance(item, End):
                    self.where = (self.file(item.file), item.ns)
                    opened = self.open.pop(item.call, None)
                    if opened is not None:
                        self.finish(*opened, (item.code, item.details), True)
                elif isinstance(item, Dropped):
                    report.cuts.append(
                        f"not replayable after {item.first_dropped / 1e9:.6f} (Unix time): "
                        f"{item.count} messages dropped by the recorder there "
                        f"({os.path.basename(self.file(item.file))})")
                    break
                if report.difference is not None:
                    break
            for call, tally in list(self.open.values()):    # still open where the run stops
                if report.difference is not None:
                    tally.player.cancel()
                else:
                    self.finish(call, tally, (call.code or "OK", call.details), False)
        finally:
            for _, tally in self.open.values():
                tally.player.cancel()

    def begin(self, call: Call) -> None:
        if call.rpc not in REPLAYABLE:
            self.report.skipped.append(f"call {call.id} ({call.rpc}): not a call replay feeds")
        elif call.continued:
            self.report.skipped.append(
                f"call {call.id} ({call.rpc}): began before "
                f"{os.path.basename(self.files[0]) if self.files else 'the file'}, the first "
                f"file of its run")
        else:
            self.open[call.id] = (call, _Tally(call, self.target.open(call)))

    def finish(self, call: Call, tally: _Tally, want: tuple[str, str], ended: bool) -> None:
        """The call ended in the recording (``ended``), or the run stops with it open."""
        self.open.pop(call.id, None)
        if not tally.requests:
            tally.player.cancel()
            return
        tally.player.end(tally.k + len(tally.want))
        got = tally.player.result()
        # a subscription's recorded answers are those it sent before its client left
        complete = ended and call.rpc != replay_world.SUBSCRIBE
        report = self.report
        report.calls += 1
        report.requests += tally.requests
        report.answers += tally.k + len(tally.player.given)
        report.difference = report.difference or tally.finish(want, got, complete, self.where)


Source = Union[Recording, Iterable[Iterable[Union[str, os.PathLike]]]]


def replay(source: Source, target, speed: Optional[float] = None) -> Report:
    """Feeds ``source`` (a :class:`Recording` in memory, or runs of files, e.g.
    :func:`dqpose.record.reader.runs`: each run's files read as one sequence as it is
    replayed) to ``target`` (:class:`InProcess` or :class:`~dqpose.rpc.replay_remote.Remote`)
    and compares; the report holds the first difference (the replay stops there) and where each
    run that could not be replayed whole stops (``cuts``: the replay goes on with the next run).
    A file that is not MCAP is a ``ValueError`` naming it, when the replay reaches it."""
    report = Report()
    t0 = time.perf_counter()
    for files, items in _runs(source):
        report.runs += 1
        report.files += len(files)
        _Run(target, speed, report, files).play(items)
        if report.difference is not None:
            break
    report.seconds = time.perf_counter() - t0
    return report


def _runs(source: Source) -> Iterator[tuple[list[str], Iterable[reader.Item]]]:
    if isinstance(source, Recording):
        yield source.files or [source.path], source.items()
        return
    for run in source:
        files = [os.fspath(f) for f in run]
        yield files, reader.items(files)


def compare_outcomes(call: Call, want: Outcome, got: Outcome,
                     complete: bool = True) -> Optional[Difference]:
    """The first difference between a call's recorded answers ``want`` and ``got``. When the
    recording of the call is not ``complete`` (cut by missing messages, or the call had not
    ended when the file did), answers beyond the recorded ones are not a difference."""
    tally = _Tally(call, _Answers(got.answers))
    tally.want.extend((a, "", 0) for a in want.answers)
    return tally.finish((want.code, want.details), (got.code, got.details), complete, ("", 0))


def _what(a: bytes, b: bytes, answer_type: str = FUSED_POSE) -> str:
    """Where two answers differ: the first field (in field order) whose values differ, after
    the body and time of a recorded FusedPose; bytes when they do not parse."""
    from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb

    classes: dict[str, Any] = {c.DESCRIPTOR.full_name: c
                               for c in (pb.FusedPose, wpb.PublishAck, wpb.WorldConfig)}
    cls = classes.get(answer_type)
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


def _recorded(rec: Recording) -> tuple[dict[int, list[Event]], Optional[str]]:
    """Each call's events up to the first messages the recording is missing, and the reason it
    stops there."""
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
    return by_call, cut


def compare(a: Recording, b: Recording) -> Report:
    """Two recordings of the same requests (two versions of the code, two settings) call by
    call in the order they began: the first difference of their answers; calls whose requests
    differ are a difference too."""
    ca, cut_a = _recorded(a)
    cb, cut_b = _recorded(b)
    report = Report(cuts=[c for c in (cut_a, cut_b) if c])
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
        complete = not report.cuts and x.code is not None and y.code is not None
        answers = [e for e in ex if e.kind == "answer"]
        d = compare_outcomes(
            x, Outcome([e.data for e in answers], x.code or "OK", x.details),
            Outcome([e.data for e in ey if e.kind == "answer"], y.code or "OK", y.details),
            complete)
        if d is not None:
            at = answers[d.answer] if 0 <= d.answer < len(answers) else ex[-1] if ex else None
            if at is not None:
                d.file, d.ns = a.files[at.file] if a.files else a.path, at.ns
            report.difference = d
            break
    else:
        if len(a.calls) != len(b.calls):
            report.skipped.append(f"{len(a.calls)} calls in {a.path}, {len(b.calls)} in "
                                  f"{b.path}: compared the first {min(len(a.calls), len(b.calls))}")
    return report


def compare_runs(a: list[list[str]], b: list[list[str]]) -> Report:
    """:func:`compare` of two lists of runs (:func:`dqpose.record.reader.runs`), run by run,
    each run's files read into memory as one recording."""
    report = Report()
    for x, y in zip(a, b):
        one = compare(reader.read_all(x), reader.read_all(y))
        report.runs += 1
        report.files += len(x)
        report.calls += one.calls
        report.requests += one.requests
        report.answers += one.answers
        report.skipped += one.skipped
        report.cuts += one.cuts
        report.difference = one.difference
        if one.cuts or one.difference:
            return report
    if len(a) != len(b):
        report.skipped.append(f"{len(a)} runs against {len(b)}: compared the first "
                              f"{min(len(a), len(b))}")
    return report
