"""The ``dqpose.v1.Fusion`` service: Fuse (one body, one answer, :func:`dqpose.fusion.fuse`) and
StreamFuse (many bodies, a live stream: a private :class:`dqpose.hub.Hub` per stream, the engine
a World's Subscribe answers from, answered at output ticks paced on the measurements' time),
errors named by proto field.
"""
from __future__ import annotations

import itertools
import math
from typing import Any

import grpc
import numpy as np
from google.protobuf.message import DecodeError

from dqpose import fusion, limits
from dqpose.errors import FieldError, rename
from dqpose.fusion.bounds import TrackerBounds
from dqpose.hub import Hub, Rows
from dqpose.names import name_problem
from dqpose.rpc import DEFAULT_MAX_POSES
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as pb
from dqpose.rpc._proto.dqpose.v1 import fusion_pb2_grpc as pb_grpc
from dqpose.rpc.calls import Calls, readable, refusal
from dqpose.rpc.checks import over_count
from dqpose.rpc.fusion_convert import (
    DEFAULT_WINDOW,
    Measurements,
    Options,
    fused_of,
    measurements_to_arrays,
    options_error,
    options_from_msg,
    unknown_sources,
)
from dqpose.rpc.wire import fuse_stream_from_wire, fused_pose_bytes, wire_rows
from dqpose.rpc.world_convert import Encoder
from dqpose.world import WorldOptions


class Stream:
    """One StreamFuse stream's state: its private world (:meth:`dqpose.hub.Hub.open_stream`:
    one producer, the stream's window, its ticks at ``rate``, the server's limits), the one
    engine the World's Subscribe answers from too. Nothing here reads a clock: the answers are a
    function of the requests alone, so a recorded stream replays to the same answers."""

    def __init__(self, options: Options, rate: float, field: str = "requests[0].options",
                 bounds: limits.Limits = limits.DEFAULT):
        self.options = options
        world = WorldOptions(robust=options.robust, probability=options.probability,
                             max_skew=options.max_skew,
                             max_extrapolation=options.max_extrapolation,
                             twist_covariance=options.twist_covariance,
                             acceleration_psd=options.acceleration_psd,
                             window=options.window or DEFAULT_WINDOW)
        try:
            self.hub, self._answers = Hub.open_stream(options.sources, world, rate,
                                                      TrackerBounds.of(bounds),
                                                      _StreamEncoder())
        except ValueError as e:
            # the world names its options "options.x", a stream's sources are among them
            raise rename(e, {"options": field, "sources": f"{field}.sources{{}}"}) from None
        self.known = frozenset(s.name for s in options.sources) if options.sources else None
        self.cost = 0       # what the answers of the last update will cost (answer_cost)
        self._pending = False   # a step's answers not all taken yet

    @property
    def tracker(self) -> fusion.Tracker:
        """The stream's measurements (its world's tracker)."""
        return self.hub.world.tracker

    def update(self, m: Measurements, first: int, offered: int, field: str, codes=None):
        """Measurements ``m`` of one request of ``offered``, numbered from ``first`` (one step
        of its world): ``(answers, errors)``, answers an iterator of ``FusedPose`` bytes in
        order of the bodies' first appearance, then of time, each fused as it is taken; errors
        ``(measurement index, FieldError)``. ``codes`` (from the C decoder, one a row): the
        rows are checked already by the tracker's rules, those with a code refused (and named by
        the tracker's own check of that row alone), the others taken in unchecked."""
        errors = []
        if self.known is not None and not self.known.issuperset(m.sources):
            errors = [(int(m.index[k]), e) for k, e in unknown_sources(m, self.options, field)]
            keep = np.setdiff1d(m.index, [i for i, _ in errors])
            rows = np.flatnonzero(np.isin(m.index, keep))
            m = Measurements(m.index[rows], tuple(m.bodies[k] for k in rows),
                             tuple(m.sources[k] for k in rows), m.times[rows], m.poses[rows],
                             m.covariances[rows])
            codes = None if codes is None else codes[rows]
        self._step()
        self.hub.measurements = first       # the stream's call numbers its measurements
        applied = self.hub.publish("", "", 0, Rows(m.index, m.bodies, m.sources, m.times,
                                                   m.poses, m.covariances, codes), offered)
        errors += [(e.index, FieldError(e.named(field))) for e in applied.errors]
        self.cost = applied.cost
        answers, self._answers[:] = list(self._answers), []
        self._pending = not all(isinstance(a, bytes) for a in answers)
        return self._made(answers), errors

    def skip(self) -> None:
        """A request none of whose measurements was used: a step, no answer."""
        self._step()
        self.hub.publish("", "", 0, None, 0)
        self.cost = 0

    def _step(self) -> None:
        # a deferred answer fits the world as it is when taken: the stream's one producer takes
        # a request's answers before it sends the next (StreamFuse writes them first)
        assert not self._pending, "a stream's answers are taken before its next request"

    def _made(self, answers: list):
        """The step's ``answers``, each fitted (a callable) as it is taken."""
        for a in answers:
            yield a if isinstance(a, bytes) else a()
        self._pending = False


class _StreamEncoder(Encoder):
    """StreamFuse's answers: the World's, a fit's failure named by the option it is about."""

    @staticmethod
    def fit_error(e: Exception) -> str:
        cause = e.__cause__ if isinstance(e.__cause__, ValueError) else e
        return str(options_error(cause, "options")) if isinstance(cause, ValueError) else str(e)


def _error_entry(r: int, measurement: int, details: str, body: str = "") -> bytes:
    """A StreamFuse answer (its bytes) saying what request ``r`` (its ``measurement``, -1: all
    of it) had wrong."""
    return pb.FusedPose(body=body, request=r, error=pb.FuseError(
        request=r, measurement=measurement, details=readable(details))).SerializeToString()


class Fusion(pb_grpc.FusionServicer):
    """The ``dqpose.v1.Fusion`` service. ``fuse`` is a plain function of a request (no gRPC
    context): :func:`~dqpose.rpc.fusion_convert.fused_pose` within the server's limits."""

    NAME = pb.DESCRIPTOR.services_by_name["Fusion"].full_name

    def __init__(self, cfg=None, calls: Calls | None = None):
        """``cfg`` is the server's ``ServerConfig`` (its defaults when None)."""
        self.max_poses = cfg.max_poses if cfg is not None else DEFAULT_MAX_POSES
        self.limits = cfg.limits if cfg is not None else limits.DEFAULT
        self.calls = calls or Calls()

    # -- request -> response, no transport

    def fuse(self, request: pb.FuseRequest) -> bytes:
        """Fuse's answer: the ``FusedPose``'s bytes (:func:`~dqpose.rpc.wire.fused_pose_bytes`)."""
        fused, body = fused_of(request, self.limits, self.max_poses)
        assert fused.time is not None       # the measurements have times (fused_of)
        return fused_pose_bytes(fused, body, fused.time)

    def fuse_bytes(self, data: bytes) -> bytes:
        """What Fuse serves: ``FusedPose`` bytes for ``FuseRequest`` bytes."""
        return self.fuse(_fuse_request(data))

    def _fuse_small(self, data: bytes):
        """A small request's answer: on the event loop, unless it asks for a fit whose cost is
        not its size (:func:`_dear`), which goes to the worker pool, parsed once either way."""
        request = _fuse_request(data)
        if _dear(request.options):
            return self.calls.work(self.fuse, request)
        return self.fuse(request)

    def stream_options(self, request: pb.FuseStreamRequest):
        """The first request's options as the stream's state; a ``FieldError`` ends the stream."""
        options = options_from_msg(request.options, "requests[0].options")
        rate = request.output_rate
        if not (math.isfinite(rate) and rate >= 0.0):
            raise FieldError(f"requests[0].output_rate: must be finite and >= 0 (0: an answer "
                             f"after every request), got {rate!r}")
        if rate > self.limits.max_output_rate:
            raise limits.over("requests[0].output_rate", f"{rate:.6g} Hz", self.limits,
                              "max_output_rate")
        if options.time:
            raise FieldError("requests[0].options.time: StreamFuse answers at its output ticks, "
                             "or at each body's newest measurement; leave it 0")
        return Stream(options, rate, bounds=self.limits)

    def stream_step(self, state, request: pb.FuseStreamRequest, r: int,
                    first_id: int) -> list[pb.FusedPose]:
        """The answers to request ``r`` of a stream (its measurements numbered from
        ``first_id``): fused poses and error entries, never an exception for bad input; as
        messages, for a reader (the stream serves their bytes)."""
        return [pb.FusedPose.FromString(a)
                for a in self._stream_answers(state, request, r, first_id)]

    def _stream_answers(self, state, request: pb.FuseStreamRequest, r: int, first_id: int):
        """:meth:`stream_step`'s answers as bytes, the error entries made at once, each fused
        pose when it is taken (what they will cost: ``state.cost``)."""
        state.cost = 0
        out = []
        if r and (request.HasField("options") or request.output_rate):
            out.append(_error_entry(r, -1, f"requests[{r}].options: only the first request "
                                           f"carries options and output_rate; these are ignored"))
        too_many = over_count(f"requests[{r}].measurements", len(request.measurements),
                              self.max_poses, "measurements")
        if too_many is not None:
            state.skip()
            out.append(_error_entry(r, -1, f"{too_many}; none was used"))
            return out
        errors: list = []
        field = f"requests[{r}].measurements"
        m = measurements_to_arrays(request.measurements, field, errors)
        answers, more = state.update(m, first_id, len(request.measurements), field)
        bodies = [request.measurements[i].body for i, _ in errors + more]
        return itertools.chain(out, self._answers(r, errors + more, bodies, answers))

    def stream_step_wire(self, state, data: bytes, r: int, first_id: int):
        """:meth:`stream_answers_wire` with the answers made at once, as a list of messages
        (for a reader)."""
        answers, n = self.stream_answers_wire(state, data, r, first_id)
        return [pb.FusedPose.FromString(a) for a in answers], n

    def stream_answers_wire(self, state, data: bytes, r: int, first_id: int):
        """:meth:`stream_step` of request ``r``'s bytes: ``(answers, its number of
        measurements)``, the answers an iterator of ``FusedPose`` bytes that fuses each as it is
        taken (what StreamFuse serves and records). A plain request
        (measurements only) is decoded and checked in C
        (:func:`dqpose.rpc.wire.fuse_stream_from_wire`) and its valid measurements go to the tracker
        unchecked; any other takes the protobuf path. Both give the same answers. Bytes that are
        not a FuseStreamRequest are an error entry for the request."""
        state.cost = 0
        w = fuse_stream_from_wire(data) if r else None
        if w is None or len(w.times) > self.max_poses:
            try:
                request = pb.FuseStreamRequest.FromString(data)
            except DecodeError:
                state.skip()
                return [_error_entry(r, -1, f"requests[{r}]: not a valid "
                                            f"dqpose.v1.FuseStreamRequest message; none of it "
                                            f"was used")], 0
            return (self._stream_answers(state, request, r, first_id),
                    len(request.measurements))
        field = f"requests[{r}].measurements"
        n = len(w.times)
        m, errors, codes = wire_rows(data, w, field)
        answers, more = state.update(m, first_id, n, field, codes)
        errors += more
        return self._answers(r, errors, [w.bodies[i] for i, _ in errors], answers), n

    def _answers(self, r: int, errors: list, bodies: list, answers):
        """Request ``r``'s error entries (``errors`` ``(measurement, FieldError)``, of the
        measurements of ``bodies``) in order of measurement, then its fused poses, one at a
        time. An entry names its body when that is a name (one refused for its name is not
        sent back)."""
        for (i, e), body in sorted(zip(errors, bodies), key=lambda x: x[0][0]):
            yield _error_entry(r, i, str(e), "" if name_problem(body) else body)
        yield from answers

    # -- RPCs

    def register(self, server) -> None:
        """``add_FusionServicer_to_server`` except that both RPCs take and give bytes: Fuse's
        are parsed with the fit (:meth:`fuse_bytes`, off the event loop when large),
        StreamFuse's decoded by :meth:`stream_answers_wire` (the C decoder for plain ones); the
        answers are written by :func:`~dqpose.rpc.wire.fused_pose_bytes`."""
        handlers: dict[str, grpc.RpcMethodHandler[Any, Any]] = {
            "Fuse": grpc.unary_unary_rpc_method_handler(
                self.Fuse, request_deserializer=None, response_serializer=None),
            "StreamFuse": grpc.stream_stream_rpc_method_handler(
                self.StreamFuse, request_deserializer=None, response_serializer=None),
        }
        generic = grpc.method_handlers_generic_handler(self.NAME, handlers)
        server.add_generic_rpc_handlers((generic,))
        server.add_registered_method_handlers(self.NAME, handlers)

    async def Fuse(self, request: bytes, context):
        # Registered without (de)serializers (register): bytes in and out, parsed and written
        # with the fit, in the worker pool when the request is not small.
        rec = self.calls.recorder.call(FUSE, pb.FuseRequest, pb.FusedPose)
        if len(request) <= limits.INLINE_BYTES:
            return await self.calls.unary("Fuse", self._fuse_small, request, context,
                                          recording=rec)
        return await self.calls.unary(
            "Fuse", lambda r: self.calls.work(self.fuse_bytes, r), request, context,
            recording=rec)

    def start_stream(self, data: bytes):
        """The first request of a stream: ``(state, its answers, its number of measurements)``;
        a FieldError (or OverLimit) for options the stream cannot start with."""
        try:
            request = pb.FuseStreamRequest.FromString(data)
        except DecodeError:
            raise FieldError("requests[0]: not a valid dqpose.v1.FuseStreamRequest "
                             "message") from None
        state = self.stream_options(request)
        return state, self._stream_answers(state, request, 0, 0), len(request.measurements)

    async def _write(self, answers, cost: int, context, rec) -> None:
        """Writes a request's answers (each recorded to ``rec`` as it goes): fused on the event
        loop when they cost little (``limits.INLINE_ROWS``), else in the worker pool,
        ``ANSWERS_PER_WORK`` at a time so that the first ones are on their way while the next
        are fused."""
        if cost <= limits.INLINE_ROWS:
            for answer in answers:
                rec.answer(answer)
                await context.write(answer)
            return
        answers = iter(answers)
        while chunk := await self.calls.work(_take, answers, ANSWERS_PER_WORK):
            for answer in chunk:
                rec.answer(answer)
                await context.write(answer)

    async def StreamFuse(self, request_iterator, context):
        state = None
        next_id = 0
        rec = self.calls.recorder.call(STREAM_FUSE, pb.FuseStreamRequest, pb.FusedPose)
        async with self.calls.stream("StreamFuse", context, rec) as call:
            if call.open() is None:
                return
            # Registered without a deserializer (register): each request arrives as bytes.
            # Decoded on the event loop when small (most of a live stream's messages), else in
            # the worker pool, like the answers (_write).
            async for data in request_iterator:
                rec.request(data)
                r = call.messages
                if state is None:
                    try:
                        state, answers, n = await self.calls.work(self.start_stream, data)
                    except FieldError as e:
                        await call.refuse(refusal(e), readable(str(e)))
                elif len(data) <= limits.INLINE_BYTES:
                    answers, n = self.stream_answers_wire(state, data, r, next_id)
                else:
                    answers, n = await self.calls.work(self.stream_answers_wire, state, data, r,
                                                       next_id)
                await self._write(answers, state.cost, context, rec)
                next_id += n
                call.messages += 1


#: the full names recordings know the calls by (dqpose.record)
FUSE = f"{Fusion.NAME}/Fuse"
STREAM_FUSE = f"{Fusion.NAME}/StreamFuse"


#: StreamFuse answers fused per turn of the worker pool (when fused there)
ANSWERS_PER_WORK = 16


def _take(answers, k: int) -> list:
    """The next ``k`` of ``answers`` (fewer at its end)."""
    return list(itertools.islice(answers, k))


def _fuse_request(data: bytes) -> pb.FuseRequest:
    try:
        return pb.FuseRequest.FromString(data)
    except DecodeError:
        raise FieldError("request: not a valid dqpose.v1.FuseRequest message") from None


def _dear(options) -> bool:
    """Whether Fuse ``options`` ask for a fit whose cost is not its size: the acceleration
    model's dense solve or a latency estimate (milliseconds at a few measurements;
    limits.CORRELATED_ROWS)."""
    return any(options.acceleration_psd) or any(s.latency_sigma for s in options.sources)
