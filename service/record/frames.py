"""What the server's recorder sends its writer process (:mod:`dqpose.record.writer`) through a
pipe: frames of ``kind`` (one byte), ``call`` (u64), ``ns`` (u64, arrival, Unix time), the
payload's length (u32), the payload. A stream of them: a partial write of the pipe loses
nothing, the next write goes on where it stopped.
"""
from __future__ import annotations

import json
import struct

HEADER = struct.Struct("<BQQI")

SCHEMA = 1      # payload: name, NUL, the FileDescriptorSet
BEGIN = 2       # JSON {rpc, request_type, answer_type[, world]}
REQUEST = 3     # the request's wire bytes
ANSWER = 4      # the answer's wire bytes
END = 5         # JSON {code, details}
GAP = 6         # JSON {first_dropped, count}
PLAN = 7        # payload: name, NUL, foxglove.PosesInFrame bytes
NOTE = 8        # JSON {topic, title, data}: one object on a JSON channel of its own


def frame(kind: int, call: int, ns: int, payload: bytes) -> bytes:
    return HEADER.pack(kind, call, ns, len(payload)) + payload


def named(name: str, data: bytes) -> bytes:
    return name.encode() + b"\0" + data


def unnamed(payload: bytes) -> tuple[str, bytes]:
    name, _, data = payload.partition(b"\0")
    return name.decode(), data


def as_json(obj: dict) -> bytes:
    return json.dumps(obj, separators=(",", ":")).encode()


def read_frames(buffer: bytearray):
    """Yields the whole frames at the start of ``buffer`` as ``(kind, call, ns, payload)`` and
    removes them from it (what is left is the start of the next)."""
    at = 0
    n = len(buffer)
    while n - at >= HEADER.size:
        kind, call, ns, size = HEADER.unpack_from(buffer, at)
        end = at + HEADER.size + size
        if end > n:
            break
        yield kind, call, ns, bytes(buffer[at + HEADER.size:end])
        at = end
    del buffer[:at]
