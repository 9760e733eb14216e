"""A recording read back in the order it was written (the calls' arrival order), every CRC and
declared size checked first (:mod:`dqpose.record.mcapread`): each call's requests and answers as
wire bytes, the calls' begin and end, the markers where messages were dropped. What replay,
export and the viewer read; any other MCAP reader sees the same file. A file that stops being
readable is a :class:`Damaged` naming it, the byte and why, once what precedes it was given out;
one that is not MCAP a :class:`~dqpose.record.mcapread.NotMcap`.

A server's recording is rotated into files ``dqpose-<server start>-<n>.mcap``; :func:`runs`
orders them into the runs they belong to and :func:`items` reads a run's files as one sequence
(a call that goes on in the next file is the same call there), streamed, so that a run larger
than memory replays whole (:mod:`dqpose.rpc.replay`); :func:`read_all` holds one in memory.
"""
from __future__ import annotations

import dataclasses
import glob
import json
import os
import re
from typing import Iterable, Iterator, Union

from google.protobuf.message import DecodeError

from dqpose.record.mcapread import Damaged, messages
from dqpose.record.schemas import message_class
from dqpose.record.topics import CALLS_TOPIC, DROPPED_TOPIC, plan_topic

PLANS = plan_topic("")


@dataclasses.dataclass
class Call:
    id: int
    rpc: str
    request_type: str
    answer_type: str
    continued: bool              # began in an earlier file: its start is not in this one
    code: str | None = None      # its status when it ended in this file, else None
    details: str = ""            # a refusal's text
    end_at: int | None = None    # the event index before which it ended
    world: str = ""              # a World call's named world (x-dqpose-world)
    begin_at: int = 0            # the event index before which it began
    internal: bool = False       # the server's own (the recorder's World subscription)


@dataclasses.dataclass
class End:
    """A call's end: its status ``code`` and a refusal's ``details``, where it was recorded."""
    call: int
    code: str
    details: str
    ns: int
    file: int = 0


@dataclasses.dataclass
class Event:
    """One recorded message of a call: ``kind`` ``"request"`` or ``"answer"``, its wire bytes."""
    kind: str
    call: int
    ns: int
    data: bytes
    file: int = 0                # the index of its file in the run (Recording.files)


@dataclasses.dataclass
class Dropped:
    first_dropped: int           # ns (Unix time) the first missing message arrived
    count: int
    at: int                      # the event index before which they are missing
    file: int = 0


#: what :func:`items` yields, in the order it was recorded
Item = Union[Call, End, Event, Dropped]


@dataclasses.dataclass
class Recording:
    path: str
    calls: dict[int, Call]
    events: list[Event]
    dropped: list[Dropped]
    schemas: dict[str, bytes]    # message type -> its FileDescriptorSet, from the file itself
    plans: list[tuple[str, int, bytes]]   # (name, ns, foxglove.PosesInFrame bytes)
    files: list[str] = dataclasses.field(default_factory=list)   # the run's files, in order
    ends: dict[int, End] = dataclasses.field(default_factory=dict)

    def message_class(self, name: str):
        """The protobuf class of message type ``name`` built from the schema the file embeds
        alone (its own descriptor pool): no generated code needed; :class:`Damaged` for a schema
        that does not build it."""
        try:
            return message_class(self.schemas[name], name)
        except Exception as e:      # protobuf's own: DecodeError, TypeError, KeyError
            raise Damaged(self.path, None, f"its schema of {name} does not build the message "
                                           f"({type(e).__name__}: {e})") from None

    def decode(self, cls, data: bytes, ns: int, file: int | None = None):
        """``data`` parsed by ``cls`` (a :meth:`message_class`); :class:`Damaged` naming the
        file and the message's arrival (``ns``) when it does not parse: a file whose CRCs hold
        was not necessarily written by dqpose."""
        try:
            return cls.FromString(data)
        except DecodeError:
            path = self.files[file] if file is not None and file < len(self.files) else self.path
            raise Damaged(path, None, f"its message of {ns} ns is not a "
                                      f"{cls.DESCRIPTOR.full_name}") from None

    def items(self) -> Iterator[Item]:
        """The recording in the order it was written (as :func:`items` reads it): before each
        event the calls that ended, the drop markers and the calls that began there."""
        begins: dict[int, list[Call]] = {}
        ends: dict[int, list[Call]] = {}
        for c in self.calls.values():
            begins.setdefault(c.begin_at, []).append(c)
            if c.end_at is not None:
                ends.setdefault(c.end_at, []).append(c)
        drops: dict[int, list[Dropped]] = {}
        for d in self.dropped:
            drops.setdefault(d.at, []).append(d)
        for i in range(len(self.events) + 1):
            for c in ends.get(i, ()):
                e = self.ends.get(c.id)
                yield End(c.id, c.code or "OK", c.details, e.ns if e else 0, e.file if e else 0)
            yield from drops.get(i, ())
            yield from begins.get(i, ())
            if i < len(self.events):
                yield self.events[i]


def read(path: str | os.PathLike) -> Recording:
    """The recording at ``path``; :class:`Damaged` (a ``ValueError``) naming it for a file that
    fails a check (a CRC, a declared size, a file cut short: its process was killed),
    :class:`~dqpose.record.mcapread.NotMcap` for one that is not MCAP."""
    return read_all([path])


def read_all(paths: Iterable[str | os.PathLike]) -> Recording:
    """One run's files (in order: :func:`runs`) read into memory as one recording."""
    files = [os.fspath(p) for p in paths]
    schemas: dict[str, bytes] = {}
    plans: list[tuple[str, int, bytes]] = []
    calls: dict[int, Call] = {}
    events: list[Event] = []
    dropped: list[Dropped] = []
    ends: dict[int, End] = {}
    for item in items(files, schemas, plans):
        if isinstance(item, Event):
            events.append(item)
        elif isinstance(item, Call):
            item.begin_at = len(events)
            calls[item.id] = item
        elif isinstance(item, End):
            if item.call in calls:
                c = calls[item.call]
                c.code, c.details, c.end_at = item.code, item.details, len(events)
                ends[item.call] = item
        else:
            item.at = len(events)
            dropped.append(item)
    return Recording(files[0] if files else "", calls, events, dropped, schemas, plans, files,
                     ends)


def items(files: list[str], schemas: dict[str, bytes] | None = None,
          plans: list | None = None) -> Iterator[Item]:
    """The items of one run's ``files`` (in order) as one sequence: a call's begin
    (:class:`Call`, ``continued`` when it began before the first file), its requests and
    answers (:class:`Event`), its :class:`End`, drop markers (:class:`Dropped`, ``at`` unset).
    ``schemas`` and ``plans`` (when given) are filled as the files are read."""
    open_calls: set[int] = set()
    for k, path in enumerate(files):
        stream = messages(path, schemas)
        for topic, metadata, ns, data in stream:
            try:
                item = _item(topic, metadata, ns, data, k, open_calls, plans)
            except (ValueError, KeyError, TypeError, RecursionError) as e:
                raise _explained(path, stream, f"its {topic} message of {ns} ns is not what "
                                 f"dqpose writes ({type(e).__name__}: {e})") from None
            if item is not None:
                yield item


def _explained(path: str, rest: Iterator, bad: str) -> Damaged:
    """A message that does not parse, named with the damage the rest of its file shows: a
    flipped bit can make an unchecked record parse as a message (a message index's opcode 7
    read as 5), and the CRC that finds it comes later, at the data section's end."""
    try:
        for _ in rest:
            pass
    except Damaged as d:
        return Damaged(path, d.offset, f"{d.reason}; before it, {bad}")
    return Damaged(path, None, bad)


def _item(topic: str, metadata: dict, ns: int, data: bytes, k: int, open_calls: set[int],
          plans: list | None) -> Item | None:
    """What one message of file ``k`` of a run is, None for one replay does not read."""
    if topic == CALLS_TOPIC:
        d = json.loads(data)
        call = int(d["call"])
        if d["event"] == "begin":
            if call in open_calls:      # goes on from the file before
                return None
            open_calls.add(call)
            return Call(call, str(d["rpc"]), str(d["request_type"]), str(d["answer_type"]),
                        bool(d.get("continued", False)), world=str(d.get("world", "")),
                        internal=bool(d.get("internal", False)))
        if d["event"] == "end" and call in open_calls:
            open_calls.discard(call)
            return End(call, str(d["code"]), str(d.get("details", "")), ns, k)
    elif topic == DROPPED_TOPIC:
        d = json.loads(data)
        return Dropped(int(d["first_dropped"]), int(d["count"]), -1, k)
    elif topic.startswith(PLANS):
        if plans is not None:
            plans.append((topic[len(PLANS):], ns, data))
    elif "call" in metadata and topic.endswith(("/requests", "/answers")):
        kind = topic.rsplit("/", 1)[1][:-1]     # requests -> request
        return Event(kind, int(metadata["call"]), ns, data, k)
    return None


#: a rotated file's name: the server's start (one for all its files) and the file's number
_ROTATED = re.compile(r"^(?P<run>.*)-(?P<n>\d{4,})\.mcap$")


def runs(args: Iterable[str | os.PathLike]) -> list[list[str]]:
    """The recordings named by ``args`` (files, directories of ``*.mcap`` files, glob
    patterns) as runs: a server's rotated files (``<run>-<n>.mcap``, the same ``<run>``,
    consecutive ``n``) in their order form one run; a run's file missing starts another from
    the next one; any other file is a run of its own. Runs in the order of their names.
    ``ValueError`` for an argument that names nothing."""
    paths: list[str] = []
    for arg in args:
        name = os.fspath(arg)
        if os.path.isdir(name):
            found = glob.glob(os.path.join(glob.escape(name), "*.mcap"))
        elif not os.path.exists(name) and any(c in name for c in "*?["):
            found = glob.glob(name)
        else:
            found = [name]
        if not found:
            raise ValueError(f"{name}: no .mcap file there")
        paths += found
    chains: dict[tuple[str, str], list[tuple[int, str]]] = {}
    alone: list[str] = []
    for p in dict.fromkeys(os.path.normpath(p) for p in paths):
        m = _ROTATED.match(os.path.basename(p))
        if m is None:
            alone.append(p)
        else:
            chains.setdefault((os.path.dirname(p), m["run"]), []).append((int(m["n"]), p))
    out: list[list[str]] = [[p] for p in alone]
    for files in chains.values():
        files.sort()
        run = [files[0][1]]
        for (a, _), (b, p) in zip(files, files[1:]):
            if b != a + 1:
                out.append(run)
                run = []
            run.append(p)
        out.append(run)
    return sorted(out, key=lambda run: run[0])
