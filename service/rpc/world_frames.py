"""``World.ListFrames``: a world's frames (:meth:`dqpose.world.World.frames`) as a ``FrameList``
(the server's), and a ``FrameList`` as :class:`dqpose.frames.FrameInfo` s (the client's)."""
from __future__ import annotations

import weakref

import numpy as np

from dqpose import _dqcore
from dqpose.frames import FrameInfo, FrameKind
from dqpose.rpc._proto.dqpose.v1 import world_pb2 as pb

# The FrameList is written field by field (protobuf's wire format: one length-delimited
# FrameInfo per frame): in a live world every body's span changes between two calls, and a
# protobuf FrameInfo made and serialized per frame costs ~3.5 us (1,000 frames: 3.5 ms). Per
# world, the bytes that seldom change are kept: each frame's name, parent and kind, and each
# list of sources; the bodies' spans are written in C (_dqcore.frame_entries) at each call.
_kept: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


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


def _head(name: str, parent: str, kind: FrameKind) -> bytes:
    return _text(1, name) + _text(2, parent) + (bytes([3 << 3]) + _varint(kind.value)
                                                if kind.value else b"")


def _sources(sources: tuple[str, ...]) -> bytes:
    return b"".join(_text(7, s) for s in sources)


def list_frames(hub, request: pb.ListFramesRequest) -> bytes:
    """The ``FrameList`` of ``hub``'s world, serialized (beside the world's steps, under its
    read lock, as a Lookup)."""
    world, bodies, fixed = hub.world.frames(columns=True)
    n = 1 + len(bodies.names) + len(fixed)
    kept = _kept.get(hub)
    if kept is None or len(kept[0]) > 2 * n or len(kept[1]) > 4 * n:
        kept = _kept[hub] = ({}, {}, {})     # the frames no longer listed go
    heads: dict[tuple, bytes] = kept[0]
    lists: dict[tuple[str, ...], bytes] = kept[1]

    def head(name: str, parent: str, kind: FrameKind) -> bytes:
        key = (name, parent, kind)
        got = heads.get(key)
        if got is None:
            got = heads[key] = _head(name, parent, kind)
        return got

    def tail(sources: tuple[str, ...]) -> bytes:
        got = lists.get(sources)
        if got is None:
            got = lists[sources] = _sources(sources)
        return got

    def body_head(name: str, kind: FrameKind) -> bytes:
        got = bodies_kept.get(name)
        if got is None or got[0] is not kind:
            got = bodies_kept[name] = (kind, head(name, "", kind))
        return got[1]

    bodies_kept: dict[str, tuple[FrameKind, bytes]] = kept[2]
    return _dqcore.frame_entries(
        [head(world.name, world.parent, world.kind)]
        + list(map(body_head, bodies.names, bodies.kinds))
        + [head(f.name, f.parent, f.kind) for f in fixed],
        np.concatenate([np.zeros((1, 3)), bodies.spans, np.zeros((len(fixed), 3))]),
        [b""] + [tail(s) for s in bodies.sources] + [b""] * len(fixed))


def frames_of(msg: pb.FrameList) -> list[FrameInfo]:
    """A ``FrameList``'s frames (a kind this client does not know: UNSPECIFIED)."""
    kinds = {k.value: k for k in FrameKind}
    return [FrameInfo(f.name, f.parent, kinds.get(int(f.kind), FrameKind.UNSPECIFIED),
                      f.oldest, f.newest, f.rate_hz, tuple(f.sources)) for f in msg.frames]
