"""What every servicer shares: one call in, one status out, one log line and one metric sample.

A handler raises :class:`~dqpose.errors.FieldError` for bad input (``INVALID_ARGUMENT`` with its
text, which starts with the proto field path), :class:`~dqpose.limits.OverLimit` for a request
over one of the server's limits and :class:`TooLarge` for an answer over the server's max message
size (both ``RESOURCE_EXHAUSTED``, see :func:`fit`); anything else is
``INTERNAL``, logged with its traceback, and the server keeps running.
"""
from __future__ import annotations

import asyncio
import contextlib
import ctypes
import ctypes.util
import functools
import gc
import json
import logging
import re
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import AsyncIterator, Callable, NoReturn

import grpc

from dqpose import limits, record
from dqpose.errors import FieldError, Infeasible, MissingExtra, WorldError
from dqpose.limits import OverLimit
from dqpose.rpc.peers import STREAM, Peers, Slot

log = logging.getLogger("dqpose.server")
call_log = logging.getLogger("dqpose.calls")

INTERNAL_DETAILS = "internal error (see the server log)"


class TooLarge(Exception):
    """An answer over the server's max message size: ``RESOURCE_EXHAUSTED`` with this text."""


def fit(response: bytes, limit: int, field: str, count: int, noun: str) -> bytes:
    """``response`` when it fits in one message of ``limit`` bytes (the server's
    ``max_message_bytes``), else :class:`TooLarge` naming the size, the limit and how many of the
    ``count`` ``noun`` of the request's ``field`` would fit.

    Checked before sending because gRPC's own refusal ("Sent message larger than max") comes
    after the handler returned: the call would be logged and counted as OK, with a traceback."""
    size = len(response)
    if size <= limit:
        return response
    what = f"{field}: the response to {count} {noun} is {size} bytes, over the server's max " \
           f"message size of {limit} bytes"
    per_call = count * limit // size   # the average answer per item: "about"
    if per_call < 1:
        raise TooLarge(f"{what}; the server's max message size is too small for one answer")
    raise TooLarge(f"{what}; send about {per_call} {noun} per call, or fewer")


def refusal(e: Exception) -> grpc.StatusCode | None:
    """The status a handler's deliberate refusal stands for; None for anything else (INTERNAL)."""
    if isinstance(e, (Infeasible, MissingExtra)):   # MissingExtra: an extra the server lacks
        return grpc.StatusCode.FAILED_PRECONDITION
    if isinstance(e, OverLimit) or (isinstance(e, WorldError) and e.limit is not None):
        return grpc.StatusCode.RESOURCE_EXHAUSTED
    if isinstance(e, FieldError):
        return grpc.StatusCode.INVALID_ARGUMENT
    if isinstance(e, TooLarge):
        return grpc.StatusCode.RESOURCE_EXHAUSTED
    return None


def refused(rpc: str, e: Exception) -> tuple[grpc.StatusCode, str]:
    """The status and text a handler's exception ends its call with: the :func:`refusal` status
    with the exception's text (:func:`readable`), else INTERNAL (logged with its traceback, the
    text kept out of the answer)."""
    status = refusal(e)
    if status is None:
        log.exception("%s failed", rpc)
        _forget_frames(e)
        return grpc.StatusCode.INTERNAL, INTERNAL_DETAILS
    _forget_frames(e)
    return status, readable(str(e))


def _forget_frames(e: BaseException | None) -> None:
    """Drops the tracebacks of ``e`` and of the exceptions it chains: their frames hold the
    request (its bytes, its messages, its arrays), and an exception caught in a coroutine is
    freed only by the cyclic collector, which a few calls do not wake. 60 refused 3.6 MB Fuse
    requests left the server 140 MB larger until a collection ran."""
    seen = set()
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        e.__traceback__ = None
        if e.__cause__ is not None:
            _forget_frames(e.__cause__)
        e = e.__context__


# a number of more than 9 significant digits standing alone (not part of a name, not an index:
# a whole number in brackets; a fraction may be in them, as an interval's bound). Nine digits
# are the domain's own deliberate precision (a norm of 0.989949494 says how far from 1 it is).
_LONG_NUMBER = re.compile(r"(?<![\w.\[])-?\d{10,}(?:\.\d*)?(?:e[+-]?\d+)?(?![\w.\]])"
                          r"|(?<![\w.])-?\d*\.\d{10,}(?:e[+-]?\d+)?(?![\w.])")


#: bytes of UTF-8 a refusal's text has at most (then "..."): a status's details travel in its
#: trailers, whose size a client bounds (8 KiB by default, a hard limit that turns the status into
#: RESOURCE_EXHAUSTED "received metadata size exceeds hard limit")
MAX_DETAILS = 1024


def readable(text: str) -> str:
    """``text`` with every number of more than 9 significant digits written ``%.6g``: what the
    domain's texts hold as ``repr`` (``0.041694716291423795``, a 300-digit count) reads as
    ``0.0416947`` and ``5e+299``; a whole count of up to 15 digits is kept (``999999990 ticks``
    reads better exact); at most :data:`MAX_DETAILS` bytes. Every refusal's text goes through
    here, so none can leak a number or grow with what a client sent."""
    cut = len(text) > 2 * MAX_DETAILS       # (what is beyond cannot be kept anyway)
    text = _LONG_NUMBER.sub(_short, text[:2 * MAX_DETAILS])
    data = text.encode(errors="replace")
    if cut or len(data) > MAX_DETAILS:
        text = data[:MAX_DETAILS - 3].decode(errors="ignore") + "..."
    return text


def _short(match: re.Match) -> str:
    number = match[0]
    if number.lstrip("-").isdigit() and len(number.lstrip("-")) <= 15:
        return number
    return f"{float(number):.6g}"


class Calls:
    """Records calls: every call that :meth:`begin` counts in gets exactly one :meth:`done`, a
    Prometheus sample (``metrics.observe``) and a JSON log line on ``dqpose.calls``. One per
    server, shared by its servicers.

    A logging record per call costs more than a whole Blend, so lines are queued and handed to
    logging in batches (:meth:`flush`, every 0.25 s while serving, and at 1024 lines). The event
    loop is single-threaded: the queue and the count of open calls need no lock.

    At shutdown the server waits for the open calls (:meth:`settled`); once the grace period is
    over it sets ``cut``: a stream that then ends "OK" ended because gRPC cancelled it (a cancelled
    stream reads as a stream the client closed), and is recorded as CANCELLED, as its client saw."""

    def __init__(self, metrics=None, workers: int = limits.DEFAULT.workers,
                 recorder=record.NULL, peers: Peers | None = None):
        self.metrics = metrics
        # every stream's slot (dqpose.rpc.peers: per peer, world and server)
        self.peers = peers if peers is not None else Peers()
        # where the servicers record their calls (dqpose.record: ``recorder.call(...)``)
        self.recorder = recorder
        self.workers = workers
        self._pool: ThreadPoolExecutor | None = None
        self._trim_due = False
        self.logging = call_log.isEnabledFor(logging.INFO)
        self.cut = False
        self._pending: list[str] = []
        self._open = 0
        self._settled: asyncio.Event | None = None

    async def work(self, fn, *args):
        """``fn(*args)`` in the server's worker pool (``workers`` threads shared by every
        servicer), so that the event loop goes on answering other calls, health and signals;
        once the pool has been idle for ``TRIM_DELAY`` what the process freed is given back to
        the system (:func:`_trim_if_idle`)."""
        if self._pool is None:
            self._pool = ThreadPoolExecutor(self.workers, thread_name_prefix="dqpose-work")
        loop = asyncio.get_running_loop()
        try:
            return await loop.run_in_executor(self._pool, functools.partial(_counted, fn), *args)
        finally:
            if _MALLOC_TRIM is not None and not _active and not self._trim_due:
                self._trim_due = True
                loop.call_later(TRIM_DELAY, self._trim)

    def _trim(self) -> None:
        self._trim_due = False
        if self._pool is not None and not _active:
            self._pool.submit(_trim_if_idle)

    def close(self) -> None:
        """Lets the worker pool's threads end once their work is done."""
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None

    @property
    def open(self) -> int:
        """Calls begun and not yet done."""
        return self._open

    def cut_off(self, e: BaseException) -> bool:
        """Whether a stream's handler raising ``e`` was cut by the server's stop (its grace period
        over: gRPC's reader raises its private ``_ServerStoppedError``), not failed: CANCELLED,
        as its client saw, and nothing to log as an error."""
        return self.cut or type(e).__name__ == "_ServerStoppedError"

    def failure_code(self, e: BaseException) -> str:
        """The code a stream's call ends with when its handler raised ``e`` (not an abort):
        CANCELLED when the server's stop cut it (see :meth:`cut_off`), else INTERNAL."""
        return "CANCELLED" if self.cut_off(e) else "INTERNAL"

    async def failed(self, rpc: str, e: Exception, context) -> NoReturn:
        """Ends a stream whose handler raised ``e`` (not an abort): cut by the server's stop it
        goes on as it is (CANCELLED, as its client saw, no error logged); anything else is
        logged with its traceback and the call aborted INTERNAL without the exception's text."""
        if self.cut_off(e):
            raise e
        log.exception("%s failed", rpc)
        await context.abort(grpc.StatusCode.INTERNAL, INTERNAL_DETAILS)
        raise AssertionError("unreachable: abort raises")

    def begin(self) -> float:
        """Counts a call in; returns its start time, for :meth:`done`."""
        self._open += 1
        return time.perf_counter()

    def done(self, rpc: str, code: str, t0: float, context, messages: int | None = None,
             world: str | None = None) -> None:
        """The call's record; ``world``: the world a World call named, in its log line."""
        dt = time.perf_counter() - t0
        self._open -= 1
        if self.cut and code == "OK":
            code = "CANCELLED"
        if self.metrics is not None:
            self.metrics.observe(rpc, code, dt)
        if self.logging:
            # Hand-built JSON: the values are our own names, numbers and an address (quoted
            # through json).
            extra = "" if messages is None else f', "messages": {messages}'
            if world is not None:
                extra += f', "world": {json.dumps(world)}'
            self._pending.append(
                f'{{"t": {time.time():.6f}, "rpc": "{rpc}", "code": "{code}", '
                f'"ms": {dt * 1e3:.3f}, "peer": {json.dumps(context.peer())}{extra}}}')
            if len(self._pending) >= 1024:  # bounded even where nothing flushes periodically
                self.flush()
        if self._open == 0 and self._settled is not None:
            self._settled.set()

    async def settled(self, timeout: float) -> bool:
        """Waits up to ``timeout`` s for every open call to be done; whether they all were."""
        if self._open == 0:
            return True
        self._settled = asyncio.Event()
        try:
            await asyncio.wait_for(self._settled.wait(), timeout)
            return True
        except asyncio.TimeoutError:
            return False
        finally:
            self._settled = None

    def flush(self) -> None:
        """Hands the queued lines to the ``dqpose.calls`` logger as one record."""
        if self._pending:
            lines = "\n".join(self._pending)
            self._pending.clear()
            call_log.info(lines)

    async def flush_periodically(self, period: float) -> None:
        while True:
            await asyncio.sleep(period)
            self.flush()

    async def unary(self, rpc: str, handle, request, context, counted: bool = False,
                    status=None, world: str | None = None, recording=None):
        """One unary call: the response of ``handle(request)`` (awaited when it is a coroutine),
        the :func:`refusal` status for a FieldError or TooLarge, INTERNAL (logged) for anything
        else, and one record either way.
        With ``counted``, ``handle`` returns ``(response, messages)`` and the record counts them.
        ``status(rpc, e)``: a service's own mapping of exceptions (default :func:`refused`).
        ``world``: the world a World call named, in its record's log line. ``recording``: the
        call's (``recorder.call(...)``), which gets its request, its answer and its end."""
        rec = record.NULL_CALL if recording is None else recording
        rec.request(request)
        t0 = self.begin()
        code, details = "OK", ""
        ended = "CANCELLED"     # the recording's end unless it was answered or refused
        messages = None
        try:
            response = handle(request)
            if asyncio.iscoroutine(response):      # work handed to a thread
                response = await response
            if counted:
                response, messages = response
            rec.answer(response)
            ended = "OK"
            return response
        except Exception as e:
            code_, details = (status or refused)(rpc, e)
            code = ended = code_.name
            await context.abort(code_, details)
        finally:
            rec.end(ended, details)
            self.done(rpc, code, t0, context, messages, world)

    @contextlib.asynccontextmanager
    async def stream(self, rpc: str, context, recording=None, world: str | None = None,
                     log_name: str | None = None) -> AsyncIterator[Call]:
        """One streaming call, ``async with calls.stream(rpc, context, rec) as call:``: counted
        in (:meth:`begin`), ended with the status the handler set on ``call`` (:class:`Call`),
        CANCELLED when the client went away, INTERNAL (logged as ``log_name``, default ``rpc``,
        see :meth:`failed`) for an exception; then ``call``'s cleanups run (last first), its
        ``recording`` ends with its status and the call gets its one :meth:`done`."""
        call = Call(self, rpc, context, record.NULL_CALL if recording is None else recording)
        t0 = self.begin()
        try:
            yield call
        except grpc.aio.AbortError:
            raise
        except Exception as e:
            call.code = self.failure_code(e)
            await self.failed(log_name or rpc, e, context)
        except BaseException:   # asyncio.CancelledError: the client went away
            call.code = "CANCELLED"
            raise
        finally:
            try:
                for cleanup in reversed(call.cleanups):
                    if asyncio.iscoroutine(done := cleanup()):
                        await done
                if call.recorded_here:
                    call.end_recording()
            finally:
                self.done(rpc, call.code, t0, context, messages=call.messages, world=world)

    def open_stream(self, rpc: str, context, kind: str = STREAM,
                    world: str | None = None) -> Slot | None:
        """A stream's slot (:mod:`dqpose.rpc.peers`: its peer's, its world's, the server's);
        None when a bound is reached: the call's status is then RESOURCE_EXHAUSTED naming it,
        for the handler to return with at once, before it has allocated anything."""
        try:
            return self.peers.open(rpc, context, kind, world)
        except OverLimit as e:
            context.set_code(grpc.StatusCode.RESOURCE_EXHAUSTED)
            context.set_details(str(e))
            return None

    async def refuse(self, rpc: str, context, status: grpc.StatusCode, details: str) -> None:
        """A call refused before its handler runs (shutting down, no token): recorded too."""
        t0 = self.begin()
        try:
            await context.abort(status, details)
        finally:
            self.done(rpc, status.name, t0, context)


class Call:
    """What a streaming call's handler tells :meth:`Calls.stream`: the status it ends with
    (``code``, "OK" unless set, and a refusal's ``details``), its ``messages`` (its log line's
    count), the cleanups to run when it ends (:meth:`on_end`); ``rec``: its recording."""

    __slots__ = ("calls", "rpc", "context", "rec", "code", "details", "messages", "cleanups",
                 "recorded_here")

    def __init__(self, calls: Calls, rpc: str, context, rec):
        self.calls, self.rpc, self.context, self.rec = calls, rpc, context, rec
        self.code, self.details, self.messages = "OK", "", 0
        self.cleanups: list[Callable] = []
        self.recorded_here = True

    def open(self, kind: str = STREAM, world: str | None = None) -> Slot | None:
        """The stream's slot (:meth:`Calls.open_stream`); None when a bound is reached, the call
        then set to end RESOURCE_EXHAUSTED naming it, for the handler to return at once."""
        slot = self.calls.open_stream(self.rpc, self.context, kind, world)
        if slot is None:
            self.code, self.details = "RESOURCE_EXHAUSTED", self.context.details() or ""
        return slot

    def on_end(self, cleanup: Callable) -> None:
        """``cleanup()`` (awaited when it returns a coroutine) when the call ends, before its
        recording does; cleanups run last first."""
        self.cleanups.append(cleanup)

    async def refuse(self, status: grpc.StatusCode, details: str) -> NoReturn:
        """Ends the call with ``status`` and ``details`` (an abort: raises)."""
        self.code, self.details = status.name, details
        await self.context.abort(status, details)
        raise AssertionError("unreachable: abort raises")

    def set(self, status: grpc.StatusCode, details: str) -> None:
        """The status the call ends with when its handler returns (not raising)."""
        self.code, self.details = status.name, details
        self.context.set_code(status)
        self.context.set_details(details)

    def end_recording(self) -> None:
        """The recording's end, with the call's status as it is now."""
        self.rec.end(self.code, self.details)

    def handed_over(self) -> Callable[[], None]:
        """The recording's end handed to the caller, who calls what this returns where the end
        belongs (a world's order); the stream no longer ends it."""
        self.recorded_here = False
        return self.end_recording


def _libc():
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return libc.malloc_trim if hasattr(libc, "malloc_trim") else None
    except OSError:
        return None


_MALLOC_TRIM = _libc()


def _counted(fn, *args):
    """``fn(*args)``, counted in ``_active`` while it runs."""
    global _active
    with _lock:
        _active += 1
    try:
        return fn(*args)
    finally:
        with _lock:
            _active -= 1


def _trim_if_idle() -> None:
    """What the process freed given back to the system (malloc_trim), when no job runs: glibc
    keeps what its arenas freed (the probe's large requests left RSS at 6-7 GB). Microseconds
    when there is nothing to give back."""
    with _lock:
        if not _active:
            # a refused call's gRPC state (its received message with it) is in a reference
            # cycle with the AbortError that ended it, freed by a collection only (60 refused
            # 3.6 MB Fuse requests: 144 -> 67 MB); ~2 ms once dqpose serve has frozen the
            # server's own objects (gc.freeze), ~30 ms of the interpreter lock without
            gc.collect()
            _MALLOC_TRIM(0)


_lock = threading.Lock()
_active = 0          # jobs running in any server's pool
# seconds after the pool fell idle that the heap is looked at: by then the calls' requests and
# answers, which gRPC holds until they are sent, are freed too
TRIM_DELAY = 0.5
