"""``dqpose.record``: calls recorded to MCAP files, with Foxglove's well-known schemas for viewing
(``docs/recording.md``: topics, schemas, frames, conventions).

The rpc layer hands every servicer one recorder (``Calls.recorder``): :data:`NULL`, which does
nothing, unless ``dqpose serve --record DIR`` opened a :class:`~dqpose.record.recorder.Recorder`
(:func:`open_recorder`). A servicer records a call as ``rec = recorder.call(rpc, RequestType,
AnswerType)``, then ``rec.request(request)`` for each request as it arrived,
``rec.answer(answer)`` for each answer, ``rec.end(code)``. This module imports nothing beyond
dqpose; ``dqpose serve --live`` serves the same channels on foxglove-sdk's WebSocket server
(:mod:`dqpose.record.live`). The recorder needs the ``[record]`` extra (``foxglove-sdk`` writes
and serves, ``mcap`` reads, ``foxglove-schemas-protobuf`` has Foxglove's schemas, ``rosbags``
writes ROS 2 bags).
"""
from __future__ import annotations

from dqpose.errors import MissingExtra, require
from dqpose.record.settings import (  # noqa: F401 (the package's names)
    DEFAULT_HOST,
    DEFAULT_PORT,
    HEALTH_SERVICE,
    LIVE_TOKEN_ENV,
    MODULES,
    PLAN_VIEW_POSES,
    PROBE_BYTES,
    LiveFailed,
    cannot_write,
    describe,
    live_problem,
    loopback,
    parse_address,
)


class _NullCall:
    __slots__ = ()
    alive = False

    def request(self, request) -> None:
        pass

    def answer(self, answer) -> None:
        pass

    def end(self, code: str, details: str = "") -> None:
        pass


class NullRecorder:
    """The recorder of a server that records nothing: the same calls, each doing nothing."""

    dropped = written = failed = 0
    files: list = []
    failure = None
    #: no subscriber of its own in a world (dqpose.rpc.world._follow)
    world_rate = None
    #: whether anything is recorded (a caller skips work only a recording needs)
    recording = False

    def call(self, rpc: str, request_type, answer_type, world: str = "",
             internal: bool = False) -> _NullCall:
        return NULL_CALL

    def plan(self, name: str, dqs) -> None:
        pass

    def note(self, topic: str, title: str, data: dict) -> None:
        pass

    def watch(self, changed) -> None:
        pass

    def close(self, timeout: float = 0.0) -> None:
        pass


#: a call that records nothing (what :data:`NULL` hands every servicer)
NULL_CALL = _NullCall()
NULL = NullRecorder()

def open_recorder(directory, **kw):
    """A :class:`~dqpose.record.recorder.Recorder` writing into ``directory`` (and serving
    ``live=(host, port)``, else :class:`LiveFailed`, to the clients ``live_token``,
    ``live_origins`` and ``live_insecure`` let in); ``MissingExtra`` naming ``[record]`` when
    its modules are not installed."""
    require(*MODULES)
    if kw.get("live") is not None:
        try:
            import websockets  # noqa: F401
        except ModuleNotFoundError:     # the [view] extra's too, which EXTRA_OF names
            raise MissingExtra("record", "websockets") from None
    from dqpose.record.recorder import Recorder

    return Recorder(directory, **kw)
