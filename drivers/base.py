"""The two driver interfaces: ``PoseSource`` (cameras, trackers, arms reporting where they are)
and ``Arm`` (anything we command).

Like python-can's ``BusABC``, each backend is one module (``drivers.ur``, ``drivers.piper``,
``drivers.camera``) with a real implementation, and ``drivers.sim`` holds simulators that speak
the same protocol. Poses cross this boundary as unit dual quaternions, NumPy ``(8,)``, in the
project's convention (``[w, x, y, z, w', x', y', z']``, metres, seconds); a tool pose is
``T_base_tool``.
"""
from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import Iterator, Optional

import numpy as np


@dataclass(frozen=True)
class Measurement:
    """One pose measurement. ``covariance`` is 6x6 in the tangent space at ``pose`` (rotation
    first, radians then metres); when it is unknown, ``weight`` says how much to trust it."""
    source: str
    time: float
    pose: np.ndarray
    covariance: Optional[np.ndarray] = None
    weight: float = 1.0


class PoseSource(abc.ABC):
    """Anything that measures poses."""

    name: str = "source"

    @abc.abstractmethod
    def read(self, timeout: Optional[float] = None) -> Optional[Measurement]:
        """The next measurement, or None if there was none within ``timeout`` seconds or the
        view was rejected (see the backend for the reason)."""

    def __iter__(self) -> Iterator[Measurement]:
        while True:
            m = self.read()
            if m is None:
                return
            yield m

    def close(self) -> None:
        """Release the device."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass
class ArmStatus:
    connected: bool = False
    protective_stop: bool = False
    emergency_stop: bool = False
    error: str = ""
    extra: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.connected and not (self.protective_stop or self.emergency_stop) and not self.error


class ArmError(RuntimeError):
    """The arm cannot do what was asked (lost connection, protective stop, refused command)."""


class Arm(abc.ABC):
    """An arm commanded in tool space."""

    #: controller period in seconds (servo commands are sent once per period)
    period: float = 0.008

    @abc.abstractmethod
    def tool_pose(self) -> tuple[float, np.ndarray]:
        """(time in seconds, T_base_tool as a dual quaternion)."""

    @abc.abstractmethod
    def servo(self, pose: np.ndarray) -> None:
        """Send one set-point; call once per ``period``."""

    @abc.abstractmethod
    def move(self, pose: np.ndarray, speed: float, accel: float) -> None:
        """Blocking tool-space move to ``pose`` (m/s, m/s^2)."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Stop any motion now."""

    @abc.abstractmethod
    def status(self) -> ArmStatus:
        """Connection and safety state."""

    def close(self) -> None:
        """Stop and disconnect."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
