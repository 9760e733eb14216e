"""Pose fusion: n measurements of one rigid body in, one estimate with an honest covariance out.

Conventions (stated once for the package; :mod:`dqpose.lie` holds the tangent-space tools):

* A covariance is 6×6, row-major, **rotation first** (``[ωx ωy ωz vx vy vz]``, radians then
  metres), for a **right (body-frame) perturbation**: the true pose is ``T · Exp(ξ)``,
  ``ξ ~ N(0, Σ)``, with ``Exp`` the SE(3) exponential. This is GTSAM's ``Pose3`` convention
  (``retract`` = compose with ``Expmap``), so a user can check us against GTSAM, and the tests do.
* A measurement is ``T_frame_body`` in its source's frame; each source has an extrinsic
  ``T_world_frame`` (identity when not given) and, for an arm, the body's offset in the flange
  frame ``T_flange_body``; the fused pose is ``T_world_body``. A measurement enters the fusion as
  ``T_world_frame · T_frame_body · T_flange_body``; the constant extrinsic on the left leaves its
  covariance as it is, the constant offset on the right maps it exactly to
  ``Ad(O⁻¹) Σ Ad(O⁻¹)ᵀ`` (:func:`dqpose.lie.cov_compose`). A source's ``extrinsic_covariance``
  (the extrinsic itself uncertain, ``T_world_frame · Exp(ε)``) makes its measurements share
  ``ε``: they are then fitted jointly with it (:mod:`~dqpose.fusion.extrinsics`).
* The residual of measurement ``Z_i`` at the estimate ``X`` is ``r_i = Log(X⁻¹ Z_i)``; its
  negative is GTSAM's ``PriorFactorPose3`` error ``Log(Z_i⁻¹ X)``, so both minimise the same cost
  ``Σ r_iᵀ Σ_i⁻¹ r_i``. Its exact Jacobian for ``X · Exp(δ)`` is ``-Jl⁻¹(r_i) = -Jr⁻¹(-r_i)``.
* Scalar weights are the isotropic special case: ``Σ_i = I / w_i``.

The maximum-likelihood estimate is found by Gauss–Newton on SE(3) from the DIB mean
(:func:`dqpose.dq.dib`) until a step is shorter than ``tol``, in the C core (``fusion.c``); its
covariance is the inverse of the information ``Σ Jᵢᵀ Σᵢ⁻¹ Jᵢ`` at the optimum (GTSAM's marginal).
The robust mode starts from the largest pairwise-consistent group and gates every measurement on
its leave-one-out normalised innovation squared (NIS: the measurement against the fit of the other
inliers, ``χ²`` with 6 degrees of freedom for a consistent source); the answer is always the plain
maximum-likelihood fit of the inliers, so a rejected measurement never moves it. Over time
(``times``) the body moves with a twist (:mod:`~dqpose.fusion.motion`), optionally a random walk
(:mod:`~dqpose.fusion.process_noise`).

The parts, each a module: :mod:`~dqpose.fusion.results` (what a fusion returns),
:mod:`~dqpose.fusion.chi2` (quantiles), :mod:`~dqpose.fusion.validation` (input checks),
:mod:`~dqpose.fusion.sources` (frames and latencies), :mod:`~dqpose.fusion.extrinsics`
(uncertain extrinsics, jointly), :mod:`~dqpose.fusion.static` (the fit of one
instant), :mod:`~dqpose.fusion.robust` (the gate), :mod:`~dqpose.fusion.consistency` (per-source
verdicts), :mod:`~dqpose.fusion.motion` (the constant-twist model over time: time alignment),
:mod:`~dqpose.fusion.process_noise` (acceleration as process noise),
:mod:`~dqpose.fusion.alignment` (fusion over time), :mod:`~dqpose.fusion.api` (:func:`fuse`),
:mod:`~dqpose.fusion.tracker` and :mod:`~dqpose.fusion.store` (live streams: :class:`Tracker`).
"""
from dqpose.fusion.alignment import DEFAULT_MAX_EXTRAPOLATION
from dqpose.fusion.api import fuse
from dqpose.fusion.chi2 import DEFAULT_PROBABILITY, chi2_quantile
from dqpose.fusion.results import (
    DOF,
    Dropped,
    Fused,
    Latency,
    Rejection,
    SourceStats,
    Status,
    Verdict,
)
from dqpose.fusion.sources import Source
from dqpose.fusion.tracker import Measurement, Rows, Tracker, Window

__all__ = ["DOF", "DEFAULT_PROBABILITY", "DEFAULT_MAX_EXTRAPOLATION", "Status", "Verdict", "Source",
           "Rejection", "SourceStats", "Fused", "fuse", "chi2_quantile", "Dropped", "Latency",
           "Measurement", "Rows", "Window", "Tracker"]
