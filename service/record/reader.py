"""A recording read back in the order it was written (the calls' arrival order), every record's
CRC checked (``mcap``'s stream reader): each call's requests and answers as wire bytes, the calls'
begin and end, the markers where messages were dropped. What replay and the tests read; any
other MCAP reader sees the same file.
"""
from __future__ import annotations

import dataclasses
import json
import os

from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader

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


@dataclasses.dataclass
class Event:
    """One recorded message of a call: ``kind`` ``"request"`` or ``"answer"``, its wire bytes."""
    kind: str
    call: int
    ns: int
    data: bytes


@dataclasses.dataclass
class Dropped:
    first_dropped: int           # ns (Unix time) the first missing message arrived
    count: int
    at: int                      # the event index before which they are missing


@dataclasses.dataclass
class Recording:
    path: str
    calls: dict[int, Call]
    events: list[Event]
    dropped: list[Dropped]
    schemas: dict[str, bytes]    # message type -> its FileDescriptorSet, from the file itself
    plans: list[tuple[str, int, bytes]]   # (name, ns, foxglove.PosesInFrame bytes)

    def message_class(self, name: str):
        """The protobuf class of message type ``name`` built from the schema the file embeds
        alone (its own descriptor pool): no generated code needed."""
        return message_class(self.schemas[name], name)


def read(path: str | os.PathLike) -> Recording:
    """The recording at ``path``; ``ValueError`` naming it for a file that is not MCAP or fails
    its CRCs, and for one that ends before its footer (cut short: the process was killed)."""
    path = os.fspath(path)
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    calls: dict[int, Call] = {}
    events: list[Event] = []
    dropped: list[Dropped] = []
    plans: list[tuple[str, int, bytes]] = []
    try:
        with open(path, "rb") as f:
            for rec in StreamReader(f, validate_crcs=True).records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Message):
                    ch = channels[rec.channel_id]
                    if ch.topic == CALLS_TOPIC:
                        _call_event(calls, json.loads(rec.data), len(events))
                    elif ch.topic == DROPPED_TOPIC:
                        d = json.loads(rec.data)
                        dropped.append(Dropped(d["first_dropped"], d["count"], len(events)))
                    elif ch.topic.startswith(PLANS):
                        plans.append((ch.topic[len(PLANS):], rec.log_time, rec.data))
                    elif "call" in ch.metadata:
                        kind = ch.topic.rsplit("/", 1)[1][:-1]     # requests -> request
                        events.append(Event(kind, int(ch.metadata["call"]), rec.log_time,
                                            rec.data))
    except OSError:
        raise
    except Exception as e:   # mcap's own exceptions: EndOfFile, CRC and record errors
        raise ValueError(f"{path}: not a complete MCAP recording ({type(e).__name__}: "
                         f"{e})") from None
    by_name = {s.name: s.data for s in schemas.values() if s.encoding == "protobuf"}
    return Recording(path, calls, events, dropped, by_name, plans)


def _call_event(calls: dict[int, Call], d: dict, at: int) -> None:
    if d["event"] == "begin":
        calls[d["call"]] = Call(d["call"], d["rpc"], d["request_type"], d["answer_type"],
                                d.get("continued", False), world=d.get("world", ""))
    elif d["event"] == "end" and d["call"] in calls:
        calls[d["call"]].code = d["code"]
        calls[d["call"]].details = d.get("details", "")
        calls[d["call"]].end_at = at
