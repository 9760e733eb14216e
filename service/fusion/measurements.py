"""What a live stream's :class:`~dqpose.fusion.Tracker` takes in: :class:`Measurement` s, one
object a row, or :class:`Rows`, arrays of many (a server's parsed request), and the one into the
other with the errors of rows whose shapes or types are wrong."""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Optional, Sequence

import numpy as np

from dqpose import dq
from dqpose.errors import WorldError
from dqpose.fusion.results import DOF
from dqpose.fusion.validation import checked_covariances, checked_seconds, shape_of


@dataclass(frozen=True)
class Measurement:
    """One pose of ``body`` from ``source`` stamped ``time`` (the proto's ``Measurement``):
    ``pose`` ``T_frame_body`` ``(8,)``, ``covariance`` ``(6, 6)``, or (``None``) isotropic
    ``I / weight`` (no weight: 1)."""
    source: str
    body: str
    time: float
    pose: np.ndarray
    covariance: Optional[np.ndarray] = None
    weight: Optional[float] = None


def arrays_of(measurements: Sequence[Measurement]):
    """:class:`Measurement` s as the arrays :meth:`Tracker.ingest` takes (poses, covariances,
    times; a bad row's left as zeros and identity) and ``{k: WorldError}`` about
    ``measurements[k]`` for the rows whose shapes or types are wrong."""
    n = len(measurements)
    poses, covs, times = np.zeros((n, 8)), np.empty((n, DOF, DOF)), np.zeros(n)
    covs[:] = np.eye(DOF)
    errors: dict[int, WorldError] = {}
    for k, m in enumerate(measurements):
        try:
            if not isinstance(m, Measurement):
                raise WorldError(k, "", f"expected a Measurement, got {type(m).__name__}")
            try:
                times[k] = checked_seconds(m.time, "time")
            except ValueError as e:
                raise WorldError.of(e, k) from None
            if shape_of(m.pose) != (8,):
                raise WorldError(k, "pose", f"expected shape (8,), got {shape_of(m.pose)}")
            try:
                poses[k] = m.pose
            except (TypeError, ValueError):
                raise WorldError(k, "pose", f"expected numbers, got "
                                            f"{type(m.pose).__name__}") from None
            if m.covariance is not None and shape_of(m.covariance) != (DOF, DOF):
                raise WorldError(k, "covariance", f"expected shape (6, 6), "
                                                  f"got {shape_of(m.covariance)}")
            try:
                covs[k] = checked_covariances(None if m.covariance is None else [m.covariance],
                                       None if m.weight is None else [m.weight], 1)[0]
            except ValueError as e:
                raise WorldError.of(e, k, {"covariances": "covariance",
                                           "weights": "weight"}) from None
        except WorldError as e:
            errors[k] = e
            poses[k] = dq.identity()
            covs[k] = np.eye(DOF)
            times[k] = 0.0
    return poses, covs, times, errors


class Rows(NamedTuple):
    """Measurements as arrays: ``bodies`` and ``sources`` one name each, ``times`` ``(n,)``
    (stamps), ``poses`` ``(n, 8)`` (``T_frame_body``), ``covariances`` ``(n, 6, 6)`` (None:
    identity)."""
    bodies: Sequence[str]
    sources: Sequence[str]
    times: np.ndarray
    poses: np.ndarray
    covariances: Optional[np.ndarray] = None


def rows_of(measurements: Sequence[Measurement]) -> tuple[Rows, dict[int, WorldError]]:
    """:func:`arrays_of` as :class:`Rows` (a refused row's body "")."""
    measurements = list(measurements)
    poses, covs, times, bad = arrays_of(measurements)
    bodies = ["" if k in bad else m.body for k, m in enumerate(measurements)]
    sources = ["" if k in bad else m.source for k, m in enumerate(measurements)]
    return Rows(bodies, sources, times, poses, covs), bad
