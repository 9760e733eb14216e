"""``World.ListFrames``: a world's frames (:meth:`dqpose.world.World.frames`) as a ``FrameList``
(the server's), and a ``FrameList`` as :class:`dqpose.frames.FrameInfo` s (the client's)."""
from __future__ import annotations

import weakref

from dqpose.frames import FrameInfo, FrameKind
from dqpose.rpc._proto.dqpose.v1 import world_pb2 as pb

# per world, each frame's bytes in a FrameList (tag, length, FrameInfo) by the FrameInfo they
# encode (the world hands out the same object while a frame's info holds): a call encodes only
# the frames that changed (1,000 frames: ~1 ms encoded, ~0.1 ms joined)
_encoded: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def list_frames(hub, request: pb.ListFramesRequest) -> bytes:
    """The ``FrameList`` of ``hub``'s world, serialized (beside the world's steps, under its
    read lock, as a Lookup)."""
    frames = hub.world.frames()
    kept = _encoded.get(hub)
    if kept is None or len(kept) > 2 * len(frames):      # the frames no longer listed go
        kept = _encoded[hub] = {}
    parts = []
    for f in frames:
        hit = kept.get(id(f))
        if hit is None or hit[0] is not f:
            hit = kept[id(f)] = (f, pb.FrameList(frames=[pb.FrameInfo(
                name=f.name, parent=f.parent, kind=f.kind.value, oldest=f.oldest,
                newest=f.newest, rate_hz=f.rate_hz, sources=f.sources)]).SerializeToString())
        parts.append(hit[1])
    return b"".join(parts)


def frames_of(msg: pb.FrameList) -> list[FrameInfo]:
    """A ``FrameList``'s frames (a kind this client does not know: UNSPECIFIED)."""
    kinds = {k.value: k for k in FrameKind}
    return [FrameInfo(f.name, f.parent, kinds.get(int(f.kind), FrameKind.UNSPECIFIED),
                      f.oldest, f.newest, f.rate_hz, tuple(f.sources)) for f in msg.frames]
