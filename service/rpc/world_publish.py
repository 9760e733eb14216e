"""A Publish request read and applied: its bytes decoded (in C where they are plain), handed to
its world's hub as one step (:meth:`dqpose.Hub.publish`), recorded in the world's order (the
hub runs the recording's hook under its lock) and its ack made. Never raises for bad input: what
a request cannot use is an error entry of its ack. Run in the worker pool (:mod:`dqpose.rpc.world`)
and by a replay (:mod:`dqpose.rpc.replay_world`)."""
from __future__ import annotations

from google.protobuf.message import DecodeError

from dqpose import record
from dqpose.hub import Hub, Rows
from dqpose.rpc._proto.dqpose.v1 import world_pb2 as pb
from dqpose.rpc.calls import readable
from dqpose.rpc.checks import over_count
from dqpose.rpc.fusion_convert import measurements_to_arrays
from dqpose.rpc.wire import publish_from_wire, publish_head, wire_rows


def publish_bytes(world: Hub, data: bytes, r: int, anonymous: str, max_poses: int,
                  rec=record.NULL_CALL) -> pb.PublishAck:
    """Request ``r``'s bytes (``anonymous``: the producer key of a request that names none)
    as one step of the world, recorded with its ack; bytes that are not a PublishRequest
    are an ack error, and so is a request of more than ``max_poses`` measurements. Its
    producer, sequence and count are read in C where the bytes are plain (``publish_head``),
    else by protobuf."""
    head = publish_head(data)
    try:
        if head is not None and head[2] <= max_poses:
            ack = _publish(world, None, *head, r, anonymous, data, max_poses, rec)
        else:
            request = pb.PublishRequest.FromString(data)
            ack = publish(world, request, r, anonymous, max_poses, data, rec)
    except DecodeError:     # raised before the world was touched
        world.count(hook=lambda: rec.request(data))
        ack = pb.PublishAck()
        ack.errors.add(request=r, measurement=-1, details=(
            f"requests[{r}]: not a valid dqpose.v1.PublishRequest message; none of it was "
            f"used"))
    rec.answer(ack)
    return ack


def publish_all(world: Hub, data: list, r: int, anonymous: str, max_poses: int,
                rec) -> tuple[list, Exception | None]:
    """:func:`publish_bytes` of requests ``r``, ``r + 1``, ... in turn (one pool job): their
    acks, and what the one that failed raised (the acks before it are still sent)."""
    acks: list = []
    try:
        for d in data:
            acks.append(publish_bytes(world, d, r + len(acks), anonymous, max_poses, rec))
    except Exception as e:
        return acks, e
    return acks, None


def publish(world: Hub, request: pb.PublishRequest, r: int, anonymous: str, max_poses: int,
            data: bytes | None = None, rec=record.NULL_CALL) -> pb.PublishAck:
    """Request ``r`` of a Publish call applied (:meth:`dqpose.Hub.publish`), its ack
    returned; never raises for bad input. ``data``: the request's bytes, whose measurements
    are then read in C."""
    return _publish(world, request, request.producer, request.sequence,
                    len(request.measurements), r, anonymous, data, max_poses, rec)


def _publish(world: Hub, request: pb.PublishRequest | None, producer: str, sequence: int,
             count: int, r: int, anonymous: str, data: bytes | None, max_poses: int,
             rec) -> pb.PublishAck:
    """A request read as its ``producer``, ``sequence`` and ``count`` of measurements, from
    ``request`` or (None) its bytes ``data``, applied; ``DecodeError`` from bytes protobuf
    would not read, before anything is done."""
    field = f"requests[{r}].measurements"
    too_many = over_count(field, count, max_poses, "measurements")
    errors: list = []
    rows = None if too_many is not None else _rows(request, data, field, errors)
    applied = world.publish(producer, anonymous, sequence, rows, count,
                            hook=lambda: rec.request(data or request))
    ack = pb.PublishAck(acked_through=applied.acked_through)

    def error(i: int, text: str) -> None:
        ack.errors.add(request=r, measurement=i, details=readable(text))

    for e in applied.notes:
        error(-1, e.named(f"requests[{r}]"))
    if applied.used:
        if too_many is not None:
            error(-1, f"{too_many}; none was used")
        for i, e in errors:
            error(i, str(e))
        for e in applied.errors:
            error(e.index, e.named(field))
    return ack


def _rows(request: pb.PublishRequest | None, data: bytes | None, field: str,
          errors: list) -> Rows:
    """A request's measurements as the world takes them, those refused by their encoding
    appended to ``errors`` as ``(i, FieldError)``. From ``data`` (its bytes) they are decoded and
    checked in C where they are plain (the same rows and texts; the rows C passed are not
    checked again); else from ``request`` (None: parsed from ``data`` here, which may raise
    ``DecodeError``)."""
    w = None if data is None else publish_from_wire(data)
    codes = None
    if data is None or w is None:
        if request is None:
            assert data is not None         # one of the two is given
            request = pb.PublishRequest.FromString(data)
        m = measurements_to_arrays(request.measurements, field, errors)
    else:
        m, more, codes = wire_rows(data, w, field)
        errors += more
    return Rows(m.index, m.bodies, m.sources, m.times, m.poses, m.covariances, codes)
