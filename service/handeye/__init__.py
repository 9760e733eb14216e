"""Hand-eye calibration: robot and camera poses in, the camera's mount with an honest covariance
out.

Conventions (the rest of dqpose's, :mod:`dqpose.dq` and :mod:`dqpose.lie`):

* ``base_flange`` are the robot's ``T_base_flange`` ``(n, 8)``; ``camera_target`` the detector's
  ``T_camera_target`` ``(n, 8)``; sample i is the pair of row i of each.
* **eye_in_hand** (camera on the flange): ``x = T_flange_camera``, ``z = T_base_target``, and every
  sample satisfies ``base_flange_i · x · camera_target_i = z``.
  **eye_to_hand** (camera fixed, target on the flange): ``x = T_base_camera``,
  ``z = T_flange_target``, and ``base_flange_i⁻¹ · x · camera_target_i = z``. Eye-to-hand is solved
  as eye-in-hand on the inverted flange poses ``A_i = base_flange_i⁻¹``; everything below is
  written for ``A_i · X · C_i = Z`` (``C_i = camera_target_i``), the robot-world-hand-eye form on
  absolute poses.
* Covariances are 6×6, rotation first ``[ωx ωy ωz vx vy vz]``, of a right (body-frame)
  perturbation ``T · Exp(ξ)`` with the SE(3) exponential: GTSAM's ``Pose3`` convention, the one
  of :mod:`dqpose.fusion`. A noise covariance given for the poses uses it too (robot: the
  perturbation of ``T_base_flange``; camera: of ``T_camera_target``).

The solution, in order:

1. **Closed form** (Daniilidis 1999, dual quaternions): motions between all pairs ``i < j``
   (not only consecutive ones), ``A_j⁻¹A_i · X = X · C_j C_i⁻¹``; each pair's dual quaternions put
   in one hemisphere (scalar parts ≥ 0, the short screw both sides); pairs that rotate less than
   ``closed_form.MIN_PAIR_ANGLE`` or nearly half a turn (sign ill-defined) left out, and samples
   whose pairs
   are not screw-congruent (rotation angle and pitch of the two motions must agree) left out of
   it; the 6 m × 8 system solved by SVD, then re-solved with Huber weights on each pair's
   residual (robust averaging). ``Z`` is then the DIB mean (:func:`dqpose.dq.dib`) of the
   per-sample estimates ``A_i X C_i``.
2. **Maximum likelihood** on ``(X, Z)``: Gauss–Newton on SE(3)×SE(3) with right perturbations
   and exact Jacobians (:mod:`dqpose.lie`) of the residuals ``r_i = Log(Z⁻¹ A_i X C_i)``. Noise on
   both the robot and the camera poses enters through each residual's covariance
   ``Σ_r,i = Jr⁻¹(r_i) (Ad(K_i⁻¹) Σ_A,i Ad(K_i⁻¹)ᵀ + Σ_C,i) Jr⁻ᵀ``, ``K_i = X C_i``
   (the errors-in-variables problem with the true poses eliminated, to first order), re-evaluated
   at each iterate. The noise covariances are the caller's when given (``noise_model == "given"``),
   else **estimated from the residuals** (``"estimated"``, :class:`~dqpose.handeye.noise.Noise`):
   three isotropic
   variance components, camera rotation, translation (camera and robot alike) and robot rotation
   (which reaches the residual's translation through the lever arm ``X C_i``), by REML Fisher
   scoring at every iterate, the 12 fitted degrees of freedom taken out by leverage. The
   covariance of ``(X, Z)`` is the inverse of the information ``Σ Jᵢᵀ Σ_r,i⁻¹ Jᵢ`` at the
   optimum; ``covariance_x``/``covariance_z`` are its marginals. With the noise estimated, the
   uncertainty of the estimate is propagated into them (Kenward–Roger,
   :meth:`~dqpose.handeye.noise.Noise.kenward_roger`): from 10 poses the bare ``H(θ̂)⁻¹`` had mean
   NEES 6.7–9.3; with
   it 5.6–6.8 over 200 seeded trials on every row of tests/bench/bench_handeye.py (5.7–6.3 at
   20 poses).
3. **Outliers**: every sample is gated on its NIS at probability ``gate._GATE``: the inliers'
   standardised residual ``r_iᵀ (Σ_r,i − J_i P J_iᵀ)⁻¹ r_i`` (the leave-one-out NIS to first
   order), the others' against the prediction ``Σ_r,i + J_i P J_iᵀ``; against χ²₆ with the noise
   given, with it estimated against the studentised laws (:mod:`~dqpose.handeye.gate`). The
   gate starts from a fit on the consensus of minimal sets (:mod:`~dqpose.handeye.consensus`:
   least median of squares over hypotheses from three samples each and the closed form, so that
   outliers screw congruence lets through do not anchor it), with the noise estimated screened
   once more at robust scales of the rotation and the translation residuals (from the 60 % of
   the samples that fit best, so that an outlier does not hide by inflating the estimate), and
   re-fits until the set settles.
   ``robust`` leaves the outliers out (``rejected``, each with a reason: a marker flip when the
   rotation is off and the board's position is not); otherwise they stay in and a warning names
   them.
4. **After solving**: leave-one-out (how far X moves when each sample is left out, to first
   order: ``P J_iᵀ S_i⁻¹ r_i``), the closed form's distance from the answer in its own
   covariance, and :func:`next_best_pose`.
5. **Corner level** (``corners`` given): maximum likelihood on the reprojection of the board's
   corners through ``C_i = X⁻¹ A_i⁻¹ Z`` (:func:`~dqpose.handeye.corners.corner_fit`), from the
   pose-level answer, with
   an optional focal-length scale and a correction of each robot pose under the robot's noise,
   given or estimated (taken as exact, 0.02° / 0.1 mm of robot noise made the covariance claim
   ~20× too much; modelled, mean NEES 5.3–6.3). The corner noise is estimated per view: among
   rendered views of one scene it ranges 0.02–0.1 px, and one σ for all had the covariance
   of X claim too much end to end (mean NEES 9.6 over 50 trials; per view 7.6 over 200). The
   rest of that 7.6 was the detector's: OpenCV's ChArUco corners shared an error within each
   view, which independent corner noise cannot describe; drivers/camera.py now refines them
   off the markers, and end to end the mean NEES is 5.5–5.7 (three seeds of 200 trials).

Data checks (:func:`check` and :func:`calibrate`): malformed input is a
:class:`~dqpose.errors.FieldError` naming the argument and index; unusable data an
:class:`~dqpose.errors.Infeasible` naming the reason and the samples (fewer than 3 distinct
poses, no rotation between samples, rotation axes all parallel, poses that do not correspond,
millimetres given as metres, the data fitting another reading far better: setup swapped or a pose
convention inverted); anything doubtful but solvable a warning naming the samples (duplicates,
stale poses, small or nearly parallel rotations, samples not screw-congruent, outliers).

Two readings fit (nearly) as well as the right one, so the residuals cannot refuse them, and
answering them as given would be silently wrong (:mod:`~dqpose.handeye.readings`):

* **Both poses inverted** (``T_flange_base`` and ``T_target_camera``) fits exactly as well as
  the truth, X and Z exchanged (``F⁻¹ Z C⁻¹ = X``). Plausibility tells: a flange-mounted part
  within ``readings._MAX_MOUNT`` of the flange, a fixed one ``readings._MIN_FIXED`` off the base,
  and the target in
  front of the camera (``z > 0`` in ``T_camera_target``; inverted, the camera's position in the
  board's frame, whose sign depends on the board's convention). When the mount is implausible as
  given and plausible inverted and the depths agree with the inverted reading, the answer is the
  inverted reading's, with a warning; when the depths do not tell, ``Infeasible`` naming both.
* **The camera's translations at another scale** (a wrong board size,
  :mod:`~dqpose.handeye.scale`):
  the data are re-solved with the camera's translations (and at corner level the board's points)
  scaled by the best-fitting scale, whose uncertainty enters the covariance (at corner level the
  board's scale is refined with the corners), with a warning naming the scale; only when the
  likelihood ratio against no scale error says so, and re-solved until the scale found on the
  rescaled data is 1 (the joint optimum of the scale, the inliers and the noise).

Healthy scenes (960 runs over tests/_handeye.py's grid) are never refused.

The package, one stage a module: :mod:`~dqpose.handeye.setups` (the two setups and their
equation), :mod:`~dqpose.handeye.checks` (the data checks), :mod:`~dqpose.handeye.closed_form`,
:mod:`~dqpose.handeye.noise` (the residual covariances, REML, Kenward–Roger),
:mod:`~dqpose.handeye.likelihood` (Gauss–Newton on X and Z),
:mod:`~dqpose.handeye.consensus` (where the fit starts), :mod:`~dqpose.handeye.outliers` (the
χ² gate, leave-one-out), :mod:`~dqpose.handeye.readings` (the readings that fit as well),
:mod:`~dqpose.handeye.scale` (the camera's scale),
:mod:`~dqpose.handeye.corners` (the corner level), :mod:`~dqpose.handeye.next_best` and
:mod:`~dqpose.handeye.calibrate`, which runs them in order; :mod:`~dqpose.handeye.result` holds
what it returns.
"""
from dqpose.handeye.calibrate import calibrate
from dqpose.handeye.checks import check
from dqpose.handeye.next_best import next_best_pose
from dqpose.handeye.result import Calibration, Rejection
from dqpose.handeye.setups import EYE_IN_HAND, EYE_TO_HAND, SETUPS, flange_for, view_at

__all__ = ["SETUPS", "EYE_IN_HAND", "EYE_TO_HAND", "Calibration", "Rejection", "calibrate",
           "check", "flange_for", "next_best_pose", "view_at"]
