"""The names a client gives (bodies, sources, producers, arms, frames): the one rule every name
obeys, and how an error quotes a name.

A name is 1 to :data:`MAX_NAME_BYTES` bytes of UTF-8 without control characters and without
``/``: it is kept per body and per producer (a world holds thousands), quoted in errors and
metadata, and becomes part of a recording's topics (``/fused/<body>`` and ``/fused/<body>/stats``
would be one topic for bodies ``a`` and ``a/stats``). An error quotes a name through
:func:`quoted`, at most :data:`QUOTE_CHARS` characters of it, so that no refusal grows with what a
client sent.
"""
from __future__ import annotations

import re
from typing import Optional

from dqpose.errors import FieldError

#: bytes of UTF-8 a name may have
MAX_NAME_BYTES = 128
#: characters of a name an error quotes (then "...")
QUOTE_CHARS = 64
# control characters (Unicode's Cc: C0, DEL, C1) and the topic separator
_FORBIDDEN = re.compile(r"[\x00-\x1f\x7f-\x9f/]")


def quoted(name: str) -> str:
    """``repr(name)`` of at most :data:`QUOTE_CHARS` characters of it (then ``...``)."""
    return repr(name[:QUOTE_CHARS]) + "..." if len(name) > QUOTE_CHARS else repr(name)


def name_problem(name: object, empty: bool = False) -> Optional[str]:
    """What is wrong with ``name`` as a name (``empty``: "" is allowed too, as a source's "" is
    the world frame), or None."""
    if not isinstance(name, str):
        return f"expected a string, got {type(name).__name__}"
    if not name:
        return None if empty else f"empty (a name has 1 to {MAX_NAME_BYTES} bytes)"
    if len(name) > MAX_NAME_BYTES:      # a character is one byte of UTF-8 or more
        return (f"{quoted(name)} has {len(name)} characters, over the {MAX_NAME_BYTES} bytes "
                f"of UTF-8 a name may have")
    try:
        size = len(name.encode())
    except UnicodeEncodeError:
        return f"{quoted(name)} is not valid UTF-8"
    if size > MAX_NAME_BYTES:
        return (f"{quoted(name)} has {size} bytes of UTF-8, over the {MAX_NAME_BYTES} a name "
                f"may have")
    bad = _FORBIDDEN.search(name)
    if bad:
        what = "'/'" if bad[0] == "/" else f"the control character U+{ord(bad[0]):04X}"
        return f"{quoted(name)} has {what} at {bad.start()} (a name has none)"
    return None


def check_name(name: object, field: str, empty: bool = False) -> str:
    """``name`` when it is a name (:func:`name_problem`), else a FieldError naming ``field``."""
    problem = name_problem(name, empty)
    if problem is not None:
        raise FieldError(field, problem)
    return name      # type: ignore[return-value]   # a str: name_problem said so


def bad_names(names, empty: bool = False) -> set:
    """The distinct ``names`` (strings) that are not names: each name checked once, however many
    rows repeat it."""
    return {n for n in set(names) if name_problem(n, empty) is not None}
