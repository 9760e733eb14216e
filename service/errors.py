"""Errors named after the caller's fields.

The core names its own arguments (``q[3]: zero quaternion``); a layer that knows where ``q[3]``
came from (a proto field, a file's key) renames it with :func:`rename`.
"""
from __future__ import annotations

import re

_INDEXED = re.compile(r"^(\w+)(\[\d+\])?(.*)$", re.S)


class FieldError(ValueError):
    """Invalid input, with a message that starts with the caller's field path."""


class Infeasible(ValueError):
    """Well-formed input whose demands cannot be met (waypoint times too short for the limits, a
    path the limits cannot follow): gRPC's ``FAILED_PRECONDITION`` rather than
    ``INVALID_ARGUMENT``. The message starts with the argument it is about, like any ValueError."""


class FieldInfeasible(FieldError, Infeasible):
    """An :class:`Infeasible` renamed to the caller's field path."""


def rename(err: ValueError, names: dict[str, str]) -> FieldError:
    """``"q[3]: x"`` with ``{"q": "poses{}.orientation"}`` -> ``"poses[3].orientation: x"``.

    ``{}`` in a target marks where the core's index goes; an unknown name is kept as it is.
    """
    msg = str(err)
    m = _INDEXED.match(msg)
    if m and m.group(1) in names:
        msg = names[m.group(1)].replace("{}", m.group(2) or "") + m.group(3)
    return _same_kind(err, msg)


def rename_all(err: ValueError, names: dict[str, str]) -> FieldError:
    """:func:`rename` of every one of ``names`` wherever the message has it, not only the first
    word: for messages about several arguments (``"a, b[2]: ..."``) or naming one in their
    text."""
    pattern = re.compile(r"\b(" + "|".join(map(re.escape, names)) + r")\b(\[\d+\])?")
    msg = pattern.sub(lambda m: names[m.group(1)].replace("{}", m.group(2) or ""), str(err))
    return _same_kind(err, msg)


def _same_kind(err: ValueError, msg: str) -> FieldError:
    return FieldInfeasible(msg) if isinstance(err, Infeasible) else FieldError(msg)
