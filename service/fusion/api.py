""":func:`fuse`, the entry point: every argument checked (a ``ValueError`` naming it), the
measurements brought into the world frame by their sources' frames, then the fit of one instant
(:mod:`dqpose.fusion.static`) or, with times, over time (:mod:`dqpose.fusion.alignment`); and the
same for rows a :class:`~dqpose.fusion.Tracker` checked when they came in, with its options
checked once.
"""
from __future__ import annotations

from typing import Iterable, NamedTuple, Optional, Sequence

import numpy as np

from dqpose import dq
from dqpose.errors import FieldError
from dqpose.fusion.alignment import (
    DEFAULT_MAX_EXTRAPOLATION,
    Start,
    fuse_in_time,
    time_setup,
)
from dqpose.fusion.chi2 import DEFAULT_PROBABILITY, chi2_quantile
from dqpose.fusion.extrinsics import Part, joint_fit, no_extrinsics, uncertain_extrinsics
from dqpose.fusion.results import DOF, Fused
from dqpose.fusion.sources import Source, source_table, to_world
from dqpose.fusion.static import fuse_static
from dqpose.fusion.validation import checked_covariances, checked_names, checked_poses, finite


def fuse(poses, covariances=None, *, weights=None, names: Optional[Sequence[str]] = None,
         sources: Optional[Iterable[Source]] = None, robust: bool = False,
         probability: float = DEFAULT_PROBABILITY, tol: float = 1e-12, max_iter: int = 100,
         times=None, time: Optional[float] = None, max_skew: Optional[float] = None,
         max_extrapolation: Optional[float] = DEFAULT_MAX_EXTRAPOLATION, twist_covariance=None,
         acceleration_psd=None) -> Fused:
    """Fuse ``poses`` ``(n, 8)`` (``T_frame_body`` each) with ``covariances`` ``(n, 6, 6)`` (or
    scalar ``weights`` ``(n,)``, covariance ``I / w``; neither: identity) into ``T_world_body``.

    ``names[i]`` is the source of measurement i; a source listed in ``sources`` has its frames
    applied (others are in the world frame already). ``robust`` rejects measurements whose
    leave-one-out NIS exceeds the χ² quantile ``probability`` (6 dof); ``probability`` also sets
    the per-source consistency interval. Bad input is a ``ValueError`` naming the argument and
    index.

    ``times`` ``(n,)`` (seconds, the sources' stamps) turns on time alignment: the result is the
    pose at ``time`` (default: the newest time a measurement was taken, stamp minus latency) under
    a constant-twist motion model estimated with it; a measurement taken more than ``max_skew``
    from ``time`` is dropped (:attr:`Fused.dropped`); a ``time`` more than ``max_extrapolation``
    outside the measurements' span is refused (``None``: unbounded). ``twist_covariance`` is an
    optional zero-mean prior on the body twist, needed when the measurements are all from one
    instant and ``time`` is another. ``acceleration_psd`` ``(6, 6)`` (rotation first, rad²/s³
    and m²/s³) lets the twist drift as a random walk, so that a body that accelerates is not
    claimed to be known better than the constant-twist model can know it
    (:mod:`dqpose.fusion.process_noise`);
    ``None`` or zeros: the twist is constant over the window. Measurements all taken at one
    instant and fused at that instant give the static fit exactly (the same C core, bit for
    bit); then the twist keeps its prior and each estimated latency its prior, as one instant
    shows neither. Without ``times`` none of this applies and latencies are ignored.
    """
    Z = checked_poses(poses)
    n = Z.shape[0]
    S = checked_covariances(covariances, weights, n)
    names = checked_names(names, n)
    table = source_table(sources)
    for k, src in enumerate(table.values()):
        if src.parent:      # the parent's pose at each measurement's time is a world's fit
            raise FieldError("sources", "only a world resolves a parent", k, ".parent")
    try:
        probability = float(probability)
    except (TypeError, ValueError):
        probability = float("nan")
    if not 0.0 < probability < 1.0:
        raise FieldError("probability", f"must be within (0, 1), got {probability!r}")
    tol = dq.as_tol(tol)
    max_iter = dq.as_iter(max_iter)
    Z, S = to_world(Z, S, names, table)
    gate2 = chi2_quantile(probability, DOF)
    if times is not None:
        return fuse_in_time(Z, S, names, table, finite(times, "times", (), n), time, max_skew,
                             max_extrapolation, twist_covariance, acceleration_psd, robust,
                             probability, gate2, tol, max_iter)
    for key, value in (("time", time), ("max_skew", max_skew),
                       ("twist_covariance", twist_covariance),
                       ("acceleration_psd", acceleration_psd)):
        if value is not None:
            raise FieldError(key, "needs the measurements' times (times=...)")

    return fuse_static(Z, S, names, robust, probability, gate2, tol, max_iter,
                        uncertain_extrinsics(names, table))


class Checked(NamedTuple):
    """:func:`fuse`'s options as its checks leave them, for a caller that fuses many times
    with the same options (:class:`Tracker`)."""
    table: dict
    robust: bool
    probability: float
    gate2: float
    tol: float
    max_iter: int
    max_skew: Optional[float]
    max_extrapolation: Optional[float]
    twist_covariance: Optional[np.ndarray]
    acceleration_psd: Optional[np.ndarray]


def fuse_world_rows(Z, S, names, times, time, o: Checked, nis: bool = True,
                     joint: bool = True) -> Fused:
    """:func:`fuse` with times of rows already checked by its rules (finite stamps, unit rigid
    poses, symmetric positive definite covariances symmetrised, names as strings) and brought
    into the world frame (``to_world(dq.normalize(Z), S, names, o.table)``, as a
    :class:`~dqpose.fusion.Tracker` keeps them), with checked options: the same result, bit for
    bit, without checking them again (without ``nis``, the leave-one-out NIS left out where the
    answer does not need them; without ``joint``, where a joint fit of several bodies starts:
    ``fuse_in_time``)."""
    return fuse_in_time(Z, S, names, o.table, times, time, o.max_skew, o.max_extrapolation,
                         o.twist_covariance, o.acceleration_psd, o.robust, o.probability,
                         o.gate2, o.tol, o.max_iter, nis, joint)


def fuse_static_rows(Z, S, names, o: Checked) -> Fused:
    """:func:`fuse` without times (one instant: no twist, times ignored) of rows checked and in
    the world frame as for :func:`fuse_world_rows`: a body that does not move."""
    return fuse_static(Z, S, names, o.robust, o.probability, o.gate2, o.tol, o.max_iter,
                        uncertain_extrinsics(names, o.table))


def fuse_joint_rows(rows, starts: Sequence, time, o: Checked):
    """Several bodies' rows ``(poses, covariances, names, times)`` (checked and in the world
    frame as for :func:`fuse_world_rows`) fitted together, with one error per uncertain
    extrinsic and one latency per source whose latency is estimated
    (:func:`dqpose.fusion.extrinsics.joint_fit`), each body started from ``starts``: its own
    fit (a :class:`Fused`) or a :class:`~dqpose.fusion.alignment.Start`, keeping its inliers:
    the poses and the joint covariance of their right perturbations ``(6k, 6k)``."""
    parts, names_all, begun = [], [], []
    for (Z, S, names, times), st in zip(rows, starts):
        if isinstance(st, Fused):
            st = Start.of(st, time_setup(Z, names, o.table, times,
                                      time if time is not None else st.time, o.max_skew,
                                      o.max_extrapolation, o.twist_covariance,
                                      o.acceleration_psd))
        begun.append((Z, S, st))
        names_all.extend(names)
    ext = uncertain_extrinsics(names_all, o.table)
    latencies = list(dict.fromkeys(s for _, _, st in begun for s in st.setup.estimated))
    if ext is None and not latencies:
        raise FieldError("bodies", "no uncertain extrinsic or estimated latency to fit them "
                         "jointly over")
    if ext is None:
        ext = no_extrinsics(len(names_all))
    start = 0
    for Z, S, st in begun:
        n = Z.shape[0]
        shared = np.array([latencies.index(s) for s in st.setup.estimated], dtype=np.intp)
        parts.append(Part(Z, S, st.setup.model, st.inlier, ext.slot[start:start + n], st.mean,
                           st.V, st.ell, shared))
        start += n
    fit = joint_fit(parts, ext, o.tol, o.max_iter)
    idx = np.concatenate([np.arange(off, off + DOF) for off in fit.offsets])
    return fit.X, fit.P[np.ix_(idx, idx)]
