"""MCAP files built byte by byte (the format's spec, not a writer library), so that a test can
declare what no writer would: sizes beyond the record or the file, chunks that decompress to
more than they declare, statistics that miscount. CRCs are right unless a test says otherwise."""
from __future__ import annotations

import struct
import zlib

import lz4.frame
import zstandard
from mcap.opcode import Opcode

MAGIC = b"\x89MCAP0\r\n"


def record(op: int, body: bytes, length: int | None = None) -> bytes:
    """A record: opcode, length (``body``'s unless given), body."""
    return struct.pack("<BQ", op, len(body) if length is None else length) + body


def text(s: str) -> bytes:
    b = s.encode()
    return struct.pack("<I", len(b)) + b


def header() -> bytes:
    return record(Opcode.HEADER, text("") + text("tests/record/_mcap.py"))


def schema(sid: int = 1, name: str = "t.Json", data: bytes = b"{}") -> bytes:
    return record(Opcode.SCHEMA, struct.pack("<H", sid) + text(name) + text("jsonschema") +
                  struct.pack("<I", len(data)) + data)


def channel(cid: int = 1, sid: int = 1, topic: str = "/t", metadata: dict | None = None) -> bytes:
    pairs = b"".join(text(k) + text(v) for k, v in (metadata or {}).items())
    return record(Opcode.CHANNEL, struct.pack("<HH", cid, sid) + text(topic) + text("json") +
                  struct.pack("<I", len(pairs)) + pairs)


def message(cid: int = 1, ns: int = 1, data: bytes = b"{}") -> bytes:
    return record(Opcode.MESSAGE, struct.pack("<HIQQ", cid, 0, ns, ns) + data)


def chunk(records: bytes, compression: str = "zstd", size: int | None = None,
          packed: bytes | None = None, crc: int | None = None) -> bytes:
    """A chunk of ``records``, compressed; ``size`` (the declared uncompressed size), ``packed``
    (its compressed bytes) and ``crc`` as given, else as ``records`` make them."""
    if packed is None:
        packed = {"zstd": zstandard.ZstdCompressor().compress, "lz4": lz4.frame.compress,
                  "": bytes}[compression](records)
    size = len(records) if size is None else size
    crc = zlib.crc32(records) if crc is None else crc
    return record(Opcode.CHUNK, struct.pack("<QQQI", 0, 0, size, crc) + text(compression) +
                  struct.pack("<Q", len(packed)) + packed)


def attachment(data: bytes, declared: int | None = None, crc: int | None = None) -> bytes:
    head = struct.pack("<QQ", 0, 0) + text("a") + text("application/octet-stream")
    body = head + struct.pack("<Q", len(data) if declared is None else declared) + data
    return record(Opcode.ATTACHMENT, body + struct.pack("<I", zlib.crc32(body) if crc is None
                                                        else crc))


def metadata(pairs: dict, declared: int | None = None) -> bytes:
    inner = b"".join(text(k) + text(v) for k, v in pairs.items())
    return record(Opcode.METADATA, text("m") + struct.pack(
        "<I", len(inner) if declared is None else declared) + inner)


def statistics(messages: int, channels: dict[int, int], schemas: int = 1, chunks: int = 0,
               attachments: int = 0, metadata: int = 0) -> bytes:
    per = b"".join(struct.pack("<HQ", c, n) for c, n in channels.items())
    return record(Opcode.STATISTICS, struct.pack(
        "<QHIIIIQQ", messages, schemas, len(channels), attachments, metadata, chunks, 0, 0) +
        struct.pack("<I", len(per)) + per)


def mcap(data: list[bytes], summary: list[bytes] = (), summary_crc: int | None = None) -> bytes:
    """A whole file: magic, header, the ``data`` records, data end (its CRC), ``summary``, the
    footer (the summary's CRC) and magic."""
    out = MAGIC + header() + b"".join(data)
    out += record(Opcode.DATA_END, struct.pack("<I", zlib.crc32(out)))
    summ = b"".join(summary)
    prefix = struct.pack("<BQQQ", Opcode.FOOTER, 20, len(out) if summ else 0, 0)
    crc = zlib.crc32(summ + prefix) if summary_crc is None else summary_crc
    return out + summ + prefix + struct.pack("<I", crc) + MAGIC


def zeros_zstd(n: int) -> bytes:
    """One zstd frame of ``n`` zero bytes, its content size in its header (~32 kB a GiB)."""
    obj = zstandard.ZstdCompressor(level=1).compressobj(size=n)
    block = bytes(1 << 20)
    parts = [obj.compress(block) for _ in range(n >> 20)]
    return b"".join(parts) + obj.compress(bytes(n & ((1 << 20) - 1))) + obj.flush()


#: where the first of a file's ``data`` records begins
DATA_START = len(MAGIC) + len(header())
