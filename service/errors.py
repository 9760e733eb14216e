"""Errors named after the caller's fields, and the one error for a missing optional dependency.

A domain check raises a :class:`FieldError` as data: the argument it is about (``q``), the
element (``3``), the path below it and the problem; its text ``q[3]: zero quaternion``. A layer
that knows where ``q[3]`` came from (a proto field, a file's key) renames it with :func:`rename`,
reading those fields, not the text. What needs a module of an extra that is not installed raises
:class:`MissingExtra` (:func:`require`), whose text says how to install it.
"""
from __future__ import annotations

import re

# A path as the domain writes it, ``name[i].rest``. Read only where no field was given as data:
# the C core's messages (service/csrc, through dqpose._dqcore, ``name[i]: problem``), the
# messages of modules that still write their path into their text (``FieldError(message)``:
# trajectory, lie, interpolate, smoothing, handeye) and a world's call-level paths
# (``WorldError.field`` "options.window", "sources[2]": :meth:`FieldError.of`).
_PATH = re.compile(r"^(\w+)(?:\[(\d+)\])?(.*)$", re.S)


class FieldError(ValueError):
    """Invalid input as data: ``field`` the argument or field path it is about
    (``"covariances"``; ``""`` none), ``index`` its element (None: the whole), ``tail`` the path
    below that element (``".latency"``), ``text`` the problem. Its message is
    ``field[index]tail: text`` (``text`` alone without a path). ``FieldError(message)`` alone:
    a message whose path is written in it (not :attr:`given`)."""

    def __init__(self, field: str, text: str | None = None, index: int | None = None,
                 tail: str = ""):
        self.given = text is not None       # the fields given as data
        if text is None:
            field, text = "", field
        self.field, self.text, self.index, self.tail = field, text, index, tail
        path = self.path()
        ValueError.__init__(self, f"{path}: {text}" if path else text)

    def path(self) -> str:
        """``field[index]tail``."""
        return self.field + ("" if self.index is None else f"[{self.index}]") + self.tail

    def within(self, field: str, index: int | None = None) -> "FieldError":
        """The same problem about ``field[index]``'s part this one names: ``sources[3].latency``
        of a source's ``latency``."""
        path = self.path()
        return _kind(self)(field, self.text, index, f".{path}" if path else "")

    @staticmethod
    def of(e: ValueError) -> "FieldError":
        """``e`` as data: itself when its fields were given, else read from its path (a
        :class:`WorldError`'s) or its message (``name[i]: problem``; any other text: no
        path)."""
        if isinstance(e, WorldError):
            path, text = e.path(), e.text
        elif isinstance(e, FieldError) and e.given:
            return e
        else:
            path, sep, text = str(e).partition(": ")
            if not sep:
                path, text = "", str(e)
        m = _PATH.match(path)
        if m is None:
            return _kind(e)(path, text)
        return _kind(e)(m[1], text, None if m[2] is None else int(m[2]), m[3])


class WorldError(FieldError):
    """Bad input to a world or a live stream (:mod:`dqpose.world`, :class:`dqpose.fusion.Tracker`)
    as data, so a transport names it without reading its text: ``index`` the row of the call it
    is about (None: the call itself, as a configuration's option), ``field`` the path below it
    (``"time"``; ``""`` the row itself), ``text`` the problem, ``limit`` the server's limit it is
    over (a :class:`dqpose.limits.Limits` field: RESOURCE_EXHAUSTED), ``about`` the row described
    (``"body 'box', source 'cam', time 1.5"``). Its message is :meth:`named` ``()``:
    ``measurements[3].time: ...``, ``options.window: ...``."""

    def __init__(self, index: int | None, field: str, text: str, limit: str | None = None,
                 about: str | None = None):
        self.index, self.field, self.text, self.limit, self.about = (
            index, field, text, limit, about)
        self.tail, self.given = "", True
        ValueError.__init__(self, self.named())

    def path(self, under: str = "", index: int | None = None) -> str:
        """The field's path below ``under``: ``under[index].field`` for a row's (``index``
        default its own, ``under`` default ``measurements``), ``under.field`` for the call's."""
        if self.index is None:
            return ".".join(part for part in (under, self.field) if part)
        i = self.index if index is None else index
        return f"{under or 'measurements'}[{i}]" + (f".{self.field}" if self.field else "")

    def named(self, under: str = "", index: int | None = None) -> str:
        """The message, its path :meth:`path` ``(under, index)``."""
        about = f" ({self.about})" if self.about else ""
        path = self.path(under, index)
        return f"{path}{about}: {self.text}" if path or about else self.text

    def _key(self) -> tuple:
        return (self.index, self.field, self.text, self.limit, self.about)

    def __eq__(self, other) -> bool:
        return isinstance(other, WorldError) and self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())

    def at(self, index: int) -> "WorldError":
        """The same error about row ``index`` of the caller's."""
        return WorldError(index, self.field, self.text, self.limit, self.about)

    @classmethod
    def of(cls, e: ValueError, index: int | None = None,
           field: str | dict[str, str] | None = None, under: str = "") -> "WorldError":
        """A domain check's error (a :class:`FieldError`, or the C core's, :meth:`FieldError.of`)
        as data about row ``index``'s ``field``: a dict maps the argument named to the field;
        None: the error's path itself, below ``under`` when given."""
        f = FieldError.of(e)
        named = f.path()
        if isinstance(field, dict):
            field = field.get(f.field, named)
        elif field is None:
            field = f"{under}.{named}" if under else named
        return cls(index, field, f.text)


class NotFound(LookupError):
    """An unknown body or arm."""


def seconds_text(t: float) -> str:
    """A time to the microsecond, without trailing zeros (Unix times keep their digits)."""
    return f"{t:.6f}".rstrip("0").rstrip(".")


def known_from(name: str, oldest: float, newest: float) -> str:
    """What an :class:`OutOfRange` names: the span a body (or frame) is known over."""
    return f"{name!r} is known from {seconds_text(oldest)} to {seconds_text(newest)}"


class OutOfRange(LookupError):
    """A time outside the buffer, or beyond ``max_extrapolation`` past what is known; the
    message names what is known."""


class NotYet(OutOfRange):
    """A time past the newest measurement beyond ``max_extrapolation``: measurements to come
    may answer it (a Lookup's ``wait`` waits for them)."""


class Infeasible(ValueError):
    """Well-formed input whose demands cannot be met (waypoint times too short for the limits, a
    path the limits cannot follow): gRPC's ``FAILED_PRECONDITION`` rather than
    ``INVALID_ARGUMENT``. The message starts with the argument it is about, like any ValueError."""


class FieldInfeasible(FieldError, Infeasible):
    """An :class:`Infeasible` renamed to the caller's field path."""


class WorldInfeasible(WorldError, Infeasible):
    """A world's refusal of well-formed input it cannot serve (FAILED_PRECONDITION): an arm
    whose source rides on a body."""


def rename(err: ValueError, names: dict[str, str]) -> FieldError:
    """``"q[3]: x"`` with ``{"q": "poses{}.orientation"}`` -> ``"poses[3].orientation: x"``, from
    the error's fields (:meth:`FieldError.of`).

    ``{}`` in a target marks where the index goes (without one, the index is left out); an
    unknown name is kept as it is.
    """
    e = FieldError.of(err)
    target = names.get(e.field) if e.field else None
    if target is None:
        return _kind(err)(e.field, e.text, e.index, e.tail)
    head, brace, rest = target.partition("{}")
    if brace:
        return _kind(err)(head, e.text, e.index, rest + e.tail)
    return _kind(err)(target, e.text, None, e.tail)


def rename_all(err: ValueError, names: dict[str, str]) -> FieldError:
    """:func:`rename` of every one of ``names`` wherever the message has it, not only the first
    word: for messages about several arguments (``"a, b[2]: ..."``) or naming one in their
    text."""
    pattern = re.compile(r"\b(" + "|".join(map(re.escape, names)) + r")\b(\[\d+\])?")
    msg = pattern.sub(lambda m: names[m.group(1)].replace("{}", m.group(2) or ""), str(err))
    return _same_kind(err, msg)


def _same_kind(err: ValueError, msg: str) -> FieldError:
    return _kind(err)(msg)


def _kind(err: ValueError) -> type[FieldError]:
    return FieldInfeasible if isinstance(err, Infeasible) else FieldError


# ---- optional dependencies -----------------------------------------------------------------------

#: The extra (pyproject.toml's optional-dependencies) that brings each module imported on demand;
#: tests/test_errors.py checks it against the installed distribution's metadata.
EXTRA_OF = {
    "scipy": "planning", "casadi": "planning",
    "matplotlib": "plot",
    "yaml": "yaml",
    "foxglove": "record", "mcap": "record", "foxglove_schemas_protobuf": "record",
    "rosbags": "record",
    "viser": "view", "websockets": "view",
    "cv2": "devices", "can": "devices", "rtde_control": "devices", "rtde_receive": "devices",
}


class MissingExtra(Exception):
    """What was asked needs a module of an extra that is not installed: gRPC's
    ``FAILED_PRECONDITION`` and the command line's exit 2, with :func:`install_hint`'s text (not a
    ValueError: the input is fine, the install is not)."""

    def __init__(self, extra: str, module: str):
        super().__init__(install_hint(extra))
        self.extra, self.module = extra, module


def install_hint(extra: str) -> str:
    """``install dqpose with the [EXTRA] extra: pip install 'SPEC[EXTRA]'``, SPEC as pip names this
    install: ``.`` when it was installed from the folder it runs in (a clone), that folder's path
    from elsewhere, ``dqpose`` for a wheel or an index (pip keeps the installed version and adds
    the extra's packages)."""
    return f"install dqpose with the [{extra}] extra: pip install '{_install_spec()}[{extra}]'"


def _install_spec() -> str:
    import json
    import os
    from importlib import metadata
    from urllib.parse import unquote, urlparse

    try:
        direct = metadata.distribution("dqpose").read_text("direct_url.json")
    except metadata.PackageNotFoundError:      # run from a source tree that was never installed
        return "."
    info = json.loads(direct) if direct else {}
    if "dir_info" not in info:
        return "dqpose"
    folder = unquote(urlparse(info["url"]).path)
    try:
        here = os.path.samefile(folder, os.getcwd())
    except OSError:
        here = False
    return "." if here else folder


def require(*modules: str) -> None:
    """Imports ``modules`` (names of :data:`EXTRA_OF`), or raises :class:`MissingExtra` naming the
    extra of the first one missing."""
    import importlib

    for name in modules:
        try:
            importlib.import_module(name)
        except ModuleNotFoundError as e:
            raise missing(e) from None


def missing(e: ModuleNotFoundError) -> Exception:
    """``e`` as :class:`MissingExtra` when the module it misses is one of an extra, else ``e``
    itself (a broken install is not a missing extra)."""
    top = (e.name or "").split(".")[0]
    return MissingExtra(EXTRA_OF[top], top) if top in EXTRA_OF else e
