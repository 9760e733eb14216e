"""A measurement's source: its frames and latency (:class:`Source`), checked into a table by name,
and the measurements brought into the world frame, ``T_world_frame · Z · T_flange_body``, their
covariances transported exactly (the convention of :mod:`dqpose.fusion`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Optional

import numpy as np

from dqpose import dq, lie
from dqpose.errors import FieldError, rename
from dqpose.fusion.results import DOF
from dqpose.fusion.validation import checked_covariances, checked_pose, checked_seconds, shape_of
from dqpose.names import name_problem, quoted


@dataclass(frozen=True)
class Source:
    """A source's frames: ``extrinsic`` is ``T_world_frame`` and ``body_offset`` the body in the
    frame the source measures (``T_flange_body`` for an arm); ``None`` is the identity.

    ``latency`` (seconds): a measurement stamped ``t`` was taken at ``t - latency`` (used when
    :func:`fuse` is given times). ``latency_sigma``: ``None`` takes the latency as exact; a
    positive value makes it a prior ``N(latency, latency_sigma²)`` and estimates it from the data
    jointly with the motion (reported in :attr:`Fused.latencies`).

    ``extrinsic_covariance`` ``(6, 6)`` (rotation first): the extrinsic's own uncertainty, a right
    perturbation of ``T_world_frame`` (the true extrinsic is ``extrinsic · Exp(ε)``,
    ``ε ~ N(0, Σ)``), e.g. a hand-eye calibration's covariance. Every measurement of the source
    shares the one ``ε``; :mod:`dqpose.fusion.extrinsics` estimates it jointly with the body.
    ``None``: the extrinsic is exact.

    ``parent``: the frame ``extrinsic`` is given in (``T_parent_frame``): "" the world; a body's
    or a static's name in a :class:`dqpose.world.World`, which composes the parent's pose at each
    measurement's taken time when it fits (:func:`fuse` has no parents: it refuses one)."""
    name: str
    extrinsic: Optional[np.ndarray] = None
    body_offset: Optional[np.ndarray] = None
    latency: float = 0.0
    latency_sigma: Optional[float] = None
    extrinsic_covariance: Optional[np.ndarray] = None
    parent: str = ""

    @property
    def exact(self) -> bool:
        """Its extrinsic and latency are taken as exact (no ``extrinsic_covariance``, no
        ``latency_sigma``): nothing of it is estimated, and no two bodies it sees share an
        error through it."""
        return self.extrinsic_covariance is None and self.latency_sigma is None


# What a latency and its prior's standard deviation may be (seconds): a prior of 5e-324 s has an
# information (sigma^-2) no double holds.
_MAX_LATENCY = 1e6
_LATENCY_SIGMA = (1e-9, 1e6)


def _latency(s: Source) -> tuple[float, Optional[float]]:
    latency = checked_seconds(s.latency, "latency")
    if abs(latency) > _MAX_LATENCY:
        raise FieldError("latency", f"{latency:.6g} s is beyond +-{_MAX_LATENCY:g} s")
    if s.latency_sigma is None:
        return latency, None
    sigma = checked_seconds(s.latency_sigma, "latency_sigma", "positive")
    lo, hi = _LATENCY_SIGMA
    if not lo <= sigma <= hi:
        raise FieldError("latency_sigma", f"{sigma:.6g} s is outside [{lo:g}, {hi:g}] s")
    return latency, sigma


def pose_covariance(covariance, name: str) -> Optional[np.ndarray]:
    """A fixed pose's covariance (an extrinsic's, a static's; None: exact) by the measurements'
    rule (symmetric, variances within bounds, positive definite), symmetrised; a FieldError
    naming ``name``."""
    if covariance is None:
        return None
    shape = shape_of(covariance)
    if shape != (DOF, DOF):
        raise FieldError(name, f"expected shape (6, 6), got {shape}")
    try:
        return checked_covariances([covariance], None, 1)[0]
    except ValueError as e:
        raise rename(e, {"covariances": name}) from None


def source_table(sources: Optional[Iterable[Source]]) -> dict[str, Source]:
    table: dict[str, Source] = {}
    for k, s in enumerate(sources or ()):
        try:
            table[s.name] = _source(s, table)
        except FieldError as e:
            raise e.within("sources", k) from None
    return table


def _source(s: Source, table: dict[str, Source]) -> Source:
    """``s`` checked (its fields' errors named by field; one of ``table``'s names: refused), its
    poses normalised."""
    if not isinstance(s, Source):
        raise FieldError("", f"expected a Source, got {type(s).__name__}")
    problem = name_problem(s.name)
    if problem is not None:
        raise FieldError("name", problem)
    if s.name in table:
        raise FieldError("", f"source {quoted(s.name)} given twice")
    problem = name_problem(s.parent, empty=True)
    if problem is not None:
        raise FieldError("parent", problem)
    return Source(s.name,
                  None if s.extrinsic is None else checked_pose(s.extrinsic, "extrinsic"),
                  None if s.body_offset is None else checked_pose(s.body_offset, "body_offset"),
                  *_latency(s), pose_covariance(s.extrinsic_covariance, "extrinsic_covariance"),
                  s.parent)


def to_world(Z: np.ndarray, S: np.ndarray, names: tuple[str, ...],
              table: dict[str, Source]) -> tuple[np.ndarray, np.ndarray]:
    """``T_world_frame · Z · T_flange_body`` and the exactly transported covariances."""
    framed = {name: src for name, src in table.items()
              if src.body_offset is not None or src.extrinsic is not None}
    rows: dict[str, list[int]] = {}
    if framed:
        for i, s in enumerate(names):       # one pass: each framed source's measurements
            if s in framed:
                rows.setdefault(s, []).append(i)
    if rows:
        Z, S = Z.copy(), S.copy()
    for name, idx in rows.items():
        src = framed[name]
        if src.body_offset is not None:
            Z[idx] = dq.mul(Z[idx], src.body_offset)
            S[idx] = lie.cov_compose(S[idx], src.body_offset, None)
        if src.extrinsic is not None:
            Z[idx] = dq.mul(src.extrinsic, Z[idx])
    return dq.normalize(Z), S
