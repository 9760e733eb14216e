"""One MCAP file being written: schemas and channels registered as they are first used, messages
in protobuf (schema embedded) or JSON, chunked, zstd-compressed, every chunk and the summary with
their CRCs (``mcap``'s writer). Not thread-safe: the recorder's writer thread owns it.
"""
from __future__ import annotations

import json
import os

from mcap.writer import CompressionType, Writer

from dqpose.record.schemas import descriptor_set, json_schema

#: what the file says wrote it (MCAP's header ``library``)
LIBRARY = "dqpose"


class McapFile:
    def __init__(self, path: str | os.PathLike, chunk_size: int = 1 << 20):
        self.path = os.fspath(path)
        self._file = open(self.path, "wb")
        self._writer = Writer(self._file, chunk_size=chunk_size,
                              compression=CompressionType.ZSTD)
        self._writer.start(profile="", library=LIBRARY)
        self._schemas: dict = {}
        self._channels: dict = {}
        self.messages = 0

    def _schema(self, key, name: str, encoding: str, data: bytes) -> int:
        sid = self._schemas.get(key)
        if sid is None:
            sid = self._schemas[key] = self._writer.register_schema(name, encoding, data)
        return sid

    def channel(self, topic: str, cls, metadata: tuple = ()) -> int:
        """The channel of ``topic`` for protobuf messages of class ``cls`` (``metadata``: pairs
        that tell channels of one topic apart, e.g. the call they record)."""
        key = (topic, cls, metadata)
        cid = self._channels.get(key)
        if cid is None:
            sid = self._schema(cls, cls.DESCRIPTOR.full_name, "protobuf", descriptor_set(cls))
            cid = self._channels[key] = self._writer.register_channel(
                topic, "protobuf", sid, dict(metadata))
        return cid

    def json_channel(self, topic: str, title: str, properties: dict) -> int:
        """The channel of ``topic`` for JSON objects (``properties``: name -> JSON type, for the
        schema viewers read)."""
        key = (topic, "json")
        cid = self._channels.get(key)
        if cid is None:
            sid = self._schema(("json", title), title, "jsonschema",
                               json_schema(title, properties))
            cid = self._channels[key] = self._writer.register_channel(topic, "json", sid)
        return cid

    def write(self, channel: int, ns: int, data: bytes, sequence: int = 0) -> None:
        self._writer.add_message(channel, log_time=ns, data=data, publish_time=ns,
                                 sequence=sequence)
        self.messages += 1

    def write_json(self, channel: int, ns: int, obj: dict) -> None:
        self.write(channel, ns, json.dumps(obj, separators=(",", ":")).encode())

    @property
    def size(self) -> int:
        """Bytes written so far (chunks are written when full: up to a chunk behind)."""
        return self._file.tell()

    def close(self) -> None:
        """The last chunk, the summary (indexes, statistics) and the footer, then the file."""
        try:
            self._writer.finish()
        finally:
            self._file.close()
