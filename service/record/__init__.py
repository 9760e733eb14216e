"""``dqpose.record``: calls recorded to MCAP files, with Foxglove's well-known schemas for viewing
(``docs/recording.md``: topics, schemas, frames, conventions).

The rpc layer hands every servicer one recorder (``Calls.recorder``): :data:`NULL`, which does
nothing, unless ``dqpose serve --record DIR`` opened a :class:`~dqpose.record.recorder.Recorder`
(:func:`open_recorder`). A servicer records a call as ``rec = recorder.call(rpc, RequestType,
AnswerType)``, then ``rec.measurements(request)`` for each request as it arrived,
``rec.fused(answer)`` for each answer, ``rec.end(code)``. This module imports nothing beyond
dqpose; the recorder needs the ``[record]`` extra (``foxglove-sdk`` writes, ``mcap`` reads,
``foxglove-schemas-protobuf`` has Foxglove's schemas, ``rosbags`` writes ROS 2 bags).
"""
from __future__ import annotations

from dqpose.errors import require


class _NullCall:
    __slots__ = ()
    alive = False

    def measurements(self, request) -> None:
        pass

    def fused(self, answer) -> None:
        pass

    def end(self, code: str, details: str = "") -> None:
        pass


class NullRecorder:
    """The recorder of a server that records nothing: the same calls, each doing nothing."""

    dropped = written = 0
    files: list = []

    def call(self, rpc: str, request_type, answer_type) -> _NullCall:
        return _NULL_CALL

    def plan(self, name: str, dqs) -> None:
        pass

    def close(self, timeout: float = 0.0) -> None:
        pass


_NULL_CALL = _NullCall()
NULL = NullRecorder()

#: the modules of the [record] extra
MODULES = ("foxglove", "mcap", "foxglove_schemas_protobuf")


def open_recorder(directory, **kw):
    """A :class:`~dqpose.record.recorder.Recorder` writing into ``directory``; ``MissingExtra``
    naming ``[record]`` when its modules are not installed."""
    require(*MODULES)
    from dqpose.record.recorder import Recorder

    return Recorder(directory, **kw)
