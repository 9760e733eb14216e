"""What every servicer shares: one call in, one status out, one log line and one metric sample.

A handler raises :class:`~service.errors.FieldError` for bad input (``INVALID_ARGUMENT`` with its
text, which starts with the proto field path); anything else is ``INTERNAL``, logged with its
traceback, and the server keeps running.
"""
from __future__ import annotations

import asyncio
import json
import logging
import time

import grpc

from service.errors import FieldError

log = logging.getLogger("dqpose.server")
call_log = logging.getLogger("dqpose.calls")

INTERNAL_DETAILS = "internal error (see the server log)"


class Calls:
    """Records finished calls: a Prometheus sample (``metrics.observe``) and a JSON log line on
    ``dqpose.calls``. One per server, shared by its servicers.

    A logging record per call costs more than a whole Blend, so lines are queued and handed to
    logging in batches (:meth:`flush`, every 0.25 s while serving, and at 1024 lines). The event
    loop is single-threaded: the queue needs no lock."""

    def __init__(self, metrics=None):
        self.metrics = metrics
        self.logging = call_log.isEnabledFor(logging.INFO)
        self._pending: list[str] = []

    def done(self, rpc: str, code: str, t0: float, context, messages: int | None = None) -> None:
        dt = time.perf_counter() - t0
        if self.metrics is not None:
            self.metrics.observe(rpc, code, dt)
        if self.logging:
            # Hand-built JSON: the values are our own names, numbers and an address (quoted
            # through json).
            extra = "" if messages is None else f', "messages": {messages}'
            self._pending.append(
                f'{{"t": {time.time():.6f}, "rpc": "{rpc}", "code": "{code}", '
                f'"ms": {dt * 1e3:.3f}, "peer": {json.dumps(context.peer())}{extra}}}')
            if len(self._pending) >= 1024:  # bounded even where nothing flushes periodically
                self.flush()

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

    async def unary(self, rpc: str, handle, request, context, counted: bool = False):
        """One unary call: the response of ``handle(request)``, INVALID_ARGUMENT for a FieldError,
        INTERNAL (logged) for anything else, and one record either way. With ``counted``,
        ``handle`` returns ``(response, messages)`` and the record counts them."""
        t0 = time.perf_counter()
        code = "OK"
        messages = None
        try:
            response = handle(request)
            if counted:
                response, messages = response
            return response
        except FieldError as e:
            code = "INVALID_ARGUMENT"
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(e))
        except Exception:
            code = "INTERNAL"
            log.exception("%s failed", rpc)
            await context.abort(grpc.StatusCode.INTERNAL, INTERNAL_DETAILS)
        finally:
            self.done(rpc, code, t0, context, messages)
