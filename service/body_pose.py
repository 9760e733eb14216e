"""What a world answers of a body: :class:`BodyPose`, and :func:`body_name`, the check of a body's
name a world's calls share. Below :mod:`dqpose.world` and the modules it is made of
(:mod:`dqpose.frames`, :mod:`dqpose.lookup`, :mod:`dqpose.two_times`), which answer with it."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from dqpose.errors import WorldError
from dqpose.fusion.results import Fused
from dqpose.names import name_problem


@dataclass(frozen=True)
class BodyPose:
    """A pose at ``time``: ``pose`` ``(8,)`` (``T_world_body``, or ``T_target_source``),
    ``covariance`` ``(6, 6)`` in the convention of :mod:`dqpose.fusion`; ``fused`` the full
    fusion result when the answer is one body's own fit, ``None`` for a composed pose."""
    body: str
    time: float
    pose: np.ndarray
    covariance: np.ndarray
    fused: Optional[Fused]


def body_name(body, field: str = "body") -> str:
    """``body`` when it is a body's name or "" (the world frame), else a ``WorldError`` naming
    ``field``."""
    problem = name_problem(body, empty=True)
    if problem is not None:
        raise WorldError(None, field, problem)
    return body
