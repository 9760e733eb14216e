"""An MCAP file read record by record, nothing in it trusted before it is checked: what every
reader of a recording (replay, export, the viewer) reads through (:mod:`dqpose.record.reader`).

``mcap``'s stream reader checks the chunk and data-section CRCs, but it believes every declared
size: a record's length is allowed up to 4 GiB whatever the file holds (Python allocates what a
read asks for), a zstd chunk is decompressed to the size its frame declares (``zstandard``
ignores the limit it is given when the frame states a content size: a 277 kB file declaring
1 GiB of zeros kept ``replay`` busy for minutes), lz4 without any bound, a short read inside a
record is taken as the record, attachments' CRCs and the summary's are not checked. Here:

- a record is read whole only once its length is known to fit in what is left of the file and
  in :data:`MAX_RECORD_BYTES`; every field's declared size is checked against its record;
- a chunk declaring more than :data:`MAX_RECORD_BYTES` uncompressed is refused before anything
  is decompressed, and decompression stops one byte past the declared size;
- every CRC: each chunk's (its records are given out only after it held), each attachment's,
  the data section's at its ``DataEnd``, the summary's at the footer;
- the summary's sanity: it starts where the data ends, its statistics count the messages,
  chunks, attachments and metadata read (per channel too), its schemas and channels are the
  ones the data defined; the footer and the closing magic end the file.

- a compressed chunk declaring more than :data:`MAX_RATIO` times its compressed size (beyond
  1 MiB) is refused too, so a file of many small chunks cannot ask for gigabytes either.

Time and memory a file can cost are thus bounded by its size (times the ratio) and the 64 MiB
limit, whatever it holds. Anything wrong is a :class:`Damaged` naming the file, the byte and
what is wrong; messages before it were given out (a replay replays them), none after it.
"""
from __future__ import annotations

import io
import os
import struct
import zlib
from typing import Iterator, NamedTuple

import lz4.frame
import zstandard
from mcap.opcode import Opcode

MAGIC = b"\x89MCAP0\r\n"
#: the most bytes a record may declare (it is read whole to be checked) and a chunk may declare
#: it holds uncompressed; dqpose writes 16 kB chunks, and a gRPC message is 4 MiB at most
MAX_RECORD_BYTES = 64 << 20
#: the most a compressed chunk may declare per byte it holds (beyond its first MiB): dqpose's
#: 16 kB chunks of poses compress 2-10x, while zeros compress ~30,000x, so without it a file of
#: many chunks each declaring 64 MiB costs decompression work thousands of times its size
MAX_RATIO = 1024

_U16, _U32, _U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")
_HEAD = struct.Struct("<BQ")            # a record's opcode and length
_MESSAGE = struct.Struct("<HIQ")        # a message's channel, sequence, log time
_MESSAGE_FIXED = 22                     # ... and publish time: the bytes before its data
_IN_CHUNK = {Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE}
_SUMMARY_ONLY = {Opcode.STATISTICS, Opcode.CHUNK_INDEX, Opcode.ATTACHMENT_INDEX,
                 Opcode.METADATA_INDEX, Opcode.SUMMARY_OFFSET}
_SUMMARY = {Opcode.SCHEMA, Opcode.CHANNEL, *_SUMMARY_ONLY}


class Damaged(ValueError):
    """``path`` cannot be read past byte ``offset`` (None: where is not known): ``reason``."""

    def __init__(self, path: str, offset: int | None, reason: str):
        self.path, self.offset, self.reason = path, offset, reason
        at = "" if offset is None else f"byte {offset}: "
        super().__init__(f"{path}: not a complete MCAP recording: {at}{reason}")


class NotMcap(ValueError):
    """A file that is not MCAP at all (it does not begin with MCAP's magic)."""


class Channel(NamedTuple):
    topic: str
    encoding: str
    schema: int
    metadata: dict


_NAMES = {int(op): op.name.lower().replace("_", " ") + " record" for op in Opcode}


def _name(op: int) -> str:
    return _NAMES.get(op) or f"record of opcode 0x{op:02x}"


class _Fields:
    """A record's body read field by field, each field's size checked against what is left."""

    def __init__(self, data, start: int, end: int, what: str):
        self.data, self.i, self.end, self.what = data, start, end, what

    def _take(self, n: int, field: str):
        i = self.i
        if n > self.end - i:
            raise ValueError(f"its {field} declares {n} bytes where {self.end - i} are left "
                             f"in the {self.what}")
        self.i = i + n
        return i

    def u16(self, field: str) -> int:
        return _U16.unpack_from(self.data, self._take(2, field))[0]

    def u32(self, field: str) -> int:
        return _U32.unpack_from(self.data, self._take(4, field))[0]

    def u64(self, field: str) -> int:
        return _U64.unpack_from(self.data, self._take(8, field))[0]

    def blob(self, n: int, field: str) -> bytes:
        i = self._take(n, field)
        return bytes(self.data[i:i + n])

    def text(self, field: str) -> str:
        raw = self.blob(self.u32(field), field)
        try:
            return raw.decode()
        except UnicodeDecodeError:
            raise ValueError(f"its {field} is not UTF-8") from None

    def pairs(self, field: str, key, value) -> list:
        """A map: its byte length, then keys and values read by ``key`` and ``value``."""
        n = self.u32(field)
        self._take(n, field)
        inner = _Fields(self.data, self.i - n, self.i, f"{field} of the {self.what}")
        out = []
        while inner.i < inner.end:
            out.append((key(inner), value(inner)))
        return out


class _Reader:
    def __init__(self, f, path: str, schemas: dict[str, bytes] | None):
        self.f, self.path, self.protobuf = f, path, schemas
        self.size = os.fstat(f.fileno()).st_size
        self.pos = 0
        self.crc = 0                       # of every byte read so far (the data section's CRC)
        self.schemas: dict[int, tuple] = {}
        self.channels: dict[int, Channel] = {}
        self.counts: dict[int, int] = {}   # messages per channel
        self.chunks = self.attachments = self.metadata = 0
        self.stats: tuple | None = None
        self._zstd = zstandard.ZstdDecompressor()

    def damaged(self, at: int | None, reason: str) -> Damaged:
        return Damaged(self.path, at, reason)

    def read(self, n: int) -> bytes:
        data = self.f.read(n)
        if len(data) != n:      # the size was checked against the file's: it shrank meanwhile
            raise self.damaged(self.pos + len(data), "the file ends there (it was cut while "
                                                     "being read)")
        self.pos += n
        self.crc = zlib.crc32(data, self.crc)
        return data

    def records(self) -> Iterator[tuple]:
        head = self.f.read(len(MAGIC))
        if head != MAGIC:
            if not MAGIC.startswith(head):
                raise NotMcap(f"{self.path}: not an MCAP file (it begins {head!r}, MCAP files "
                              f"{MAGIC!r})")
            raise self.damaged(len(head), "the file ends in its opening magic")
        self.pos, self.crc = len(MAGIC), zlib.crc32(MAGIC)
        data_end = None           # where the data section ended, once it has
        summary_crc = 0
        first = True
        while True:
            at = self.pos
            left = self.size - at
            if left < _HEAD.size:
                raise self.damaged(at, "the file ends after its last whole record, before "
                                       "its footer (cut short)" if left == 0 else
                                   "the file ends inside a record's header (cut short)")
            crc_before = self.crc
            op, length = _HEAD.unpack(self.read(_HEAD.size))
            what = _name(op)
            if op == 0:
                raise self.damaged(at, "opcode 0 (no record has it)")
            if first != (op == Opcode.HEADER):
                raise self.damaged(at, f"{what} where the header record must be" if first
                                   else "a second header record")
            first = False
            if length > MAX_RECORD_BYTES:
                raise self.damaged(at, f"this {what} declares {length} bytes, more than the "
                                       f"{MAX_RECORD_BYTES >> 20} MiB a record may have")
            if length > left - _HEAD.size:
                raise self.damaged(at, f"the file ends {left - _HEAD.size} bytes into "
                                       f"this {what} of {length} bytes (cut short)")
            body = self.read(length)
            if data_end is not None and op != Opcode.FOOTER:
                summary_crc = zlib.crc32(body, zlib.crc32(_HEAD.pack(op, length), summary_crc))
                if op not in _SUMMARY and op < 0x80:
                    raise self.damaged(at, f"{what} in the summary")
            elif op in _SUMMARY_ONLY:
                raise self.damaged(at, f"{what} in the data section")
            try:
                if op == Opcode.MESSAGE:
                    yield self.message(body, 0, length)
                elif op == Opcode.CHUNK:
                    yield from self.chunk(body, at)
                elif op == Opcode.SCHEMA:
                    self.schema(body, 0, length)
                elif op == Opcode.CHANNEL:
                    self.channel(body, 0, length)
                elif op == Opcode.ATTACHMENT:
                    self.attachment(body)
                elif op == Opcode.METADATA:
                    f = _Fields(body, 0, length, what)
                    f.text("name")
                    f.pairs("metadata", lambda g: g.text("key"), lambda g: g.text("value"))
                    self.metadata += 1
                elif op == Opcode.STATISTICS:
                    self.stats = self.statistics(body)
                elif op == Opcode.DATA_END:
                    (crc,) = _U32.unpack_from(body) if length >= 4 else (None,)
                    if crc is None or data_end is not None:
                        raise ValueError("a second one" if crc is not None else "it is short")
                    if crc and crc != crc_before:
                        raise ValueError(f"the data section's CRC fails (recorded {crc:#010x}, "
                                         f"computed {crc_before:#010x})")
                    data_end = self.pos
                elif op == Opcode.FOOTER:
                    self.footer(body, at, data_end, summary_crc)
                    return
            except ValueError as e:
                if isinstance(e, Damaged):
                    raise
                raise self.damaged(at, f"{what}: {e}") from None

    def message(self, data, start: int, end: int) -> tuple:
        if end - start < _MESSAGE_FIXED:
            raise ValueError(f"{end - start} bytes, fewer than a message's fixed fields")
        ch, _, ns = _MESSAGE.unpack_from(data, start)
        channel = self.channels.get(ch)
        if channel is None:
            raise ValueError(f"its channel {ch} was not defined before it")
        self.counts[ch] = self.counts.get(ch, 0) + 1
        return channel.topic, channel.metadata, ns, bytes(data[start + _MESSAGE_FIXED:end])

    def schema(self, data, start: int, end: int) -> None:
        f = _Fields(data, start, end, "schema record")
        sid = f.u16("id")
        name, encoding = f.text("name"), f.text("encoding")
        value = (name, encoding, f.blob(f.u32("data"), "data"))
        if sid == 0 or self.schemas.setdefault(sid, value) != value:
            raise ValueError(f"schema id {sid} is 0 or was defined otherwise before")
        if self.protobuf is not None and encoding == "protobuf":
            self.protobuf[name] = value[2]

    def channel(self, data, start: int, end: int) -> None:
        f = _Fields(data, start, end, "channel record")
        cid, sid = f.u16("id"), f.u16("schema id")
        topic, encoding = f.text("topic"), f.text("message encoding")
        metadata = dict(f.pairs("metadata", lambda g: g.text("key"), lambda g: g.text("value")))
        value = Channel(topic, encoding, sid, metadata)
        if sid and sid not in self.schemas:
            raise ValueError(f"channel {cid}'s schema {sid} was not defined before it")
        if self.channels.setdefault(cid, value) != value:
            raise ValueError(f"channel {cid} was defined otherwise before")

    def chunk(self, body: bytes, at: int) -> Iterator[tuple]:
        f = _Fields(body, 0, len(body), "chunk record")
        f.u64("start time"), f.u64("end time")
        size, crc = f.u64("uncompressed size"), f.u32("uncompressed CRC")
        compression = f.text("compression")
        n = f.u64("records")
        if size > MAX_RECORD_BYTES:
            raise ValueError(f"it declares {size} bytes uncompressed, more than the "
                             f"{MAX_RECORD_BYTES >> 20} MiB a chunk may hold: not decompressed")
        packed = memoryview(body)[f._take(n, "records"):f.i]
        if compression and size > max(1 << 20, MAX_RATIO * len(packed)):
            raise ValueError(f"it declares {size} bytes uncompressed from {len(packed)} "
                             f"compressed, more than the {MAX_RATIO}:1 a chunk may expand: "
                             f"not decompressed")
        if compression == "":
            data = bytes(packed)
        elif compression == "zstd":
            try:
                reader = self._zstd.stream_reader(io.BytesIO(packed), read_across_frames=True)
                data = reader.read(size + 1)
            except zstandard.ZstdError as e:
                raise ValueError(f"its zstd data: {e}") from None
        elif compression == "lz4":
            try:
                data = lz4.frame.LZ4FrameDecompressor().decompress(packed, max_length=size + 1)
            except RuntimeError as e:
                raise ValueError(f"its lz4 data: {e}") from None
        else:
            raise ValueError(f"compression {compression!r} (dqpose reads zstd, lz4 or none)")
        if len(data) != size:
            raise ValueError(f"it holds more than the {size} bytes it declares" if len(data) >
                             size else f"it holds {len(data)} bytes, {size} declared")
        if crc and zlib.crc32(data) != crc:
            raise ValueError(f"its CRC fails (recorded {crc:#010x}, computed "
                             f"{zlib.crc32(data):#010x})")
        self.chunks += 1
        i = 0
        while i < size:
            if size - i < _HEAD.size:
                raise ValueError(f"it ends inside a record's header at its byte {i}")
            op, length = _HEAD.unpack_from(data, i)
            start = i + _HEAD.size
            if op not in _IN_CHUNK or length > size - start:
                raise ValueError(f"its byte {i}: {_name(op)} of {length} bytes (a chunk "
                                 f"holds schemas, channels and messages, {size - start} "
                                 f"bytes are left)")
            i = start + length
            if op == Opcode.MESSAGE:
                yield self.message(data, start, i)
            elif op == Opcode.CHANNEL:
                self.channel(data, start, i)
            else:
                self.schema(data, start, i)

    def attachment(self, body: bytes) -> None:
        f = _Fields(body, 0, len(body), "attachment record")
        f.u64("log time"), f.u64("create time"), f.text("name"), f.text("media type")
        f.blob(f.u64("data"), "data")
        end = f.i
        crc = f.u32("CRC")
        if crc and zlib.crc32(body[:end]) != crc:
            raise ValueError("its CRC fails")
        self.attachments += 1

    def statistics(self, body: bytes) -> tuple:
        f = _Fields(body, 0, len(body), "statistics record")
        counts = (f.u64("message count"), f.u16("schema count"), f.u32("channel count"),
                  f.u32("attachment count"), f.u32("metadata count"), f.u32("chunk count"))
        f.u64("start time"), f.u64("end time")
        per = f.pairs("channel message counts", lambda g: g.u16("channel"),
                      lambda g: g.u64("count"))
        return counts, {c: n for c, n in per if n}

    def footer(self, body: bytes, at: int, data_end: int | None, summary_crc: int) -> None:
        if data_end is None:
            raise ValueError("before the data section's end (no data end record)")
        if len(body) < 20:
            raise ValueError("it is short")
        start, offsets, crc = struct.unpack_from("<QQI", body)
        if start not in (0, data_end) or (start == 0) != (at == data_end):
            raise ValueError(f"its summary start {start} is not where the data ends "
                             f"({data_end})")
        if not (offsets == 0 or data_end <= offsets <= at):
            raise ValueError(f"its summary offsets at {offsets} are outside the summary")
        summary_crc = zlib.crc32(body[:16], zlib.crc32(_HEAD.pack(Opcode.FOOTER, len(body)),
                                                         summary_crc))
        if crc and crc != summary_crc:
            raise ValueError(f"the summary's CRC fails (recorded {crc:#010x}, computed "
                             f"{summary_crc:#010x})")
        tail = self.f.read(len(MAGIC) + 1)
        if tail != MAGIC:
            raise self.damaged(self.pos, "the closing magic is missing or wrong, or bytes "
                                         "follow it")
        if self.stats is not None:
            (messages, schemas, channels, attachments, metadata, chunks), per = self.stats
            read = (sum(self.counts.values()), len(self.schemas), len(self.channels),
                    self.attachments, self.metadata, self.chunks)
            names = ("messages", "schemas", "channels", "attachments", "metadata", "chunks")
            for name, want, got in zip(names, (messages, schemas, channels, attachments,
                                               metadata, chunks), read):
                if want != got:
                    raise ValueError(f"its statistics count {want} {name}, the file holds "
                                     f"{got}")
            if per != self.counts:
                raise ValueError("its statistics' messages per channel are not those read")


def messages(path: str | os.PathLike, schemas: dict[str, bytes] | None = None
             ) -> Iterator[tuple[str, dict, int, bytes]]:
    """``(topic, channel metadata, log_time, data)`` of each message of the MCAP file at
    ``path`` in file order, every record checked first (the module's list); ``schemas`` (when
    given) gets each protobuf schema's ``FileDescriptorSet`` by message type as it is defined.
    :class:`Damaged` where the file stops being readable, :class:`NotMcap` for a file that is
    not MCAP, ``OSError`` as ``open`` raises it."""
    name = os.fspath(path)
    with open(name, "rb") as f:
        yield from _Reader(f, name, schemas).records()
