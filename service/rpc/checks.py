"""The request checks every service (and the client) shares: how many items a field may carry,
and errors named after the request's fields.

A count over the server's ``max_poses`` reads ``{field}: {n} {what} exceed the server limit of
{limit} per request`` wherever it is refused, on the server or, before sending, in the client.
"""
from __future__ import annotations

import re

from dqpose.errors import FieldError, rename


def over_count(field: str, n: int, limit: int, what: str = "") -> str | None:
    """The text refusing ``n`` items (``what``) of ``field`` over ``limit``; None within it."""
    if n <= limit:
        return None
    counted = f"{n} {what}" if what else f"{n}"
    return f"{field}: {counted} exceed the server limit of {limit} per request"


def check_count(field: str, n: int, limit: int, what: str = "", *, empty: bool = False) -> None:
    """A :class:`FieldError` for ``n`` items of ``field`` over ``limit`` (the server's
    ``max_poses``), and with ``empty`` for none."""
    if empty and n == 0:
        raise FieldError(f"{field}: empty request: no {what}")
    text = over_count(field, n, limit, what)
    if text is not None:
        raise FieldError(text)


def field_named(e: ValueError, fields: tuple[str, ...], default: str) -> FieldError:
    """``e`` as a :class:`FieldError` (an Infeasible stays one) whose text starts with a field
    path of the request, one of ``fields`` (``pairs`` covers ``pairs[3].robot_covariance``):
    as it is when it does, else after ``default``: what NumPy, SciPy or casadi raised from
    inside the domain (``Singular matrix``) then says which input it was about."""
    out = rename(e, {})
    if re.match(r"^(%s)\b" % "|".join(map(re.escape, fields)), str(out)):
        return out
    return type(out)(f"{default}: {out}")
