"""The shared world: named bodies fed by many producers, each body's pose at any time within the
buffer, the pose of any body relative to any other, and an arm's base, all with covariances.

A :class:`World` holds one :class:`dqpose.fusion.Tracker` whose window is the ``buffer`` (the
history kept for lookups at past times); a body's pose at a time is :func:`dqpose.fusion.fuse`
over the measurements taken within ``window`` of that time (the tracker's rows, so the answer is
``fuse``'s to the last bit). Producers call :meth:`World.publish` from any thread (one lock).

Correlations: two bodies measured by the same source share its extrinsic error ``ε`` (the
source's ``extrinsic_covariance``). :meth:`World.relative` fits both bodies jointly, with one ``ε``
per source, so the relative pose's covariance carries their cross-covariance. Not modelled: a
latency error two bodies share (each body's fit estimates a source's latency on its own), errors
of a source's ``body_offset``, and correlations between measurement noises of one image.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Optional, Sequence

import numpy as np

from dqpose import limits as _limits
from dqpose.fusion import (
    DEFAULT_MAX_EXTRAPOLATION,
    DEFAULT_PROBABILITY,
    Fused,
    Measurement,
    Source,
)

__all__ = ["WorldOptions", "WorldBounds", "WorldError", "NotFound", "OutOfRange", "Published",
           "BodyPose", "World", "Measurement", "Source", "Fused"]


@dataclass(frozen=True)
class WorldOptions:
    """What the world's fusion runs with besides its sources and arms (the options of
    :func:`dqpose.fusion.fuse`), and how much time it keeps: ``window`` seconds of measurements
    in one body's fit, ``buffer`` seconds of history for lookups at past times, ``max_delay``
    seconds of measurement time a tick waits for slower sources."""
    robust: bool = False
    probability: float = DEFAULT_PROBABILITY
    max_skew: Optional[float] = None
    max_extrapolation: Optional[float] = DEFAULT_MAX_EXTRAPOLATION
    twist_covariance: Optional[np.ndarray] = None
    acceleration_psd: Optional[np.ndarray] = None
    window: float = 1.0
    buffer: float = 10.0
    max_delay: float = 0.1


@dataclass(frozen=True)
class WorldBounds:
    """What a world holds at most; a refusal names the bound ("bodies: 1001 is above the
    world's 1000"). ``max_measurements_per_body``: measurements a body's buffer keeps (the
    server's ``Limits.max_window`` when the world has limits)."""
    max_bodies: int = 1000
    max_sources: int = 64
    max_measurements_per_body: int = _limits.Limits().max_window
    max_buffer: float = 60.0


class WorldError(ValueError):
    """Bad input: the message starts with the field path."""


class NotFound(LookupError):
    """An unknown body or arm."""


class OutOfRange(LookupError):
    """A time outside the buffer, or beyond ``max_extrapolation`` past what is known; the
    message names what is known."""


@dataclass(frozen=True)
class Published:
    """What one :meth:`World.publish` did: ``accepted`` measurements fused into the world,
    ``errors`` ``(index in the request's measurements, message)`` of the others, the
    ``bodies`` the request touched."""
    accepted: int
    errors: tuple[tuple[int, str], ...]
    bodies: tuple[str, ...]


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


class World:
    """Named bodies and sources; see the module's docstring."""

    def __init__(self, *, sources: Sequence[Source] = (), arms: Mapping[str, str] = {},
                 options: WorldOptions = WorldOptions(), bounds: WorldBounds = WorldBounds(),
                 limits: Optional[_limits.Limits] = None):
        raise NotImplementedError

    def configure(self, *, sources: Sequence[Source], arms: Mapping[str, str],
                  options: WorldOptions) -> None:
        """Replace the sources, arms and options; the measurements kept that still fit stay."""
        raise NotImplementedError

    @property
    def bodies(self) -> tuple[str, ...]:
        raise NotImplementedError

    def publish(self, measurements: Sequence[Measurement]) -> Published:
        """Add measurements (thread-safe); a bad one is answered in ``errors``, never raised."""
        raise NotImplementedError

    def sources_of(self, body: str) -> tuple[str, ...]:
        """The sources that ever fed ``body``."""
        raise NotImplementedError

    def newest(self, body: str, source: Optional[str] = None) -> float:
        """When ``body``'s newest measurement (of ``source``) was taken."""
        raise NotImplementedError

    def pose(self, body: str, time: Optional[float] = None) -> BodyPose:
        """``T_world_body`` at ``time`` (None: the body's newest)."""
        raise NotImplementedError

    def relative(self, target: str, source: str, time: float = 0.0) -> BodyPose:
        """``T_target_source`` at ``time`` (0: the newest time both are known at); "" is the
        world frame."""
        raise NotImplementedError

    def arm_base(self, arm: str) -> BodyPose:
        """``T_world_base`` of ``arm``: the extrinsic of the source ``arms`` names."""
        raise NotImplementedError
