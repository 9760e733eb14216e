"""When a body's time may leap: a :class:`~dqpose.fusion.Tracker`'s measurements taken more than
``max_time_jump`` after their body's newest wait here for a second one to confirm them, and who
may confirm.

Rows may name their origin (a World's producer; None: a stream, its bodies' one producer). A
jump of one origin is confirmed by another origin's measurement near it, or by its own while no
other origin fed the body within ``max_time_jump`` of its newest (a body seen again after a
pause by the one camera that sees it): one producer's clock never takes a body away from the
others feeding it.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np


class Jumps:
    """Per body code: its last refused jump (time taken, origin) and the two origins that fed
    it last, each with its newest time taken (enough to find whether any origin but one fed it
    lately). ``jump``: the limit's seconds."""

    def __init__(self, jump: float):
        self.jump = jump
        self._pending: dict[int, tuple[float, Any]] = {}
        self._feeders: dict[int, list[tuple[Any, float]]] = {}

    def fed(self, origin, body: np.ndarray, taken: np.ndarray) -> None:
        """``origin`` fed the bodies ``body`` (codes) measurements taken at ``taken``."""
        # each body's newest of the call by plain look-ups: a request holds few rows a body,
        # and the bodies are independent here (np.unique cost more than the rest of a step)
        newest: dict[int, float] = {}
        for b, t in zip(body.tolist(), taken.tolist()):
            if not t <= newest.get(b, -math.inf):
                newest[b] = t
        feeders = self._feeders
        for b, t in newest.items():
            had = feeders.get(b)
            if had is None:
                feeders[b] = [(origin, t)]
                continue
            others = []
            for o, u in had:
                if o != origin:
                    others.append((o, u))
                elif u > t:
                    t = u
            others.append((origin, t))
            feeders[b] = sorted(others, key=lambda x: -x[1])[:2]

    def alone(self, b: int, origin, newest: float) -> bool:
        """Whether a jump of ``origin`` needs no other origin to confirm it: a stream's (None),
        or no other origin fed body ``b`` within the limit of its ``newest``."""
        floor = newest - self.jump
        return origin is None or not any(o != origin and u >= floor
                                         for o, u in self._feeders.get(b, ()))

    def confirms(self, b: int, t: float, origin, newest: float) -> bool:
        """Whether a row of ``origin`` taken at ``t`` confirms body ``b``'s pending jump (then
        forgotten: the body moves on); else it is the body's pending jump now."""
        pending = self._pending.get(b)
        if pending is not None and abs(t - pending[0]) <= self.jump and (
                origin is None or origin != pending[1] or self.alone(b, origin, newest)):
            del self._pending[b]
            return True
        self._pending[b] = (t, origin)
        return False

    def forget(self, b: int) -> None:
        self._pending.pop(b, None)
        self._feeders.pop(b, None)
