"""``World.ListFrames``: a world's frames (:meth:`dqpose.world.World.frames`) as a ``FrameList``
(the server's), and a ``FrameList`` as :class:`dqpose.frames.FrameInfo` s (the client's)."""
from __future__ import annotations

import struct
import weakref

from dqpose.frames import FrameInfo, FrameKind
from dqpose.rpc._proto.dqpose.v1 import world_pb2 as pb

# The FrameList is written field by field (protobuf's wire format: one length-delimited
# FrameInfo per frame): in a live world every body's span changes between two calls, and a
# protobuf FrameInfo made and serialized per frame costs ~3.5 us (1,000 frames: 3.5 ms). Per
# world, the bytes that seldom change are kept: a frame's name, parent and kind, and a list of
# sources; the span and rate are packed at each call.
_kept: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_SPAN = struct.Struct("<BdBdBd")        # FrameInfo fields 4, 5, 6: doubles (wire type 1)


def _varint(n: int) -> bytes:
    out = bytearray()
    while n > 0x7F:
        out.append(n & 0x7F | 0x80)
        n >>= 7
    out.append(n)
    return bytes(out)


def _text(field: int, s: str) -> bytes:
    data = s.encode()
    return bytes([field << 3 | 2]) + _varint(len(data)) + data if data else b""


def _head(f: FrameInfo) -> bytes:
    kind = f.kind.value
    return _text(1, f.name) + _text(2, f.parent) + (bytes([3 << 3]) + _varint(kind) if kind
                                                     else b"")


def _sources(sources: tuple[str, ...]) -> bytes:
    return b"".join(_text(7, s) for s in sources)


def list_frames(hub, request: pb.ListFramesRequest) -> bytes:
    """The ``FrameList`` of ``hub``'s world, serialized (beside the world's steps, under its
    read lock, as a Lookup)."""
    frames = hub.world.frames()
    kept = _kept.get(hub)
    if kept is None or len(kept[0]) > 2 * len(frames) or len(kept[2]) > 4 * len(frames):
        kept = _kept[hub] = ({}, {}, {})     # the frames no longer listed go
    done: dict[str, tuple[FrameInfo, bytes]] = kept[0]
    heads: dict[tuple, bytes] = kept[1]
    lists: dict[tuple[str, ...], bytes] = kept[2]
    parts = []
    for f in frames:
        hit = done.get(f.name)
        if hit is None or hit[0] is not f:      # the world hands out the same info unchanged
            hit = done[f.name] = (f, _entry(f, heads, lists))
        parts.append(hit[1])
    return b"".join(parts)


def _entry(f: FrameInfo, heads: dict, lists: dict) -> bytes:
    """``f``'s entry in a FrameList, from the kept bytes of its head and its list of sources."""
    key = (f.name, f.parent, f.kind)
    head = heads.get(key)
    if head is None:
        head = heads[key] = _head(f)
    tail = lists.get(f.sources)
    if tail is None:
        tail = lists[f.sources] = _sources(f.sources)
    body = (head + _SPAN.pack(0x21, f.oldest, 0x29, f.newest, 0x31, f.rate_hz) + tail
            if f.oldest or f.newest or f.rate_hz else head + tail)
    return b"\x0a" + _varint(len(body)) + body


def frames_of(msg: pb.FrameList) -> list[FrameInfo]:
    """A ``FrameList``'s frames (a kind this client does not know: UNSPECIFIED)."""
    kinds = {k.value: k for k in FrameKind}
    return [FrameInfo(f.name, f.parent, kinds.get(int(f.kind), FrameKind.UNSPECIFIED),
                      f.oldest, f.newest, f.rate_hz, tuple(f.sources)) for f in msg.frames]
