"""One MCAP file being written, through foxglove-sdk's writer (Rust: ~2 us a message here, where
``mcap``'s Python writer took ~37 us, which the server's event loop paid for in interpreter-lock
waits): schemas and channels registered as they are first used, messages in protobuf (schema
embedded) or JSON, chunked, zstd-compressed on the SDK's own threads, chunk CRCs. A context of
its own per file, so that files rotate without touching any other sink. Not thread-safe: the
recorder's writer thread owns it.
"""
from __future__ import annotations

import json
import logging
import os

import foxglove
from foxglove.mcap import MCAPWriteOptions

from dqpose.record.schemas import descriptor_set, json_schema

#: what the file says wrote it (MCAP's header ``profile`` is left empty: no ROS profile)
LIBRARY = "dqpose"

# Channels of one topic tell calls apart by their metadata (MCAP allows it); the SDK warns at
# each such channel, which would be a log line per call.
foxglove.set_log_level(logging.ERROR)


#: a chunk's uncompressed size: the SDK compresses a chunk inside the ``log`` call that fills it,
#: holding the interpreter lock (~2-4 ms for 1 MB, which the server's event loop waited for;
#: 16 kB: ~0.1 ms)
CHUNK_BYTES = 16 << 10


class McapFile:
    def __init__(self, path: str | os.PathLike, chunk_size: int = CHUNK_BYTES):
        self.path = os.fspath(path)
        self._context = foxglove.Context()
        self._writer = foxglove.open_mcap(
            self.path, allow_overwrite=False, context=self._context,
            writer_options=MCAPWriteOptions(chunk_size=chunk_size, compression_threads=0))
        self._channels: dict = {}
        self.messages = 0

    def channel(self, topic: str, cls, metadata: tuple = ()):
        """The channel of ``topic`` for protobuf messages of class ``cls``."""
        return self.proto_channel(topic, cls.DESCRIPTOR.full_name, descriptor_set(cls),
                                  metadata)

    def proto_channel(self, topic: str, name: str, schema: bytes, metadata: tuple = ()):
        """The channel of ``topic`` for protobuf messages of type ``name`` (``schema``: its
        ``FileDescriptorSet``; ``metadata``: pairs that tell channels of one topic apart, e.g.
        the call they record)."""
        key = (topic, name, metadata)
        ch = self._channels.get(key)
        if ch is None:
            ch = self._channels[key] = foxglove.Channel(
                topic, schema=foxglove.Schema(name=name, encoding="protobuf", data=schema),
                message_encoding="protobuf", context=self._context, metadata=dict(metadata))
        return ch

    def json_channel(self, topic: str, title: str, properties: dict):
        """The channel of ``topic`` for JSON objects (``properties``: name -> JSON type, for the
        schema viewers read)."""
        key = (topic, "json")
        ch = self._channels.get(key)
        if ch is None:
            schema = foxglove.Schema(name=title, encoding="jsonschema",
                                     data=json_schema(title, properties))
            ch = self._channels[key] = foxglove.Channel(
                topic, schema=schema, message_encoding="json", context=self._context)
        return ch

    def forget(self, topic: str, name: str, metadata: tuple) -> None:
        """Closes a channel no more messages will come on (a call that ended)."""
        ch = self._channels.pop((topic, name, metadata), None)
        if ch is not None:
            ch.close()

    def write(self, channel, ns: int, data: bytes) -> None:
        channel.log(data, log_time=ns)
        self.messages += 1

    def write_json(self, channel, ns: int, obj: dict) -> None:
        self.write(channel, ns, json.dumps(obj, separators=(",", ":")).encode())

    @property
    def size(self) -> int:
        """Bytes on disk so far (chunks are written when full: up to a chunk behind)."""
        try:
            return os.path.getsize(self.path)
        except OSError:
            return 0

    def close(self) -> None:
        """The last chunk, the summary (indexes, statistics) and the footer."""
        for ch in self._channels.values():
            ch.close()
        self._channels.clear()
        self._writer.close()
