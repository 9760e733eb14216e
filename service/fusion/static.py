"""The fit of one instant: the maximum-likelihood pose of n measurements and its covariance (the
inverse information at the optimum, GTSAM's marginal) by Gauss–Newton on SE(3) from the DIB mean,
in the C core (service/csrc/fusion.c; tests/fusion_reference.py in NumPy), each measurement's
leave-one-out NIS with it; robust or not.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from dqpose import _dqcore as _c
from dqpose.fusion.consistency import codes, source_stats
from dqpose.fusion.extrinsics import Extrinsics, motion_fit_ext, static_model
from dqpose.fusion.results import DOF, Fused, Status, read_only
from dqpose.fusion.robust import consensus, nis_gate, rejections


@dataclass(frozen=True)
class _Fit:
    status: Status
    mean: np.ndarray
    covariance: np.ndarray  # inverse information at the optimum
    r: np.ndarray           # residuals Log(mean⁻¹ Z_i), all measurements
    distances: np.ndarray   # sqrt(r_iᵀ Σ_i⁻¹ r_i), all measurements
    nis: np.ndarray         # leave-one-out NIS against the fit of the other inliers
    tested: np.ndarray
    chi2: float             # the inliers' squared distances summed (the cost at the optimum)
    iterations: int


def _fit(Z: np.ndarray, S: np.ndarray, inlier: np.ndarray, tol: float, max_iter: int,
         ext: Optional[Extrinsics] = None) -> _Fit:
    """ML fit of the measurements ``inlier`` selects, evaluated at every measurement, with the
    leave-one-out NIS of each: measurement j against the fit of the other inliers (one
    Gauss-Newton step from the optimum; an outlier against all inliers; untested without
    another inlier). With uncertain extrinsics (``ext``) the joint fit of
    :mod:`dqpose.fusion.extrinsics`, started from the C fit."""
    mean, P, r, d, nis, tested, status, iterations, chi2 = _c.fuse(Z, S, inlier, tol, max_iter)
    if ext is None:
        return _Fit(Status(int(status)), mean, P, r, d, nis, tested, float(chi2),
                    int(iterations))
    m = motion_fit_ext(Z, S, static_model(Z.shape[0]), ext, inlier, mean, np.zeros(DOF),
                        np.zeros(0), tol, max_iter)
    assert m.nis is not None and m.tested is not None     # the joint fit computes them
    return _Fit(m.status, m.mean, m.P[:DOF, :DOF], m.r, np.sqrt(m.cost), m.nis, m.tested,
                m.chi2, int(iterations) + m.iterations)


def _robust(Z, S, gate2, tol, max_iter, ext=None):
    # the C fit computes each measurement's leave-one-out NIS with the fit itself
    return nis_gate(consensus(Z, S, gate2), np.ones(Z.shape[0], dtype=bool),
                 lambda inlier: _fit(Z, S, inlier, tol, max_iter, ext),
                 lambda fit, inlier: (fit.nis, fit.tested), gate2)


def fuse_static(Z, S, names, robust, probability, gate2, tol, max_iter,
                 ext: Optional[Extrinsics] = None) -> Fused:
    """The fit of one instant: the C core's, robust or not; jointly with the uncertain
    extrinsics ``ext`` when there are any."""
    n = Z.shape[0]
    if robust and n > 1:
        fit, nis, tested, inlier, gate_status = _robust(Z, S, gate2, tol, max_iter, ext)
    else:
        inlier = np.ones(n, dtype=bool)
        fit = _fit(Z, S, inlier, tol, max_iter, ext)
        nis, tested = fit.nis, fit.tested
        gate_status = None
    rejected = rejections(names, nis, ~inlier, gate2, probability)
    k = int(np.count_nonzero(inlier))
    return Fused(
        status=gate_status if gate_status is not None else fit.status,
        mean=read_only(fit.mean),
        covariance=read_only(fit.covariance),
        residuals=read_only(fit.r),
        distances=read_only(fit.distances),
        nis=read_only(nis),
        tested=read_only(tested),
        inliers=read_only(np.flatnonzero(inlier)),
        rejected=rejected,
        chi2=fit.chi2,
        dof=DOF * (k - 1),
        iterations=fit.iterations,
        sources=source_stats(*codes(names), nis, tested, inlier, probability),
    )
