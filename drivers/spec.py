"""The arm spec, one grammar for every arm: ``KIND:TARGET[?key=value&key=value...]``.

``ur:192.168.1.10?stale_after=0.3&max_tracking=0.005``, ``piper:socketcan:can0?watchdog=0.2``.
``KIND`` picks the backend (``drivers.ARMS``), ``TARGET`` is the backend's channel (a UR's host;
a PiPER's ``<python-can interface>:<channel>``), and the query sets the keys of
:data:`ARM_KEYS`, the one table of what can be set per arm: the same keys for every kind (a kind
may have its own default), each a positive number in the unit the table states. The keys become
the backend's keyword arguments (:func:`drivers.open_arm`); the ones every arm shares are kept on
the arm as attributes of the same name (``arm.stale_after``, ``arm.max_tracking``, ...).
"""
from __future__ import annotations

import difflib
import importlib
import math
import numbers
from dataclasses import dataclass, field
from typing import Optional

from dqpose.drivers.backends import ARMS, split_backend

__all__ = ["ArmKey", "ARM_KEYS", "ArmSpec", "parse_arm_spec", "key_table", "resolve", "arm_class",
           "open_here"]

GRAMMAR = "KIND:TARGET[?key=value&key=value...]"


@dataclass(frozen=True)
class ArmKey:
    """One settable key: ``defaults`` by arm kind (``"*"``: every kind without its own)."""
    name: str
    unit: str
    help: str
    defaults: dict

    def default_for(self, kind: Optional[str]) -> float:
        return self.defaults.get(kind, self.defaults.get("*"))

    def check(self, value) -> float:
        """``value`` as a float, else ``ValueError`` naming the key and the value."""
        if isinstance(value, bool) or not (isinstance(value, numbers.Real)
                                           and math.isfinite(value) and value > 0):
            raise ValueError(f"{self.name}: must be a positive number of {self.unit}, got "
                             f"{value!r}")
        return float(value)

    def parse(self, text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise ValueError(f"{self.name}: {text!r} is not a number ({self.unit})") from None
        return self.check(value)

    def describe(self) -> str:
        """``name (unit, default ...): help``, the line ``serve --help`` prints."""
        kinds = sorted(k for k in self.defaults if k != "*")
        if "*" in self.defaults and not kinds:
            default = f"{self.defaults['*']:g}"
        else:
            default = ", ".join(f"{k} {self.defaults[k]:g}" for k in kinds)
        return f"{self.name} ({self.unit}, default {default}): {self.help}"


ARM_KEYS: dict[str, ArmKey] = {k.name: k for k in (
    ArmKey("stale_after", "s", "feedback (pose, status) older than this is a fault: the run "
           "under way ends ERROR, and the fault clears once data flows again (a PiPER's "
           "default is at least 3 periods of its feedback, as measured, and at most 1 s)",
           {"ur": 0.1, "piper": 0.35}),
    ArmKey("watchdog", "s", "servo set-points may pause this long before the driver holds the "
           "arm", {"ur": 0.05, "piper": 0.1}),
    ArmKey("max_tracking", "m", "a set-point farther than this from the arm's actual tool "
           "position (against the set-points of the last tracking_lag) stops the run: TRACKING",
           {"*": 0.005}),
    ArmKey("max_tracking_angle", "rad", "the same for the tool's rotation", {"*": 0.05}),
    ArmKey("tracking_lag", "s", "how far behind its set-points the arm may follow: tracking is "
           "measured against every set-point sent this long before the reading", {"*": 0.05}),
    ArmKey("heartbeat", "s", "a running plan's owner beats this often (Executor.beat); three "
           "missed beats bring the arm to a controlled stop: STALLED (0.3 s by default: a "
           "server's event loop on a loaded machine pauses 0.1 s, and the plan it leaves "
           "running is already checked against the Limits)", {"*": 0.1}),
    ArmKey("connect_timeout", "s", "how long opening waits for the arm to answer and for its "
           "first state", {"*": 2.0}),
)}


def resolve(kind: str, given: dict) -> dict:
    """Every key of :data:`ARM_KEYS` for an arm of ``kind``: the ``given`` values checked, the
    kind's defaults for the rest (a given None is the default); ``ValueError`` for a name that
    is not a key."""
    for name in given:
        if name not in ARM_KEYS:
            raise ValueError(f"{name}: unknown arm key (did you mean {_nearest(name)!r}?); "
                             f"known: {', '.join(ARM_KEYS)}")
    out = {}
    for name, key in ARM_KEYS.items():
        v = given.get(name)
        out[name] = key.default_for(kind) if v is None else key.check(v)
    return out


def key_table() -> str:
    """The keys, one line each, for help texts."""
    return "\n".join(k.describe() for k in ARM_KEYS.values())


@dataclass(frozen=True)
class ArmSpec:
    kind: str
    target: str
    options: dict = field(default_factory=dict)

    @property
    def channel(self) -> str:
        """``KIND:TARGET`` without the options (what a backend's ``open`` is named by)."""
        return f"{self.kind}:{self.target}"

    def __str__(self) -> str:
        query = "&".join(f"{k}={v:g}" for k, v in self.options.items())
        return self.channel + (f"?{query}" if query else "")


def _nearest(name: str) -> str:
    return difflib.get_close_matches(name, ARM_KEYS, n=1, cutoff=0.0)[0]


def parse_arm_spec(text: str) -> ArmSpec:
    """``KIND:TARGET[?key=value&...]`` to an :class:`ArmSpec`; ``ValueError`` for an unknown kind
    or key (naming the nearest known key) or a bad value (naming the key and the value)."""
    if not isinstance(text, str):
        raise ValueError(f"arm: expected '{GRAMMAR}', got {text!r}")
    body, question, query = text.partition("?")
    kind, target = split_backend("arm", ARMS, body, text, GRAMMAR)
    options: dict = {}
    if question:
        if not query:
            raise ValueError(f"arm: {text!r} ends in '?' without key=value")
        for part in query.split("&"):
            name, eq, value = part.partition("=")
            if not eq or not name or not value:
                raise ValueError(f"arm: {part!r} in {text!r} is not key=value")
            if name not in ARM_KEYS:
                raise ValueError(f"{name}: unknown arm key in {text!r} (did you mean "
                                 f"{_nearest(name)!r}?); known: {', '.join(ARM_KEYS)}")
            if name in options:
                raise ValueError(f"{name}: given twice in {text!r}")
            options[name] = ARM_KEYS[name].parse(value)
    return ArmSpec(kind, target, options)


def arm_class(spec: ArmSpec):
    """The backend class of ``spec``'s kind (its module imported now)."""
    module, cls = ARMS[spec.kind].split(":")
    return getattr(importlib.import_module(module), cls)


def open_here(spec, **kwargs):
    """The arm of ``spec`` (an :class:`ArmSpec` or its text) opened in this process: its
    backend's ``open(target, **keys)``, the spec's keys and ``kwargs`` (which win)."""
    s = spec if isinstance(spec, ArmSpec) else parse_arm_spec(spec)
    return arm_class(s).open(s.target, **{**s.options, **kwargs})
