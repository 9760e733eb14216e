"""Where the writer process logs a recording's channels: a foxglove-sdk context of its own with
its channels, registered as they are first used (protobuf with the schema embedded, or JSON).
An MCAP file (:mod:`dqpose.record.mcapfile`) and the live WebSocket server
(:mod:`dqpose.record.live`, whose channels are its own: ``_open``) are each one, so both carry
the same topics and schemas, built by the same code (:mod:`dqpose.record.writer`). Not
thread-safe: the writer owns it.
"""
from __future__ import annotations

import json
import logging

import foxglove

from dqpose.record.schemas import descriptor_set, json_schema

# Channels of one topic tell calls apart by their metadata (MCAP allows it); the SDK warns at
# each such channel, which would be a log line per call.
foxglove.set_log_level(logging.ERROR)


class Sink:
    def __init__(self) -> None:
        self._context = foxglove.Context()
        self._channels: dict = {}
        self.messages = 0
        #: the bodies whose views this sink carries (at most MAX_VIEW_BODIES)
        self.view_bodies: set[str] = set()

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
            ch = self._channels[key] = self._open(topic, "protobuf", name, "protobuf", schema,
                                                  metadata)
        return ch

    def json_channel(self, topic: str, title: str, properties: dict):
        """The channel of ``topic`` for JSON objects (``properties``: name -> JSON type, for the
        schema viewers read)."""
        key = (topic, "json")
        ch = self._channels.get(key)
        if ch is None:
            ch = self._channels[key] = self._open(topic, "json", title, "jsonschema",
                                                  json_schema(title, properties))
        return ch

    def _open(self, topic: str, message_encoding: str, schema_name: str, schema_encoding: str,
              schema: bytes, metadata: tuple = ()):
        """A new channel (anything with ``log(data, log_time=ns)`` and ``close()``): here
        foxglove-sdk's, in this sink's context."""
        return foxglove.Channel(
            topic, schema=foxglove.Schema(name=schema_name, encoding=schema_encoding,
                                          data=schema),
            message_encoding=message_encoding, context=self._context, metadata=dict(metadata))

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

    def close_channels(self) -> None:
        for ch in self._channels.values():
            ch.close()
        self._channels.clear()
