"""The schemas a recording embeds: a protobuf message class's ``FileDescriptorSet`` (its file and
every file it imports), and the JSON schemas of the recorder's own small channels.

MCAP's protobuf profile stores a schema as the serialized ``google.protobuf.FileDescriptorSet``
that holds the message's type; a reader rebuilds the message class from it alone (what the tests
do), so a file stays readable without dqpose or Foxglove's packages.
"""
from __future__ import annotations

import functools
import json

from google.protobuf import descriptor_pb2


@functools.lru_cache(maxsize=None)
def descriptor_set(cls) -> bytes:
    """The ``FileDescriptorSet`` of protobuf message class ``cls``: its file after every file it
    depends on, each once."""
    out = descriptor_pb2.FileDescriptorSet()
    seen: set[str] = set()

    def add(fd) -> None:
        if fd.name in seen:
            return
        seen.add(fd.name)
        for dep in fd.dependencies:
            add(dep)
        fd.CopyToProto(out.file.add())

    add(cls.DESCRIPTOR.file)
    return out.SerializeToString()


def json_schema(title: str, properties: dict) -> bytes:
    """A JSON schema (the ``jsonschema`` encoding of MCAP's profile) of an object with these
    ``properties`` (name -> JSON type)."""
    return json.dumps({"title": title, "type": "object",
                       "properties": {k: {"type": v} for k, v in properties.items()}}).encode()


def message_class(data: bytes, name: str):
    """The protobuf class of message type ``name`` built from a ``FileDescriptorSet`` alone (a
    descriptor pool of its own): what a recording embeds is enough to read it."""
    from google.protobuf import descriptor_pool, message_factory

    pool = descriptor_pool.DescriptorPool()
    for fd in descriptor_pb2.FileDescriptorSet.FromString(data).file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))
