"""The ``dqpose.v1.Fusion`` service: Fuse (one body, one answer) and StreamFuse (many bodies, a
live stream), both answered by :func:`service.fusion.fuse`, whose errors name the proto field.

StreamFuse keeps its per-body state in a :class:`Snapshot` made per stream: the only part that
changes when :mod:`service.fusion` grows its sliding-window tracker (time alignment, output-rate
pacing): a class with the same ``update`` replaces it.
"""
from __future__ import annotations

import math
import re

import grpc
import numpy as np

from service import fusion
from service.errors import FieldError, rename
from service.rpc import DEFAULT_MAX_POSES
from service.rpc.calls import INTERNAL_DETAILS, Calls, log
from service.rpc.convert import (Measurements, Options, fused_to_msg, measurements_to_arrays,
                                 options_from_msg)
from service.rpc._proto.dqpose.v1 import fusion_pb2 as pb
from service.rpc._proto.dqpose.v1 import fusion_pb2_grpc as pb_grpc

# The domain's per-measurement arguments, as fields of a Measurement.
_MEASUREMENT_FIELDS = {"poses": "pose", "covariances": "covariance"}
_INDEXED = re.compile(r"^(\w+)\[(\d+)\]")


def _options_error(e: ValueError, field: str) -> FieldError:
    return rename(e, {"sources": f"{field}.sources{{}}", "probability": f"{field}.probability"})


def _domain_error(e: ValueError, index: np.ndarray, field: str, options: str):
    """The domain's ``ValueError`` about row ``k`` of the arrays it was given as ``(k, error
    naming the message's measurement index[k])``; ``(None, error)`` for one about the options."""
    hit = _INDEXED.match(str(e))
    if hit is None or hit[1] not in _MEASUREMENT_FIELDS:
        return None, _options_error(e, options)
    k = int(hit[2])
    return k, rename(e, {hit[1]: f"{field}[{int(index[k])}].{_MEASUREMENT_FIELDS[hit[1]]}"})


def unknown_sources(m: Measurements, options: Options, field: str) -> list[int]:
    """Rows of ``m`` whose source the options do not list (when they list any), each with the
    error naming it: a misspelt name would otherwise silently lose its frames."""
    if not options.sources:
        return []
    known = {s.name for s in options.sources}
    listed = ", ".join(s.name for s in options.sources)
    return [(k, FieldError(f"{field}[{int(m.index[k])}].source: {m.sources[k]!r} is not among "
                           f"options.sources ({listed})"))
            for k in range(len(m.index)) if m.sources[k] not in known]


def fuse_rows(m: Measurements, rows: list[int], options: Options, field: str,
              errors: list | None = None, options_field: str = "options"):
    """:func:`fusion.fuse` of rows ``rows`` of ``m``: ``(rows fused, Fused)``. A measurement the
    domain refuses raises its error (naming ``{field}[i]``), or with ``errors`` is appended there
    as ``(i, FieldError)`` and the rest are fused (``(rows, None)`` when none is left)."""
    rows = list(rows)
    while rows:
        try:
            return rows, fusion.fuse(m.poses[rows], m.covariances[rows],
                                     names=[m.sources[k] for k in rows], sources=options.sources,
                                     robust=options.robust, probability=options.probability)
        except ValueError as e:
            k, err = _domain_error(e, m.index[rows], field, options_field)
            if k is None or errors is None:
                raise err from None
            errors.append((int(m.index[rows[k]]), err))
            del rows[k]
    return rows, None


def check_options(options: Options, field: str) -> None:
    """The domain's checks of the sources, before any measurement arrives (StreamFuse): one
    identity measurement fused with them."""
    try:
        fusion.fuse(np.array([[1.0, 0, 0, 0, 0, 0, 0, 0]]), sources=options.sources,
                    probability=options.probability)
    except ValueError as e:
        raise _options_error(e, field) from None


class Snapshot:
    """StreamFuse's per-body state until :mod:`service.fusion` has its sliding-window tracker:
    none. Each request's measurements of a body are fused alone, at the newest one's time (or
    the options' time)."""

    def __init__(self, options: Options):
        self.options = options

    def update(self, m: Measurements, ids: np.ndarray, field: str):
        """Measurements ``m`` of one request (``ids``: their stream-wide numbers): ``(answers,
        errors)``, answers ``(body, time, Fused, ids of the fused measurements)`` per body in
        order of first appearance, errors ``(measurement index, FieldError)``."""
        errors = unknown_sources(m, self.options, field)
        bad = {k for k, _ in errors}
        errors = [(int(m.index[k]), e) for k, e in errors]
        groups: dict[str, list[int]] = {}
        for k, body in enumerate(m.bodies):
            if k not in bad:
                groups.setdefault(body, []).append(k)
        answers = []
        for body, rows in groups.items():
            rows, fused = fuse_rows(m, rows, self.options, field, errors)
            if fused is not None:
                answers.append((body, self.options.time or float(m.times[rows].max()), fused,
                                ids[rows]))
        return answers, errors


class Fusion(pb_grpc.FusionServicer):
    """The ``dqpose.v1.Fusion`` service. ``fuse`` is a plain function of a request (no gRPC
    context): ``dqpose fuse --local`` answers with it."""

    NAME = pb.DESCRIPTOR.services_by_name["Fusion"].full_name
    # StreamFuse's per-stream state (see Snapshot): made from the stream's Options.
    State = Snapshot

    def __init__(self, cfg=None, calls: Calls | None = None):
        """``cfg`` is the server's ``ServerConfig`` (its defaults when None)."""
        self.max_poses = cfg.max_poses if cfg is not None else DEFAULT_MAX_POSES
        self.calls = calls or Calls()

    def _check_count(self, field: str, n: int) -> None:
        if n == 0:
            raise FieldError(f"{field}: empty request: no measurements")
        if n > self.max_poses:
            raise FieldError(f"{field}: {n} measurements exceed the server limit of "
                             f"{self.max_poses}")

    # -- request -> response, no transport

    def fuse(self, request: pb.FuseRequest) -> pb.FusedPose:
        self._check_count("measurements", len(request.measurements))
        options = options_from_msg(request.options)
        m = measurements_to_arrays(request.measurements)
        for k, body in enumerate(m.bodies):
            if body != m.bodies[0]:
                raise FieldError(f"measurements[{k}].body: {body!r} differs from "
                                 f"measurements[0].body {m.bodies[0]!r} (Fuse fuses one body; "
                                 f"StreamFuse takes many)")
        unknown = unknown_sources(m, options, "measurements")
        if unknown:
            raise unknown[0][1]
        _, fused = fuse_rows(m, range(len(m.index)), options, "measurements")
        return fused_to_msg(fused, m.bodies[0], options.time or float(m.times.max()))

    def stream_options(self, request: pb.FuseStreamRequest):
        """The first request's options as the stream's state; a ``FieldError`` ends the stream."""
        options = options_from_msg(request.options, "requests[0].options")
        rate = request.output_rate
        if not (math.isfinite(rate) and rate >= 0.0):
            raise FieldError(f"requests[0].output_rate: must be finite and >= 0 (0: an answer "
                             f"after every request), got {rate!r}")
        check_options(options, "requests[0].options")
        return self.State(options)

    def stream_step(self, state, request: pb.FuseStreamRequest, r: int,
                    first_id: int) -> list[pb.FusedPose]:
        """The answers to request ``r`` of a stream (its measurements numbered from
        ``first_id``): fused poses and error entries, never an exception for bad input."""
        out = []

        def error(measurement: int, e: FieldError, body: str = "") -> None:
            out.append(pb.FusedPose(body=body, request=r, error=pb.FuseError(
                request=r, measurement=measurement, details=str(e))))

        if r and (request.HasField("options") or request.output_rate):
            error(-1, FieldError(f"requests[{r}].options: only the first request carries "
                                 f"options and output_rate; these are ignored"))
        n = len(request.measurements)
        if n > self.max_poses:
            error(-1, FieldError(f"requests[{r}].measurements: {n} measurements exceed the "
                                 f"server limit of {self.max_poses}; none was used"))
            return out
        errors: list = []
        field = f"requests[{r}].measurements"
        m = measurements_to_arrays(request.measurements, field, errors)
        answers, more = state.update(m, first_id + m.index, field)
        for i, e in sorted(errors + more, key=lambda x: x[0]):
            error(i, e, request.measurements[i].body)
        for body, t, fused, ids in answers:
            msg = fused_to_msg(fused, body, t)
            msg.request = r
            msg.measurements.extend(ids.tolist())
            out.append(msg)
        return out

    # -- RPCs

    def register(self, server) -> None:
        pb_grpc.add_FusionServicer_to_server(self, server)

    async def Fuse(self, request, context):
        return await self.calls.unary("Fuse", self.fuse, request, context)

    async def StreamFuse(self, request_iterator, context):
        t0 = self.calls.begin()
        code = "OK"
        r = 0
        next_id = 0
        state = None
        try:
            async for request in request_iterator:
                if state is None:
                    try:
                        state = self.stream_options(request)
                    except FieldError as e:
                        code = "INVALID_ARGUMENT"
                        await context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(e))
                for answer in self.stream_step(state, request, r, next_id):
                    await context.write(answer)
                next_id += len(request.measurements)
                r += 1
        except Exception as e:
            if isinstance(e, grpc.aio.AbortError):
                raise
            code = "INTERNAL"
            log.exception("StreamFuse failed")
            await context.abort(grpc.StatusCode.INTERNAL, INTERNAL_DETAILS)
        except BaseException:   # asyncio.CancelledError: the client went away
            code = "CANCELLED"
            raise
        finally:
            self.calls.done("StreamFuse", code, t0, context, messages=r)
